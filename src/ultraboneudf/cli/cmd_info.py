"""``ultraboneudf info``: what a bug report needs — versions, devices, optional extras, data found."""

from __future__ import annotations

import argparse
import importlib.metadata
import json
import os
import platform
import sys
from pathlib import Path

from .._version import __version__

EXTRAS = {  # distribution → what it enables
    "pymeshlab": "--method poisson (extra 'poisson')",
    "open3d": "--method poisson with poisson.backend=open3d",
    "onnxruntime": "sweep2points --segment MODEL.onnx (extra 'onnx')",
}
CORE = ("torch", "numpy", "scipy", "trimesh", "rich", "pillow", "pynrrd")


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("info", help="versions, devices, optional extras and shared data found "
                                           "(for bug reports)")
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    p.set_defaults(func=run)


def _version(name: str) -> str | None:
    try:
        return importlib.metadata.version(name)
    except importlib.metadata.PackageNotFoundError:
        return None


def _shared_data() -> dict[str, str | None]:
    """The shared data folders the tests and benchmarks look for, and whether they exist."""
    root = Path(__file__).resolve().parents[4] / "shared" / "data"
    bones = Path(os.environ.get("ULTRABONEUDF_BONES", root / "bones"))
    found = {}
    for name, path in (("bones", bones), ("ultrabones100k_sample", root / "ultrabones100k_sample"),
                       ("plus", root / "plus")):
        found[name] = str(path) if path.is_dir() else None
    return found


def report() -> dict:
    """The report as a dict (``info --json`` prints it)."""
    import torch

    cuda = torch.cuda.is_available()
    return {
        "ultraboneudf": __version__,
        "python": sys.version.split()[0],
        "platform": platform.platform(),
        "cpu_threads": torch.get_num_threads(),
        "packages": {name: _version(name) for name in CORE},
        "torch_cuda_build": torch.version.cuda,
        "cuda_available": cuda,
        "gpus": [torch.cuda.get_device_name(i) for i in range(torch.cuda.device_count())] if cuda else [],
        "extras": {name: _version(name) for name in EXTRAS},
        "shared_data": _shared_data(),
    }


def run(args: argparse.Namespace) -> int:
    info = report()
    if args.json:
        print(json.dumps(info, indent=2))
        return 0
    print(f"ultraboneudf {info['ultraboneudf']} on Python {info['python']} ({info['platform']})")
    print("packages: " + ", ".join(f"{k} {v or 'missing'}" for k, v in info["packages"].items()))
    gpus = ", ".join(info["gpus"]) or "none"
    print(f"torch: CUDA build {info['torch_cuda_build'] or 'none (CPU build)'}; CUDA available: "
          f"{'yes' if info['cuda_available'] else 'no'} (GPUs: {gpus}); {info['cpu_threads']} CPU threads")
    for name, use in EXTRAS.items():
        version = info["extras"][name]
        print(f"extra {name}: {version if version else 'not installed'} — {use}")
    for name, path in info["shared_data"].items():
        print(f"shared data {name}: {path or 'not found'}")
    return 0
