"""``ultraboneudf config``: the configuration a run would use, every field with its documentation."""

from __future__ import annotations

import argparse
import json
import re
import textwrap
from dataclasses import fields
from pathlib import Path
from typing import Any

from ..config import DEFAULT_PRESET, PRESETS, Config, field_docs
from ..methods import NAMES


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("config", help="print the resolved configuration of a preset and method, each "
                                      "field with its meaning and unit",
                       description="The configuration `reconstruct` would use with the same --preset, "
                                   "--method and --set: one line per field, `section.key = value`, "
                                   "then what it means (lengths without _mm are in unit space).")
    p.add_argument("--preset", default=DEFAULT_PRESET, choices=list(PRESETS))
    p.add_argument("--method", default="ultraboneudf", choices=sorted(NAMES))
    p.add_argument("--set", dest="assignments", action="append", default=[], metavar="KEY=VALUE")
    p.add_argument("--changed", action="store_true",
                   help="only the fields that differ from the dataclass defaults")
    p.add_argument("--json", action="store_true", help="the resolved values as JSON (as in the sidecar)")
    p.add_argument("--update-docs", type=Path, metavar="FILE",
                   help="rewrite the generated tables of a Markdown page (docs/methods.md) from the "
                        "dataclasses and the methods' defaults")
    p.set_defaults(func=run)


def lines(cfg: Config, changed: bool = False) -> list[str]:
    """``section.key = value`` and its wrapped documentation, for every field of ``cfg``."""
    base = Config()
    out = []
    for section in fields(cfg):
        obj, ref = getattr(cfg, section.name), getattr(base, section.name)
        docs = field_docs(type(obj))
        for f in fields(obj):
            value = getattr(obj, f.name)
            if changed and value == getattr(ref, f.name):
                continue
            out.append(f"{section.name}.{f.name} = {json.dumps(value) if not isinstance(value, str) else value}")
            if docs[f.name]:
                out.extend(textwrap.wrap(docs[f.name], 96, initial_indent="    ", subsequent_indent="    "))
    return out


# ---------------------------------------------------------------------------------- docs tables

BLOCK = re.compile(r"(<!-- config (?P<spec>[^>]*?) -->\n)(?P<body>.*?)(<!-- end config -->)", re.S)
"""A generated table: ``<!-- config KEY=VALUE ... -->`` … ``<!-- end config -->``."""


def _value(value: Any) -> str:
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, (tuple, list)):
        return ",".join(str(v) for v in value)
    return str(value)


def _markdown(doc: str) -> str:
    """A docstring as table-cell Markdown: reST literals and roles as code, no bare ``|``."""
    doc = re.sub(r":\w+:`~?([^`]+)`", r"`\1`", doc)
    return re.sub(r"``([^`]+)``", r"`\1`", doc).replace("|", "\\|")


def _flat(cfg: Config) -> dict[str, Any]:
    return {f"{s.name}.{f.name}": getattr(getattr(cfg, s.name), f.name)
            for s in fields(cfg) for f in fields(getattr(cfg, s.name))}


def _docs() -> dict[str, str]:
    cfg = Config()
    return {f"{s.name}.{name}": _markdown(doc)
            for s in fields(cfg) for name, doc in field_docs(type(getattr(cfg, s.name))).items()}


def table(spec: str) -> str:
    """The Markdown table a block's ``spec`` asks for, one row per field (``--set`` spelling, value,
    the field's docstring):

    - ``method=M``: every field the method's ``configure`` changes on the ``official`` preset
      (``official value → M's``) and every field of the sections in ``sections=a,b``;
    - ``preset=P base=B``: every field preset ``P`` sets differently from preset ``B``;
    - ``sections=a,b`` alone: every field of those sections; ``keys=a.x,b.y``: those fields."""
    from ..pipeline import configure

    args = dict(item.split("=", 1) for item in spec.split())
    docs = _docs()
    base_name = args.get("base", "official")
    base = _flat(configure(base_name, "ultraboneudf"))
    if "method" in args:
        target = _flat(configure("official", args["method"]))
        head = f"`official` → `{args['method']}`"
    elif "preset" in args:
        target = _flat(configure(args["preset"], "ultraboneudf"))
        head = f"`{base_name}` → `{args['preset']}`"
    else:
        target, head = base, "default"
    keys = [k for k in target if target[k] != base[k]] if ("method" in args or "preset" in args) else []
    sections = [s for s in args.get("sections", "").split(",") if s]
    keys += [k for k in target if k.split(".")[0] in sections and k not in keys]
    keys += [k for k in args.get("keys", "").split(",") if k and k not in keys]
    rows = ["| `--set` | " + head + " | meaning |", "| --- | --- | --- |"]
    for key in keys:
        before, after = _value(base[key]), _value(target[key])
        shown = " → ".join(f"`{v}`" if v else "empty" for v in ((before, after) if before != after else (after,)))
        rows.append(f"| `{key}={after}` | {shown} | {docs[key]} |")
    return "\n".join(rows) + "\n"


def update_docs(text: str) -> str:
    """``text`` with every generated block rewritten from the dataclasses."""
    return BLOCK.sub(lambda m: m.group(1) + table(m.group("spec")) + m.group(4), text)


def run(args: argparse.Namespace) -> int:
    if args.update_docs is not None:
        from ..errors import InputError
        from ..io import atomic_write_bytes, check_input

        path = check_input(args.update_docs, "file")
        try:
            text = path.read_text(encoding="utf-8")
        except UnicodeDecodeError:
            raise InputError(f"{path}: not a text file (cannot decode as UTF-8)") from None
        if not BLOCK.search(text):
            raise InputError(f"{path}: no generated table (<!-- config … --> … <!-- end config -->) to rewrite")
        new = update_docs(text)
        if new != text:  # the page's own generated tables, rewritten whole or not at all
            atomic_write_bytes(path, new.encode("utf-8"))
        state = "rewritten" if new != text else "up to date"
        print(f"config: {path}: {len(BLOCK.findall(text))} tables {state}")
        return 0
    from ..pipeline import configure

    cfg = configure(args.preset, args.method, assignments=args.assignments)
    if args.json:
        print(json.dumps(cfg.to_dict(), indent=2))
        return 0
    print(f"# preset {args.preset}, method {args.method}" + (" (fields changed from the defaults)"
                                                             if args.changed else ""))
    print("\n".join(lines(cfg, args.changed)))
    return 0
