"""Data flow one way (docs/DESIGN.md): input -> points -> field -> mesh -> metrics, with the command
line and the benchmarks on top. No module imports from its own layer's neighbours or from a layer
above; the check reads every module's imports (also those inside functions, and the submodules a
package's lazy ``_WHERE`` map names) without running anything."""

from __future__ import annotations

import ast
from pathlib import Path
from typing import Iterator, Sequence

import ultraboneudf

PACKAGE = Path(ultraboneudf.__file__).resolve().parent

LAYERS: list[set[str]] = [
    {"_version", "_lazy", "errors"},          # what everything may use
    {"progress", "devices", "config"},
    {"io", "geometry"},                        # files in and out; geometry on point sets
    {"checkpoints", "pictures"},
    {"sweep"},                                 # input: tracked sweeps -> points
    {"synth"},                                 # simulated input with known truth
    {"preprocess"},                            # points -> training samples
    {"fields"},
    {"training"},
    {"methods", "extraction"},                 # fitted field; field -> mesh
    {"evaluation"},                            # mesh -> metrics, pictures
    {"registration"},
    {"pipeline"},
    {"__init__"},                              # the public API
    {"bench"},
    {"cli"},
]
"""Top-level modules and packages of ``ultraboneudf``, lowest first. A module may import its own
package and the layers below; two names in one layer may not import each other."""


def _package_parts(path: Path, root: Path) -> list[str]:
    """The dotted package ``path`` belongs to (itself for an ``__init__.py``), as parts."""
    parts = [root.name, *path.relative_to(root).with_suffix("").parts]
    return parts[:-1]


def _is_module(root: Path, parts: Sequence[str]) -> bool:
    where = root.parent.joinpath(*parts)
    return where.with_suffix(".py").is_file() or (where / "__init__.py").is_file()


def _lazy_maps(tree: ast.Module) -> Iterator[tuple[int, list[str]]]:
    """The submodule names of each module-level dict handed to ``lazy_getattr``."""
    handed = {call.args[1].id for call in ast.walk(tree)
              if isinstance(call, ast.Call) and getattr(call.func, "id", None) == "lazy_getattr"
              and len(call.args) > 1 and isinstance(call.args[1], ast.Name)}
    for node in tree.body:
        if (isinstance(node, ast.Assign) and isinstance(node.value, ast.Dict)
                and any(isinstance(t, ast.Name) and t.id in handed for t in node.targets)):
            yield node.lineno, [v.value for v in node.value.values if isinstance(v, ast.Constant)]


def imported_modules(path: Path, root: Path) -> Iterator[tuple[int, str]]:
    """``(line, dotted module)`` for every import in ``path`` of a module of the package at ``root``."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    package = _package_parts(path, root)
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.split(".")[0] == root.name:
                    yield node.lineno, alias.name
        elif isinstance(node, ast.ImportFrom):
            base = package[: len(package) - node.level + 1] if node.level else []
            parts = base + (node.module.split(".") if node.module else [])
            if not parts or parts[0] != root.name:
                continue
            for alias in node.names:  # `from pkg import sub` imports the submodule
                yield node.lineno, ".".join(parts + [alias.name] if _is_module(root, parts + [alias.name])
                                            else parts)
    for line, names in _lazy_maps(tree):
        for name in names:
            yield line, ".".join(package + [name])


def _top(dotted: str) -> str:
    parts = dotted.split(".")
    return parts[1] if len(parts) > 1 else "__init__"


def violations(root: Path, layers: Sequence[set[str]]) -> list[str]:
    """Every import in the package at ``root`` that climbs: to a higher layer, or across to another
    name of the same layer; and every top-level name no layer holds."""
    rank = {name: i for i, layer in enumerate(layers) for name in layer}
    out = []
    for path in sorted(root.rglob("*.py")):
        rel = path.relative_to(root.parent).as_posix()
        own = _top(".".join([root.name, *path.relative_to(root).with_suffix("").parts]))
        if own not in rank:
            out.append(f"{rel}: {own} is in no layer")
            continue
        for line, target in imported_modules(path, root):
            other = _top(target)
            if other == own:
                continue
            if other not in rank:
                out.append(f"{rel}:{line}: imports {target}, whose {other} is in no layer")
            elif rank[other] >= rank[own]:
                out.append(f"{rel}:{line}: {own} (layer {rank[own]}) imports {target} (layer {rank[other]})")
    return out


def test_no_import_climbs_the_layers():
    assert violations(PACKAGE, LAYERS) == []


def test_every_layer_name_exists_at_most_once():
    names = [n for layer in LAYERS for n in layer]
    assert len(names) == len(set(names))


# the checker itself, on a small package written for it


def _write(root: Path, files: dict[str, str]) -> Path:
    for rel, text in files.items():
        p = root / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(text)
    return root / "pkg"


SYNTHETIC = {
    "pkg/__init__.py": "from ._lazy import lazy_getattr\n_WHERE = {'Top': 'top'}\n"
                       "__getattr__ = lazy_getattr(__name__, _WHERE, globals())\n",
    "pkg/_lazy.py": "",
    "pkg/low/__init__.py": "from . import a\n",
    "pkg/low/a.py": "import os\n\n\ndef f():\n    from ..top import x\n    return x\n",
    "pkg/mid.py": "import pkg.low.a\nfrom pkg import top\nfrom .low import a\n",
    "pkg/side.py": "from .mid import y\n",
    "pkg/top.py": "from .mid import y\nfrom . import low\nfrom pkg.low.a import f\n",
}
SYNTHETIC_LAYERS = [{"_lazy"}, {"low"}, {"mid", "side"}, {"top"}, {"__init__"}]


def test_checker_finds_imports_that_climb(tmp_path):
    found = violations(_write(tmp_path, SYNTHETIC), SYNTHETIC_LAYERS)
    assert found == [
        "pkg/low/a.py:5: low (layer 1) imports pkg.top (layer 3)",       # inside a function, relative
        "pkg/mid.py:2: mid (layer 2) imports pkg.top (layer 3)",         # a submodule by from-import
        "pkg/side.py:1: side (layer 2) imports pkg.mid (layer 2)",       # across one layer
    ]


def test_checker_reads_lazy_maps_and_unplaced_names(tmp_path):
    root = _write(tmp_path, SYNTHETIC)
    layers = [{"_lazy", "__init__"}, {"low"}, {"mid", "side"}, {"top"}]
    assert "pkg/__init__.py:2: __init__ (layer 0) imports pkg.top (layer 3)" in violations(root, layers)
    (root / "extra.py").write_text("")
    assert "pkg/extra.py: extra is in no layer" in violations(root, SYNTHETIC_LAYERS)
