"""The ``ultraboneudf`` command. It only composes the library; each sub-command lives in
``cli/cmd_<name>.py`` and exposes ``register(subparsers)``, which adds its parser and sets
``func`` to a callable ``(args) -> int``.

Exit codes: 0 success; 2 bad input or usage (one line on stderr, no traceback); 1 anything else.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
import traceback
import warnings

from .._version import __version__
from ..errors import FitWarning, InputError, SweepWarning

COMMANDS = ["reconstruct", "demo", "evaluate", "render", "register", "stats", "sweep2points", "simulate", "bench",
            "config", "info"]


class _Parser(argparse.ArgumentParser):
    """A usage error is one line (``ultraboneudf CMD: error: …``) and exit 2, like a bad input;
    ``--help`` still shows the whole usage."""

    def error(self, message: str):  # type: ignore[override]
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="ultraboneudf",
        description="Bone surface meshes (mm) from tracked ultrasound point clouds with neural "
                    "unsigned distance fields (UltraBoneUDF) and DualMesh-UDF extraction.")
    parser.add_argument("--version", action="version", version=f"ultraboneudf {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    for name in COMMANDS:
        try:
            module = importlib.import_module(f".cmd_{name}", __name__)
        except ModuleNotFoundError as exc:
            if exc.name != f"{__name__}.cmd_{name}":
                raise
            continue  # a command whose module is not part of this build
        module.register(sub)
    return parser


class _InputWarnings:
    """Collects tolerated input defects (:class:`~ultraboneudf.errors.SweepWarning`) during a
    command and prints them, one line each, when it succeeds; a failed command prints only its
    one error line. :class:`~ultraboneudf.errors.FitWarning` is dropped: the commands print the same
    sentences with command-line advice."""

    def __init__(self, command: str) -> None:
        self.command, self.category, self.lines = command, SweepWarning, []
        self.default = warnings.showwarning

    def show(self, message, category, filename, lineno, file=None, line=None) -> None:
        if issubclass(category, self.category):
            self.lines.append(f"ultraboneudf {self.command}: warning: {message}")
        elif not issubclass(category, FitWarning):
            self.default(message, category, filename, lineno, file, line)

    def flush(self) -> None:
        for text in dict.fromkeys(self.lines):
            print(text, file=sys.stderr)


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help(sys.stderr)
        return 2
    collected = _InputWarnings(args.command)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("always", collected.category)
            warnings.simplefilter("always", FitWarning)
            warnings.showwarning = collected.show
            code = int(args.func(args) or 0)
        collected.flush()
        return code
    except InputError as exc:
        print(f"ultraboneudf {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("ultraboneudf: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # the reader went away (`| head`): stop quietly, as other tools do
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141
    except Exception:  # a bug: show it, exit 1
        traceback.print_exc()
        return 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
