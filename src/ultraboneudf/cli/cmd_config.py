"""``ultraboneudf config``: the configuration a run would use, every field with its documentation."""

from __future__ import annotations

import argparse
import json
import textwrap
from dataclasses import fields

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


def run(args: argparse.Namespace) -> int:
    from ..pipeline import configure

    cfg, _ = configure(args.preset, args.method, None, None, args.assignments)
    if args.json:
        print(json.dumps(cfg.to_dict(), indent=2))
        return 0
    print(f"# preset {args.preset}, method {args.method}" + (" (fields changed from the defaults)"
                                                             if args.changed else ""))
    print("\n".join(lines(cfg, args.changed)))
    return 0
