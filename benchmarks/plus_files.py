"""Every sequence file of PlusLibData (github.com/PlusToolkit/PlusLibData; ``--plus DIR``, by default
../shared/data/plus) through the command line, as a user runs it, and the pictures of docs/sweep.md's
PLUS section.

    python benchmarks/plus_files.py [--plus DIR] [--out DIR] [--figures docs/img]

For each file: ``sweep2points`` (with its calibration, where PlusLibData has one) — exit code and
the one-line outcome; for the bone and spine sweeps also ``reconstruct`` with the default preset (timing,
points, faces, data_fit) and a picture of frames with the detected bone (red) and the mesh's cut
through each frame (green), beside the mesh coloured by its distance to the points. Where ``--plus``
also holds PlusLibData's bone-enhancer output (``TestImages/outputPlusTransverseProcessEnhancerTest.igs.mha``),
it is run and reconstructed with ``--segment probability``. Wall time about 3 minutes on the shared
2-core machine.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
PLUS = ROOT.parent / "shared" / "data" / "plus"
NWIRE_CFG = "PlusDeviceSet_NwirePhantomFreehand_vtkVolumeReconstructorTest2.xml"
ENHANCED = "outputPlusTransverseProcessEnhancerTest.igs.mha"
RUNS = [  # file, its calibration in PlusLibData (None: none exists), extra arguments
    ("BoneUltrasound_L14.igs.mha", "BoneUltrasound_L14_config.xml", []),
    ("SpinePhantomFreehand.igs.mha", "PlusDeviceSet_SpinePhantomFreehandReconstructionOnly.xml", []),
    ("NwirePhantomFreehand.igs.mha", NWIRE_CFG, []),
    ("NwirePhantomFreehand.igs.nrrd", NWIRE_CFG, []),
    ("NwirePhantomFreehandCropped.igs.mha", NWIRE_CFG, []),
    ("NrrdSample.igs.nrrd", None, []),
    ("Prostate10_video.igs.mhd", None, []),
    # the bone enhancer's output for BoneUltrasound_L14 (TestImages/ of PlusLibData; not in
    # ../shared): its frames are a bone map, so the classical detector is replaced
    (ENHANCED, "BoneUltrasound_L14_config.xml", ["--segment", "probability"]),
]
RECONSTRUCT = {"BoneUltrasound_L14.igs.mha": "plus_bone", "SpinePhantomFreehand.igs.mha": "plus_spine",
               ENHANCED: "plus_enhanced"}
FIGURES = ("BoneUltrasound_L14.igs.mha", "SpinePhantomFreehand.igs.mha")


def cli(*args: object) -> tuple[int, str, str, float]:
    t = time.perf_counter()
    res = subprocess.run([sys.executable, "-m", "ultraboneudf.cli", *map(str, args)],
                         capture_output=True, text=True)
    return res.returncode, res.stdout, res.stderr, time.perf_counter() - t


def last_line(text: str) -> str:
    lines = [line for line in text.strip().splitlines() if line.strip()]
    return lines[-1] if lines else ""


def overlay_sheet(sweep_path: Path, cal: Path, out: Path, n: int = 8, crop=None) -> None:
    """``n`` frames with the classical detector's bone surface in red (the docs' overlay picture)."""
    from ultraboneudf.pictures import save_picture
    from ultraboneudf.sweep import read_sweep
    from ultraboneudf.sweep.bone import classical_bone_masks
    from ultraboneudf.sweep.figures import contact_sheet, mark_dilation, overlay

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        sweep = read_sweep(sweep_path, **({} if cal is None else {"calibration": cal}))
    masks, _ = classical_bone_masks(sweep)
    frames = np.linspace(0, sweep.n_frames - 1, n).round().astype(int)
    tiles = []
    for i in frames:
        im = overlay(sweep.images[i], masks[i], dilate=mark_dilation(crop[2] if crop else sweep.width, 225))
        tiles.append(im.crop((crop[0], crop[1], crop[0] + crop[2], crop[1] + crop[3])) if crop else im)
    save_picture(contact_sheet(tiles, [sweep.frame_names[i] for i in frames], columns=4, tile_width=225),
             out, greys=64)


def figure(sweep_path: Path, cal: Path | None, mesh_path: Path, out: Path, crop=None) -> None:
    from PIL import Image

    from ultraboneudf.evaluation.render import render_distance_image
    from ultraboneudf.io import load_mesh
    from ultraboneudf.pictures import save_picture
    from ultraboneudf.sweep import read_sweep, sweep_to_points
    from ultraboneudf.sweep.bone import classical_bone_masks
    from ultraboneudf.sweep.figures import frames_with_mesh

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        sweep = read_sweep(sweep_path, **({} if cal is None else {"calibration": cal}))
    masks, _ = classical_bone_masks(sweep)
    points = sweep_to_points(sweep.with_masks(masks), segment="masks").points
    mesh = load_mesh(mesh_path)
    frames = np.linspace(0, sweep.n_frames - 1, 6).round().astype(int)
    sheet = frames_with_mesh(sweep, masks, mesh, frames, columns=3, tile_width=300, crop=crop)
    render = render_distance_image(mesh, points, views=("front", "right", "top"), tile_height=260, vmax=3.0,
                                   title=f"{sweep_path.name}: mesh, distance to the points")
    scale = sheet.width / render.width
    render = render.resize((sheet.width, round(render.height * scale)), Image.BILINEAR)
    canvas = Image.new("RGB", (sheet.width, render.height + sheet.height), (0, 0, 0))
    canvas.paste(render, (0, 0))
    canvas.paste(sheet, (0, render.height))
    save_picture(canvas, out, greys=64)


def _shown(arg: object, args: argparse.Namespace) -> str:
    """A command-line argument as the docs show it: the PlusLibData file or output by its name."""
    text = str(arg)
    for folder in (args.plus, args.out):
        text = text.replace(str(folder) + "/", "")
    return text


def main() -> int:
    from ultraboneudf.io import sidecar_path

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--plus", type=Path, default=PLUS)
    ap.add_argument("--out", type=Path, default=Path("bench_out/plus_runs"))
    ap.add_argument("--figures", type=Path, default=None, help="write the docs pictures here")
    args = ap.parse_args()
    if not args.plus.is_dir():
        print(f"{args.plus}: not present", file=sys.stderr)
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    results = []
    for name, cfg, extra in RUNS:
        if not (args.plus / name).exists():
            print(json.dumps({"file": name, "outcome": "not present, skipped"}), flush=True)
            continue
        flags = (["--calibration", args.plus / cfg] if cfg else []) + extra
        cmd = ["sweep2points", args.plus / name, *flags, "-o", args.out / f"{name}.ply", "--quiet"]
        code, out, err, dt = cli(*cmd)
        row = {"file": name, "command": "ultraboneudf " + " ".join(
            _shown(c, args) for c in cmd),
            "exit": code, "seconds": round(dt, 1), "outcome": last_line(out if code == 0 else err)}
        results.append(row)
        print(json.dumps(row, ensure_ascii=False), flush=True)
        if name in RECONSTRUCT and code == 0:
            mesh = args.out / f"{RECONSTRUCT[name]}.ply"
            cmd = ["reconstruct", args.plus / name, *flags, "-o", mesh, "--quiet"]
            code, out, err, dt = cli(*cmd)
            side = json.loads(sidecar_path(mesh).read_text()) if code == 0 else {}
            rec = {"file": name, "command": "ultraboneudf " + " ".join(
                _shown(c, args) for c in cmd),
                "exit": code, "seconds": round(dt, 1), "stderr": err.strip(),
                "timings": side.get("timings"), "counts": side.get("counts"),
                "data_fit": side.get("data_fit"),
                "sweep": {k: side["input"]["sweep"][k] for k in ("pose_chain", "pixel_spacing_mm",
                                                                 "shear_deg", "points")} if side else None}
            results.append(rec)
            print(json.dumps(rec, ensure_ascii=False), flush=True)
            if code == 0 and args.figures is not None and name in FIGURES:
                figure(args.plus / name, args.plus / cfg, mesh, args.figures / f"{RECONSTRUCT[name]}_result.png",
                       crop=(170, 0, 480, 616))
                overlay_sheet(args.plus / name, args.plus / cfg,
                              args.figures / f"{RECONSTRUCT[name]}_overlays.png", crop=(170, 0, 480, 616))
    (args.out / "results.json").write_text(json.dumps(results, indent=1, ensure_ascii=False) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
