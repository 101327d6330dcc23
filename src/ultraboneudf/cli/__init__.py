"""The ``ultraboneudf`` command. It only composes the library; each sub-command lives in
``cli/cmd_<name>.py`` and exposes ``register(subparsers)``, which adds its parser and sets
``func`` to a callable ``(args) -> int``.

Exit codes, one rule for every command (docs/reliability.md):

- 0: done;
- 2: refused before any work — a bad input, option or output name, no room or no permission to
  write there (one line on stderr naming the file or option; nothing written);
- 1: failed after the work began — the disk filled up or a write failed (one line), the memory ran
  out (one line), or a bug (a traceback); the earlier output is kept and nothing new is left;
- 128 + N: stopped by signal N (130 Ctrl-C, 143 SIGTERM, 129 SIGHUP), one line; the earlier output
  is kept, or the new one is complete if the signal came while it was being put in place; no
  temporary file is left.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import os
import signal
import sys
import threading
import traceback
import warnings

from .._version import __version__
from ..errors import InputError, SweepWarning

COMMANDS = ["reconstruct", "demo", "evaluate", "render", "register", "stats", "sweep2points", "simulate", "bench",
            "config", "info"]


class Terminated(BaseException):
    """SIGTERM or SIGHUP arrived: raised where the program is, so that its clean-up runs."""

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = signum


def one_line(text: str) -> str:
    """``text`` with its control characters written as escapes: a newline in a file name cannot
    split a message."""
    return "".join(c if c.isprintable() or c == " " else repr(c)[1:-1] for c in str(text))


@contextlib.contextmanager
def _signals_raise():
    """While a command runs (main thread only): SIGTERM and SIGHUP raise :class:`Terminated`."""
    def terminate(signum, frame):
        raise Terminated(signum)

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    wanted = [s for s in (getattr(signal, "SIGTERM", None), getattr(signal, "SIGHUP", None)) if s is not None]
    before = {s: signal.getsignal(s) for s in wanted}
    for sig, handler in before.items():
        if handler is not signal.SIG_IGN:  # a signal ignored by whoever started us stays ignored
            signal.signal(sig, terminate)
    try:
        yield
    finally:
        for sig, handler in before.items():
            signal.signal(sig, signal.SIG_DFL if handler is None else handler)


def add_overwrite(p: argparse.ArgumentParser, what: str = "the output") -> None:
    """``--overwrite``: replace what stands at the output's name even if this package did not write
    it (an input is never replaced)."""
    p.add_argument("--overwrite", action="store_true",
                   help=f"replace {what} even where a file of that name was not written by ultraboneudf "
                        f"(by default only an unchanged earlier output is replaced; an input never is)")


class _Parser(argparse.ArgumentParser):
    """A usage error is one line (``ultraboneudf CMD: error: …``) and exit 2, like a bad input;
    ``--help`` still shows the whole usage."""

    def error(self, message: str):  # type: ignore[override]
        self.exit(2, f"{self.prog}: error: {one_line(message)} (see {self.prog} --help)\n")


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
    one error line."""

    def __init__(self, command: str) -> None:
        self.command, self.category, self.lines = command, SweepWarning, []
        self.default = warnings.showwarning

    def show(self, message, category, filename, lineno, file=None, line=None) -> None:
        if issubclass(category, self.category):
            self.lines.append(f"ultraboneudf {self.command}: warning: {message}")
        else:
            self.default(message, category, filename, lineno, file, line)

    def flush(self) -> None:
        for text in dict.fromkeys(self.lines):
            print(one_line(text), file=sys.stderr)


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help(sys.stderr)
        return 2
    from ..io.commit import WriteError

    collected = _InputWarnings(args.command)
    name = f"ultraboneudf {args.command}"
    try:
        with warnings.catch_warnings(), _signals_raise():
            warnings.simplefilter("always", collected.category)
            warnings.showwarning = collected.show
            code = int(args.func(args) or 0)
        collected.flush()
        return code
    except InputError as exc:
        print(f"{name}: error: {one_line(exc)}", file=sys.stderr)
        return 2
    except WriteError as exc:
        print(f"{name}: error: {one_line(exc.strerror or exc)}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"{name}: interrupted", file=sys.stderr)
        return 128 + signal.SIGINT
    except Terminated as exc:
        print(f"{name}: stopped by {signal.Signals(exc.signum).name}", file=sys.stderr)
        return 128 + exc.signum
    except MemoryError:
        print(f"{name}: error: out of memory; nothing written (give the run more memory, or thin the "
              f"input)", file=sys.stderr)
        return 1
    except BrokenPipeError:  # the reader went away (`| head`): stop quietly, as other tools do
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141
    except Exception:  # a bug: show it, exit 1
        traceback.print_exc()
        return 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
