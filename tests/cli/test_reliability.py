"""What every bad input, option, output, disk and signal gets, from the command line: each case is
run as a user runs it (a fresh process, in its own folder) and checked — the exit code, the one line
on stderr, and what the folder holds afterwards. docs/reliability.md is written from these cases and
the lines they printed, so the page cannot drift from the program:

    python tests/cli/test_reliability.py          # runs every case, rewrites docs/reliability.md

``test_the_page_lists_every_case_as_run`` fails when a case changed and the page was not rewritten.
"""

from __future__ import annotations

import os
import re
import shutil
import struct
import subprocess
import sys
import textwrap
import zlib
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
PAGE = ROOT / "docs" / "reliability.md"
FAST = ["--preset", "fast", "--iters", "100", "--set", "train.batch=500", "--set", "extract.max_depth=6",
        "--set", "model.hidden=32,32", "--quiet"]


@dataclass
class Case:
    """One command line and what it must get: ``code`` and a ``line`` fragment (one line on
    stderr), then ``after(folder)`` holds. ``setup(folder)`` makes the files it needs beside the
    shared inputs; ``hook=(n, action)`` stops it right after the n-th file operation of a commit
    (a signal, or ``ENOSPC``: the file system refuses that operation)."""

    id: str
    section: str
    what: str
    argv: list[str]
    line: str
    code: int = 2
    setup: Callable[[Path], None] | None = None
    after: Callable[[Path], None] | None = None
    hook: tuple[int, str] | None = None


@dataclass
class Row:
    """A row of the page checked by another test (library level, or too slow to run here)."""

    section: str
    what: str
    gets: str
    test: str


# ------------------------------------------------------------------------------------------------
# the shared inputs of every case's folder


def _inputs(folder: Path) -> None:
    import trimesh

    from ultraboneudf.sweep import Sweep, write_sweep
    from ultraboneudf.sweep.transforms import rigid_from_euler

    rng = np.random.default_rng(0)
    theta = rng.uniform(np.pi / 4, 3 * np.pi / 4, 2000)
    cloud = np.c_[20 * np.cos(theta), rng.uniform(0, 40, 2000), 20 * np.sin(theta)]
    np.savetxt(folder / "in.xyz", cloud)
    trimesh.creation.icosphere(subdivisions=3, radius=20).export(folder / "gt.ply")
    trimesh.creation.icosphere(subdivisions=3, radius=20.5).export(folder / "recon.ply")
    trimesh.creation.capsule(height=40, radius=10).export(folder / "capsule.ply")
    (folder / "results.csv").write_text("method,specimen,reconstruction,cd_mm,hd95_mm\n" + "".join(
        f"{m},s{i % 3},r{i},{1 + 0.1 * i + (m == 'B')},{2 + 0.1 * i}\n" for i in range(9) for m in "AB"))
    n = 10
    masks = np.zeros((n, 80, 64), dtype=bool)
    masks[:, 40, 8:56] = True
    poses = np.stack([rigid_from_euler([0, 0, 0.5 * i], [0, 0, 0]) for i in range(n)])
    write_sweep(Sweep(image_to_world=poses, spacing_mm=0.2, image_size=(64, 80),
                      images=(masks * 200 + 20).astype(np.uint8), masks=masks, pixel_offset=0.5), folder / "sweep")


def _write(name: str, text: str | bytes) -> Callable[[Path], None]:
    def setup(folder: Path) -> None:
        (folder / name).parent.mkdir(parents=True, exist_ok=True)
        (folder / name).write_bytes(text if isinstance(text, bytes) else text.encode())
    return setup


def _points(name: str, pts: np.ndarray) -> Callable[[Path], None]:
    return lambda folder: np.savetxt(folder / name, pts)


def _fifo(name: str) -> Callable[[Path], None]:
    return lambda folder: os.mkfifo(folder / name)


def _unchanged(name: str, text: str) -> Callable[[Path], None]:
    def after(folder: Path) -> None:
        assert (folder / name).read_text() == text, f"{name} changed"
        assert not (folder / (name + ".json")).exists()
    return after


def _absent(*names: str) -> Callable[[Path], None]:
    def after(folder: Path) -> None:
        for name in names:
            assert not os.path.lexists(folder / name), f"{name} was written"
    return after


def _untouched(folder: Path) -> None:
    """Nothing but the shared inputs and the case's own files: no output, no temporary."""
    extra = [p for p in folder.rglob("*") if p.name.startswith(".") or p.suffix in (".ubtmp", ".ubold")]
    assert not extra, extra


def _ply(name: str, *, faces_cut: int = 0, vertices_only: int = 0, nan: bool = False) -> Callable[[Path], None]:
    def setup(folder: Path) -> None:
        import trimesh

        mesh = trimesh.creation.icosphere(subdivisions=3, radius=20.5)
        if nan:
            v = mesh.vertices.copy()
            v[5] = np.nan
            trimesh.Trimesh(v, mesh.faces, process=False).export(folder / name)
            return
        lines = trimesh.exchange.ply.export_ply(mesh, encoding="ascii").decode().splitlines()
        if vertices_only:
            lines = lines[:lines.index("end_header") + 1 + vertices_only]
        elif faces_cut:
            lines = lines[:-faces_cut]
        (folder / name).write_text("\n".join(lines) + "\n")
    return setup


def _ply_header(n: int, fmt: str = "ascii 1.0") -> str:
    return f"ply\nformat {fmt}\nelement vertex {n}\nproperty float x\nproperty float y\nproperty float z\nend_header\n"


def _sparse_text(folder: Path) -> None:
    """20 GB of text that take no disk: 2,000 lines of points, then a hole."""
    with open(folder / "big.xyz", "w") as fh:
        fh.write("".join(f"{x:.4f} {2 * x:.4f} {x % 7:.4f}\n" for x in range(2000)))
    os.truncate(folder / "big.xyz", 20 * 10**9)


def _png_bomb(folder: Path) -> None:
    """Frame 3 of the sweep replaced by a PNG declaring 60000 × 60000 pixels in a few hundred bytes."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    frame = sorted((folder / "sweep" / "frames").iterdir())[3]
    frame.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", 60000, 60000, 8, 0, 0, 0, 0))
                      + chunk(b"IDAT", zlib.compress(b"\0" * 60001 * 4)) + chunk(b"IEND", b""))


def _checkpoint(run: str, cut: bool = False) -> Callable[[Path], None]:
    """A checkpoint of this package at ``o.ply.ckpt``, of the run ``run`` (or cut in half)."""
    def setup(folder: Path) -> None:
        from ultraboneudf import checkpoints

        path = folder / "o.ply.ckpt"
        checkpoints.save(checkpoints.Checkpoint(path, every=10, run=run).path, {"step": 10})
        if cut:
            data = path.read_bytes()
            path.write_bytes(data[: len(data) // 2])
    return setup


def _earlier_stats(folder: Path) -> None:
    """``report.md`` written by ``stats``, then edited by the user."""
    assert _run(["stats", "results.csv", "--baseline", "A", "-o", "report.md"], folder)[0] == 0
    with open(folder / "report.md", "a") as fh:
        fh.write("my notes\n")


def _manifest(uid: str) -> Callable[[Path], None]:
    def setup(folder: Path) -> None:
        (folder / "ds").mkdir()
        np.savez(folder / "ds" / "a.npz", points=np.loadtxt(folder / "in.xyz"))
        shutil.copy(folder / "gt.ply", folder / "ds" / "a_gt.ply")
        (folder / "ds" / "manifest.csv").write_text(f"id,specimen,input,gt\n{uid},s,a.npz,a_gt.ply\n")
    return setup


def _metaio_outside(folder: Path) -> None:
    frames = "".join(f"Seq_Frame{i:04d}_ImageToReferenceTransform = 0.2 0 0 0 0 0.2 0 0 0 0 1 {3 * i} 0 0 0 1\n"
                     for i in range(2))
    (folder / "s.mhd").write_text("ObjectType = Image\nNDims = 3\nDimSize = 4 4 2\nElementType = MET_UCHAR\n"
                                  + frames + "ElementDataFile = ../../etc/hostname\n")


def _masks(count: int, npy: bool = False) -> Callable[[Path], None]:
    def setup(folder: Path) -> None:
        if npy:
            np.save(folder / "masks.npy", np.zeros((count, 80, 64), dtype=bool))
            return
        (folder / "masks").mkdir()
        for f in sorted((folder / "sweep" / "masks").iterdir())[:count]:
            shutil.copy(f, folder / "masks" / ("m" + f.name))
    return setup


def _no_stray(folder: Path) -> None:
    left = [p.name for p in folder.iterdir() if p.suffix in (".ubtmp", ".ubold") or "commit" in p.name]
    assert not left, left


def _written(*names: str) -> Callable[[Path], None]:
    def after(folder: Path) -> None:
        for name in names:
            assert (folder / name).is_file(), f"{name} missing"
        _no_stray(folder)
    return after


def _cloud_ply(folder: Path) -> None:
    import trimesh

    trimesh.PointCloud(_cube).export(folder / "cloud.ply")


def _open_mesh(folder: Path) -> None:
    import trimesh

    mesh = trimesh.creation.icosphere()
    mesh.update_faces(np.arange(len(mesh.faces)) > 0)
    mesh.export(folder / "open.ply")


def _fifo_frame(folder: Path) -> None:
    frame = sorted((folder / "sweep" / "frames").iterdir())[2]
    frame.unlink()
    os.mkfifo(frame)


def _nothing_new(*names: str) -> Callable[[Path], None]:
    def after(folder: Path) -> None:
        _absent(*names)(folder)
        _no_stray(folder)
    return after


# ------------------------------------------------------------------------------------------------
# the cases

P, M, O, D, C, S, G = ("Point clouds", "Meshes given to render, evaluate and simulate", "Outputs",
                       "Paths from data files", "Options, configuration and checkpoints", "Sweeps",
                       "Signals and full disks")
R = ["reconstruct"]
STATS = ["stats", "results.csv", "--baseline", "A"]
_rng = np.random.default_rng(1)
_cube = _rng.random((300, 3)) * 30
_bad_line = "\n".join(f"{a} {b} {c}" for a, b, c in _cube[:6]) + "\n1 2 x\n"

CASES = [
    # point clouds
    Case("missing", P, "the file does not exist", [*R, "nothing.xyz", "-o", "o.ply", *FAST], "nothing.xyz: no such file"),
    Case("ext", P, "an unknown extension (`.las`)", [*R, "in.las", "-o", "o.ply", *FAST],
         "in.las: unknown point cloud extension '.las'", setup=_write("in.las", "1 2 3\n")),
    Case("line", P, "a line that is not numbers", [*R, "bad.xyz", "-o", "o.ply", *FAST], "bad.xyz: line 7:",
         setup=_write("bad.xyz", _bad_line)),
    Case("nan", P, "NaN in a coordinate", [*R, "nan.xyz", "-o", "o.ply", *FAST], "1 point(s) contain NaN or Inf",
         setup=_points("nan.xyz", np.where(np.arange(300)[:, None] == 10, np.nan, _cube))),
    Case("few", P, "fewer than 100 points", [*R, "few.xyz", "-o", "o.ply", *FAST], "only 50 points; at least 100",
         setup=_points("few.xyz", _cube[:50])),
    Case("columns", P, "points one per column (a 3 × N array)", [*R, "t.npy", "-o", "o.ply", *FAST],
         "one point per column; points go one per row (N×3): transpose the array",
         setup=lambda folder: np.save(folder / "t.npy", _cube.T)),
    Case("npz-names", P, "an `.npz` of several arrays, none named `points`", [*R, "two.npz", "-o", "o.ply", *FAST],
         "no array named 'points' (it holds a, b); save the points as points=…",
         setup=lambda folder: np.savez(folder / "two.npz", a=_cube, b=_cube)),
    Case("same", P, "all points identical", [*R, "same.xyz", "-o", "o.ply", *FAST], "all points are identical",
         setup=_points("same.xyz", np.ones((300, 3)))),
    Case("collinear", P, "all points on one line", [*R, "line.xyz", "-o", "o.ply", *FAST], "the points are collinear",
         setup=_points("line.xyz", np.linspace(0, 30, 300)[:, None] * [1, 2, 3])),
    Case("km", P, "a coordinate of 1e30", [*R, "far.xyz", "-o", "o.ply", *FAST], "beyond ±10⁶ mm",
         setup=_points("far.xyz", np.vstack([_cube, [[1e30, 0, 0]]]))),
    Case("metres", P, "a cloud in metres", [*R, "m.xyz", "-o", "o.ply", *FAST], "that looks like m, not mm",
         setup=_points("m.xyz", _cube / 1000)),
    Case("micrometres", P, "a cloud in micrometres", [*R, "um.xyz", "-o", "o.ply", *FAST],
         "that looks like micrometres, not mm", setup=_points("um.xyz", _cube * 1000)),
    Case("ply-short", P, "an ASCII PLY that ends before its declared vertices", [*R, "short.ply", "-o", "o.ply", *FAST],
         "the header declares 1,000 vertices but the file holds 100 (truncated?)",
         setup=_write("short.ply", _ply_header(1000) + "".join(f"{a} {b} {c}\n" for a, b, c in _cube[:100]))),
    Case("ply-binary-short", P, "a binary PLY shorter than its header declares", [*R, "short.ply", "-o", "o.ply", *FAST],
         "(truncated?)", setup=_write("short.ply", _ply_header(1000, "binary_little_endian 1.0").encode()
                                      + _cube[:100].astype("<f4").tobytes())),
    Case("ply-billion", P, "a PLY header declaring 10⁹ vertices", [*R, "bomb.ply", "-o", "o.ply", *FAST],
         "more than the limit of 500,000,000", setup=_write("bomb.ply", _ply_header(10**9, "binary_little_endian 1.0"))),
    Case("not-ply", P, "a `.ply` that is not a PLY file", [*R, "fake.ply", "-o", "o.ply", *FAST], "not a PLY file",
         setup=_write("fake.ply", "hello\n")),
    Case("huge-text", P, "a 20 GB text cloud (more than memory holds)", [*R, "big.xyz", "-o", "o.ply", *FAST],
         "GiB of memory", setup=_sparse_text, after=_absent("o.ply")),
    Case("fifo-cloud", P, "a named pipe (FIFO) as the input (would wait forever)", [*R, "pipe.xyz", "-o", "o.ply", *FAST],
         "pipe.xyz: is a named pipe (FIFO), not a regular file", setup=_fifo("pipe.xyz")),
    Case("newline", P, "a newline in the file name", [*R, "bad\nname.xyz", "-o", "o.ply", *FAST],
         "bad\\nname.xyz: no such file"),
    # meshes
    Case("nan-render", M, "`render` of a mesh with a NaN vertex", ["render", "nan.ply", "--gt", "gt.ply", "-o", "n.png"],
         "nan.ply: 1 vertices are NaN or infinite", setup=_ply("nan.ply", nan=True), after=_absent("n.png")),
    Case("nan-evaluate", M, "`evaluate` of a mesh with a NaN vertex",
         ["evaluate", "nan.ply", "--gt", "gt.ply", "--quiet"], "nan.ply: 1 vertices are NaN or infinite",
         setup=_ply("nan.ply", nan=True)),
    Case("faces-short", M, "`evaluate` of an ASCII PLY whose header promises more faces than it holds",
         ["evaluate", "short.ply", "--gt", "gt.ply", "--quiet"],
         "short.ply: the header declares 1,280 faces but the file holds 1,250 (truncated?)",
         setup=_ply("short.ply", faces_cut=30)),
    Case("vertices-short", M, "`evaluate` of an ASCII PLY cut inside its vertices",
         ["evaluate", "short.ply", "--gt", "gt.ply", "--quiet"], "the header declares 642 vertices but the file holds 49",
         setup=_ply("short.ply", vertices_only=49)),
    Case("fifo-mesh", M, "a named pipe as a mesh", ["render", "pipe.ply", "-o", "p.png"], "is a named pipe (FIFO)",
         setup=_fifo("pipe.ply")),
    Case("not-mesh", M, "a file that is not a mesh", ["evaluate", "junk.obj", "--gt", "gt.ply", "--quiet"],
         "junk.obj", setup=_write("junk.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n")),
    Case("pose-no-gt", M, "`render --gt-pose` without a ground truth to place",
         ["render", "recon.ply", "--gt-pose", "T.json", "-o", "r.png"], "--gt-pose places the ground truth and needs --gt",
         setup=_write("T.json", '{"transform": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}')),
    Case("pose-sheared", M, "`evaluate --gt-pose` with a matrix that is not rigid",
         ["evaluate", "recon.ply", "--gt", "gt.ply", "--gt-pose", "T.txt", "--quiet"], "T.txt",
         setup=_write("T.txt", "2 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n")),
    Case("open-mesh", M, "`simulate` of a mesh that is not closed", ["simulate", "open.ply", "-o", "sim", "--quiet"],
         "open.ply: the mesh is not closed", setup=_open_mesh, after=_absent("sim")),
    # outputs
    Case("is-input", O, "`-o` is the input file", [*R, "cloud.ply", "-o", "cloud.ply", *FAST],
         "cloud.ply: is the input; the input is never overwritten", setup=_cloud_ply),
    Case("input-overwrite", O, "an input, even with `--overwrite`",
         [*STATS, "-o", "results.csv", "--overwrite"], "results.csv: is the input", after=lambda f: None),
    Case("in-sweep", O, "`-o` inside the sweep folder being read (`sweep2points sweep -o sweep/poses.csv`)",
         ["sweep2points", "sweep", "-o", "sweep/poses.csv", "--quiet"], "sweep/poses.csv: inside the input folder sweep"),
    Case("user-mesh", O, "`-o` naming a mesh of the user's (no sidecar)", [*R, "in.xyz", "-o", "bone.ply", *FAST],
         "bone.ply: exists and is not an output of ultraboneudf (no sidecar bone.ply.json)",
         setup=_write("bone.ply", "mine"), after=_unchanged("bone.ply", "mine")),
    Case("user-sidecar", O, "a file of the user's at the sidecar's name (`knee.ply.json`)",
         [*R, "in.xyz", "-o", "knee.ply", *FAST], "knee.ply.json: exists and is not a sidecar of ultraboneudf",
         setup=_write("knee.ply.json", "{}"), after=_absent("knee.ply")),
    Case("user-cloud", O, "`sweep2points sweep -o pts.ply` over a user's `pts.ply`",
         ["sweep2points", "sweep", "-o", "pts.ply", "--quiet"], "pts.ply: exists and is not an output of ultraboneudf",
         setup=_write("pts.ply", "mine"), after=_unchanged("pts.ply", "mine")),
    Case("user-png", O, "`render recon.ply -o photo.png` over a user's picture", ["render", "recon.ply", "-o", "photo.png"],
         "photo.png: exists and is not an output of ultraboneudf", setup=_write("photo.png", "mine"),
         after=_unchanged("photo.png", "mine")),
    Case("user-json", O, "`evaluate … --json notes.json` over a user's notes",
         ["evaluate", "recon.ply", "--gt", "gt.ply", "--json", "notes.json", "--quiet"],
         "notes.json: exists and is not an output of ultraboneudf", setup=_write("notes.json", "mine"),
         after=_unchanged("notes.json", "mine")),
    Case("user-report", O, "`stats … -o report.md` over a user's report", [*STATS, "-o", "report.md"],
         "report.md: exists and is not an output of ultraboneudf", setup=_write("report.md", "mine"),
         after=_unchanged("report.md", "mine")),
    Case("edited-report", O, "an earlier output of ours the user has since edited", [*STATS, "-o", "report.md"],
         "report.md: changed since ultraboneudf wrote it", setup=_earlier_stats),
    Case("overwrite", O, "`--overwrite`: the user means it", [*STATS, "-o", "report.md", "--overwrite"], "", code=0,
         setup=_write("report.md", "mine"), after=_written("report.md", "report.md.json")),
    Case("user-demo", O, "`demo --out demo` where `demo/` holds a file of the user's", ["demo", "--out", "demo", *FAST],
         "demo: the folder holds files ultraboneudf did not write (e.g. demo_points.xyz)",
         setup=_write("demo/demo_points.xyz", "mine"), after=_unchanged("demo/demo_points.xyz", "mine")),
    Case("user-sim", O, "`simulate … -o sim` where `sim/` holds a file of the user's",
         ["simulate", "capsule.ply", "-o", "sim", "--quiet"], "sim: the folder holds files ultraboneudf did not write",
         setup=_write("sim/notes.txt", "mine"), after=_unchanged("sim/notes.txt", "mine")),
    Case("cwd", O, "a folder output that is the current folder (`simulate … -o .`)",
         ["simulate", "capsule.ply", "-o", ".", "--quiet", "--overwrite"], ".: is the current folder"),
    Case("user-ckpt", O, "a file of the user's at `OUT.ckpt` with `--checkpoint-every`",
         [*R, "in.xyz", "-o", "o.ply", "--checkpoint-every", "10", *FAST],
         "o.ply.ckpt: exists and is not a training checkpoint of ultraboneudf", setup=_write("o.ply.ckpt", "mine"),
         after=_unchanged("o.ply.ckpt", "mine")),
    Case("ckpt-folder", O, "`--checkpoint-every` where `OUT.ckpt` is a folder",
         [*R, "in.xyz", "-o", "o.ply", "--checkpoint-every", "10", *FAST], "o.ply.ckpt: is a folder",
         setup=lambda f: (f / "o.ply.ckpt").mkdir()),
    Case("long-name", O, "an output name of 254 characters (its sidecar's name would be 259)",
         [*R, "in.xyz", "-o", "b" * 250 + ".ply", *FAST], "is 259 bytes long, more than the 255"),
    Case("in-device", O, "an output inside a device (`-o /dev/null/x.ply`)", [*R, "in.xyz", "-o", "/dev/null/x.ply", *FAST],
         "cannot write into /dev/null (not a folder)"),
    Case("fifo-out", O, "a named pipe at the output's name", [*STATS, "-o", "pipe.md"], "pipe.md: is a named pipe",
         setup=_fifo("pipe.md")),
    # paths from data files
    Case("id-up", D, "`bench run` with a manifest id `../../x`",
         ["bench", "run", "--dataset", "ds/manifest.csv", "--out", "runs", "--method", "ultraboneudf"],
         "ds/manifest.csv: line 2: id '../../x' is not a plain name", setup=_manifest("../../x"), after=_absent("runs")),
    Case("id-abs", D, "`bench run` with a manifest id `/abs/x`",
         ["bench", "run", "--dataset", "ds/manifest.csv", "--out", "runs", "--method", "ultraboneudf"],
         "id '/abs/x' is not a plain name", setup=_manifest("/abs/x"), after=_absent("runs")),
    Case("metaio-outside", D, "a MetaIO header whose `ElementDataFile` is `../../etc/hostname`",
         ["sweep2points", "s.mhd", "-o", "o.ply", "--quiet"], "s.mhd: ElementDataFile = ../../etc/hostname lies outside",
         setup=_metaio_outside),
    # options, configuration, checkpoints
    Case("seed", C, "`--seed -1`", [*R, "in.xyz", "-o", "o.ply", "--seed", "-1"], "argument --seed: -1 is below 0"),
    Case("iters", C, "`--iters 0`", [*R, "in.xyz", "-o", "o.ply", "--iters", "0"], "argument --iters: 0 is below 1"),
    Case("depth", C, "`--set extract.max_depth=30`", [*R, "in.xyz", "-o", "o.ply", "--set", "extract.max_depth=30"],
         "extract.max_depth=30 (between 1 and 11)"),
    Case("lr", C, "`--set train.lr=-1`", [*R, "in.xyz", "-o", "o.ply", "--set", "train.lr=-1"],
         "train.lr=-1.0 (a learning rate in (0, 1])"),
    Case("gs-form", C, "`--set loss.gs_form=pairs`", [*R, "in.xyz", "-o", "o.ply", "--set", "loss.gs_form=pairs"],
         "unknown loss.gs_form 'pairs'; choose one of per_anchor, broadcast"),
    Case("unknown-key", C, "an unknown key", [*R, "in.xyz", "-o", "o.ply", "--set", "train.nope=1"],
         "unknown config key 'train.nope'"),
    Case("nan-set", C, "NaN for a number", [*R, "in.xyz", "-o", "o.ply", "--set", "loss.lambda_gs=nan"],
         "bad value 'nan' for config key 'loss.lambda_gs'"),
    Case("sim-frames", C, "`simulate --set n_frames=-3`", ["simulate", "capsule.ply", "-o", "s", "--set", "n_frames=-3"],
         "n_frames=-3 (none, or 2 to 100,000 frames)", after=_absent("s")),
    Case("sim-width", C, "`simulate --width-px 0`", ["simulate", "capsule.ply", "-o", "s", "--width-px", "0"],
         "width_px=0 (between 16 and 4096 pixels)"),
    Case("sim-fraction", C, "`simulate --set pred_gap_fraction=1.5`",
         ["simulate", "capsule.ply", "-o", "s", "--set", "pred_gap_fraction=1.5"],
         "pred_gap_fraction=1.5 (a fraction from 0 to under 1)"),
    Case("update-docs", C, "`config --update-docs missing.md`", ["config", "--update-docs", "missing.md"],
         "missing.md: no such file"),
    Case("ckpt-method", C, "`--checkpoint-every` with a method that cannot resume",
         [*R, "in.xyz", "-o", "o.ply", "--method", "funsr", "--checkpoint-every", "10"], "method funsr cannot checkpoint its training"),
    Case("ckpt-other", C, "`--resume` with a checkpoint of another run (input, preset, `--set`, method, seed)",
         [*R, "in.xyz", "-o", "o.ply", "--checkpoint-every", "10", "--resume", *FAST],
         "o.ply.ckpt: this checkpoint was made by another run", setup=_checkpoint("another run")),
    Case("ckpt-junk", C, "`--resume` with a file that is not a checkpoint",
         [*R, "in.xyz", "-o", "o.ply", "--checkpoint-every", "10", "--resume", *FAST],
         "o.ply.ckpt: not a training checkpoint of ultraboneudf", setup=_write("o.ply.ckpt", "junk")),
    Case("ckpt-cut", C, "`--resume` with a checkpoint cut short", [*R, "in.xyz", "-o", "o.ply", "--checkpoint-every",
                                                                 "10", "--resume", *FAST],
         "o.ply.ckpt: a checkpoint cut short or damaged", setup=_checkpoint("another run", cut=True)),
    Case("detector", C, "`--detector bad_key=1`", ["sweep2points", "sweep", "-o", "d.ply", "--detector", "bad_key=1"],
         "--detector 'bad_key=1': unknown detector option 'bad_key'"),
    Case("segment", C, "`--segment garbage.onnx`", ["sweep2points", "sweep", "-o", "g.ply", "--segment", "garbage.onnx"],
         "garbage.onnx: cannot load as an ONNX model", setup=_write("garbage.onnx", bytes(range(256)) * 8)),
    Case("masks", C, "`--masks` with 5 masks for 10 frames", ["sweep2points", "sweep", "-o", "m.ply", "--masks", "masks"],
         "masks: 5 masks for the 10 frames of sweep", setup=_masks(5)),
    Case("masks-npy", C, "`--masks masks.npy` of 3 frames for 10",
         ["sweep2points", "sweep", "-o", "m.ply", "--masks", "masks.npy"], "masks.npy: 3 masks for the 10 frames",
         setup=_masks(3, npy=True)),
    # sweeps
    Case("png-bomb", S, "a PNG decompression bomb among the frames (60000 × 60000 px in 400 bytes)",
         ["sweep2points", "sweep", "-o", "b.ply", "--segment", "classical", "--quiet"], "sweep/frames/",
         setup=_png_bomb, after=_absent("b.ply")),
    Case("fifo-frame", S, "a named pipe among the frames (would wait forever)",
         ["sweep2points", "sweep", "-o", "b.ply", "--segment", "classical", "--quiet"], "not a regular file",
         setup=_fifo_frame),
    # signals and full disks
    Case("sigint", G, "Ctrl-C (SIGINT) while the output is being written",
         [*STATS, "-o", "report.md"], "interrupted", code=130, hook=(1, "SIGINT"),
         after=_nothing_new("report.md", "report.md.json")),
    Case("sigterm", G, "SIGTERM while the output is being written", [*STATS, "-o", "report.md"],
         "stopped by SIGTERM", code=143, hook=(1, "SIGTERM"), after=_nothing_new("report.md", "report.md.json")),
    Case("sighup", G, "SIGHUP (the terminal closed) while the output is being written", [*STATS, "-o", "report.md"],
         "stopped by SIGHUP", code=129, hook=(1, "SIGHUP"), after=_nothing_new("report.md", "report.md.json")),
    Case("sigterm-late", G, "SIGTERM while the files are renamed into place (held until the result is complete)",
         [*STATS, "-o", "report.md"], "stopped by SIGTERM", code=143, hook=(6, "SIGTERM"),
         after=_written("report.md", "report.md.json")),
    Case("disk-first", G, "the disk fills while the first file is written", [*STATS, "-o", "report.md"],
         "report.md: cannot write (No space left on device); nothing written, the earlier output kept", code=1,
         hook=(1, "ENOSPC"), after=_nothing_new("report.md", "report.md.json")),
    Case("disk-second", G, "the disk fills after the first file, while its sidecar is written",
         [*STATS, "-o", "report.md"], "cannot write (No space left on device)", code=1, hook=(3, "ENOSPC"),
         after=_nothing_new("report.md", "report.md.json")),
]

ROWS = [
    Row(O, "a read-only output folder", "`…: cannot write into … (permission denied)`, before any work",
        "io/test_outputs.py::test_a_read_only_folder_is_one_line_before_any_work"),
    Row(O, "the input cannot be read (permission denied)", "`locked.ply: cannot read the file (Permission denied)`",
        "io/test_outputs.py::test_an_unreadable_input_is_one_line_before_any_work"),
    Row(O, "an earlier output rerun; `bone.obj` after `bone.ply`", "the pair replaced as a unit; each mesh its own "
        "sidecar", "io/test_outputs.py::test_an_earlier_output_is_replaced_as_a_unit_and_sidecars_do_not_clash"),
    Row(O, "an earlier version's output (`bone.ply` with `bone.json`)", "recognised and replaced as a unit, the old "
        "`bone.json` removed in the same commit", "io/test_outputs.py::test_an_output_with_an_earlier_versions_sidecar_is_recognised"),
    Row(O, "the input after any run", "byte for byte unchanged", "cli/test_cli.py::test_reconstruct_writes_mesh_and_sidecar"),
    Row(G, "SIGINT or SIGTERM right after each file operation of a commit (a mesh, its sidecar, a checkpoint "
        "removed, a folder replaced; new and over an earlier result)", "the earlier result or the new one, whole; no "
        "temporary file; exit 130 / 143", "io/test_commit.py::test_a_signal_after_every_step_leaves_the_earlier_or_the_new_result"),
    Row(G, "SIGKILL (or the out-of-memory killer) at each of those moments", "the next command writing there, or its "
        "check before any work, undoes or finishes the commit", "io/test_commit.py::test_a_process_killed_outright_is_undone_or_finished_by_the_next_commit"),
    Row(G, "a rename refused half-way (a full disk)", "the earlier files put back, exit 1",
        "io/test_commit.py::test_a_full_disk_puts_the_earlier_files_back"),
    Row(G, "Ctrl-C or SIGTERM while reading frames, segmenting, training or extracting", "exit 130 / 143, one line, "
        "no mesh, no sidecar, no temporary file", "test_checkpoints.py::test_a_signal_at_each_stage_leaves_no_output"),
    Row(G, "a run killed by SIGTERM during training, then the same command with `--resume`", "resumes at the last "
        "checkpoint; the mesh byte-identical to an uninterrupted run's", "test_checkpoints.py::test_cli_run_killed_by_sigterm_resumes_to_the_same_mesh"),
    Row(S, "a frame missing, more frames than poses, a non-rigid calibration, no pixel spacing, a malformed pose "
        "row, no calibration", "one line naming the file (and line)", "sweep/test_sweep_errors.py::test_missing_frame"),
    Row(S, "MetaIO: fewer transforms than frames, a sheared matrix, pixel data short or long, corrupt or a zlib bomb",
        "one line naming the file; the bomb inflated only up to its header's size", "sweep/test_sweep_errors.py::test_metaio_zlib_bomb_is_not_inflated_beyond_the_header"),
    Row(S, "frames that share one pose, or lie in one plane", "one line, exit 2",
        "sweep/test_sweep_chain.py::test_frames_with_one_pose_and_coplanar_frames"),
    Row(S, "reader warnings", "one line each, dropped when the run fails anyway",
        "sweep/test_sweep_chain.py::test_warnings_are_one_line_each_and_dropped_on_failure"),
    Row(C, "a wrong type or an unknown mode on every config field (95 cases)", "one line naming the key, before "
        "the input is read", "test_config.py::test_bad_set_on_every_field_exits_2_with_one_line"),
    Row(C, "training diverges (NaN loss)", "`training diverged: the loss is not finite at step …`, nothing written",
        "training/test_training_step.py::test_a_diverging_loss_stops_training_naming_the_step_and_the_setting"),
]


# ------------------------------------------------------------------------------------------------
# running the cases

_HOOKED = textwrap.dedent("""
    import errno, os, signal, sys
    signal.signal(signal.SIGINT, signal.default_int_handler)   # a background runner may ignore it
    signal.signal(signal.SIGHUP, signal.SIG_DFL)                # and nohup this one
    stop, action = int(sys.argv[1]), sys.argv[2]
    if stop:
        from ultraboneudf.io import commit
        steps = []

        def hook(what):
            steps.append(what)
            if len(steps) == stop:
                if action == "ENOSPC":
                    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
                os.kill(os.getpid(), getattr(signal, action))
        commit._STEP_HOOK = hook
    from ultraboneudf.cli import main
    sys.exit(main(sys.argv[3:]))
""")


def _run(argv: list[str], folder: Path, hook: tuple[int, str] | None = None) -> tuple[int, list[str]]:
    hook = hook or (0, "")
    res = subprocess.run([sys.executable, "-c", _HOOKED, str(hook[0]), hook[1], *argv], cwd=folder,
                         capture_output=True, text=True, timeout=120,
                         env={**os.environ, "PYTHONPATH": str(ROOT / "src")})
    return res.returncode, [line for line in res.stderr.splitlines() if line.strip()]


def _run_case(case: Case, template: Path, base: Path) -> tuple[int, list[str], str | None]:
    folder = base / case.id
    shutil.copytree(template, folder, symlinks=True)
    if case.setup is not None:
        case.setup(folder)
    code, lines = _run(case.argv, folder, case.hook)
    problem = None
    try:
        if case.after is not None:
            case.after(folder)
        _untouched(folder)
    except AssertionError as exc:
        problem = str(exc)
    return code, lines, problem


def run_all(base: Path) -> dict[str, tuple[int, list[str], str | None]]:
    template = base / "_inputs"
    template.mkdir()
    _inputs(template)
    with ThreadPoolExecutor(max(1, min(4, os.cpu_count() or 1))) as pool:
        results = dict(zip((c.id for c in CASES), pool.map(lambda c: _run_case(c, template, base), CASES)))
    return results


@pytest.fixture(scope="module")
def results(tmp_path_factory):
    return run_all(tmp_path_factory.mktemp("reliability"))


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_case(results, case):
    code, lines, problem = results[case.id]
    assert code == case.code, (code, lines)
    if case.code:
        assert len(lines) == 1 and "Traceback" not in lines[0], lines
        assert lines[0].startswith("ultraboneudf ") and case.line in lines[0], lines
    assert problem is None, problem


def test_refusals_before_any_work_load_neither_torch_nor_trimesh(tmp_path):
    """A refusal answers before PyTorch (or, for a point cloud, an output or a checkpoint, trimesh)
    loads: benchmarks/bench_cli.py times them."""
    _inputs(tmp_path)
    (tmp_path / "report.md").write_text("mine")
    (tmp_path / "photo.png").write_text("mine")
    (tmp_path / "o.ply.ckpt").write_text("mine")
    code = textwrap.dedent("""
        import sys
        from ultraboneudf.cli import main
        for argv in (["reconstruct", "nothing.xyz", "-o", "o.ply"], ["reconstruct", "in.xyz", "-o", "o.ply", "--set",
                     "train.nope=1"], ["stats", "results.csv", "--baseline", "A", "-o", "report.md"],
                     ["simulate", "capsule.ply", "-o", "s", "--set", "n_frames=-3"],
                     ["render", "recon.ply", "-o", "photo.png"], ["demo", "--out", "sweep"],
                     ["reconstruct", "in.xyz", "-o", "o.ply", "--checkpoint-every", "10", "--resume"]):
            assert main(argv) == 2, argv
        print("HEAVY", sorted(m for m in ("torch", "trimesh") if m in sys.modules), file=sys.stderr)
    """)
    res = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True,
                         env={**os.environ, "PYTHONPATH": str(ROOT / "src")})
    assert "HEAVY []" in res.stderr, res.stderr[-800:]


# ------------------------------------------------------------------------------------------------
# the page

INTRO = """\
# Reliability: what every bad input, option, output, disk and signal gets

<!-- Written by `python tests/cli/test_reliability.py` from the cases it runs: edit the cases there. -->

The contract, for every command that writes (`reconstruct`, `sweep2points`, `render`, `evaluate --json`,
`stats -o`, `demo`, `simulate`, `bench dataset|run|report`, training checkpoints):

- **Nothing the user gave is modified**, and no output is ever written over an input or into a folder
  being read.
- **Nothing this package did not write is replaced.** Every output carries a record: a file `X` its
  sidecar `X.json` (naming `X` and holding its SHA-256); a folder `D` the file `D/ultraboneudf.json`
  (listing every file in it with its SHA-256); a checkpoint its own header. An existing output is
  replaced only when its record is there and it is unchanged since; `--overwrite` replaces it anyway
  (never an input, a folder where a file goes, or a special file).
- **A result is put in place as a unit.** Its files are written under temporary names beside their
  targets and renamed together, SIGINT, SIGTERM and SIGHUP held for those milliseconds: on any signal
  at any moment either the earlier result or the new one is there, complete, and no temporary file is
  left. A process killed outright (SIGKILL) leaves a journal that the next command writing into that
  folder undoes or finishes before anything else. A folder output (a simulation, a demo, a dataset) is
  replaced as a whole; a `bench run` folder takes one finished cell at a time.
- **Paths read from data files stay inside their folder**: a manifest's ids name folders of results
  and must be plain names; a MetaIO header's pixel data lie beside it.
- **Every bad input, option or file is refused before any work**, in one line naming it (control
  characters in names written as escapes), exit 2 — and before PyTorch loads wherever the check does
  not need it (0.15 s and 45 MB instead of 1.7–3.4 s and 300–400 MB: `benchmarks/bench_cli.py`).

**Exit codes, one rule for every command:**

| exit | when | what is left |
| --- | --- | --- |
| 0 | done | the new result |
| 2 | refused before any work: a bad input, option or output name, no permission or no room (less than 64 MB free) to write there | nothing new; one line on stderr |
| 1 | failed after the work began: the disk filled up or a write failed (one line), the memory ran out (one line), or a bug (a traceback) | the earlier output; nothing of the new one |
| 128 + N | stopped by signal N: 130 Ctrl-C (SIGINT), 143 SIGTERM, 129 SIGHUP (one line) | the earlier output, or the new one complete if the signal came while it was being put in place; no temporary file |

Every row below is checked by the test in its last column (under `tests/`). The rows of
`cli/test_reliability.py` are run from the command line exactly as shown, in a folder of small inputs
(`in.xyz`, `gt.ply`, `recon.ply`, `capsule.ply`, `results.csv`, a ten-frame `sweep/`; commands that
would train a network also get a tiny one, `--preset fast --iters 100 …`, left out here), and the line
shown is what that run printed.
"""


def _escape(text: str) -> str:
    return text.replace("|", "\\|").replace("`", "'")


def _command(argv: list[str]) -> str:
    """The command as a user types it, without the tiny network's options (:data:`FAST`)."""
    shown = list(argv)
    for i in range(len(shown) - len(FAST) + 1):
        if shown[i:i + len(FAST)] == FAST:
            del shown[i:i + len(FAST)]
            break
    words = [repr(a)[1:-1] if "\n" in a else (a if len(a) < 40 else a[:12] + "…" + a[-8:]) for a in shown]
    return " ".join(["ultraboneudf", *words])


def page(results: dict[str, tuple[int, list[str], str | None]]) -> str:
    out = [INTRO]
    sections = list(dict.fromkeys([c.section for c in CASES] + [r.section for r in ROWS]))
    for section in sections:
        out.append(f"\n## {section}\n\n| case | command | exit | what the user gets | test |\n| --- | --- | --- | --- | --- |")
        for c in CASES:
            if c.section == section:
                code, lines, _ = results[c.id]
                gets = _escape(lines[0]) if lines and c.code else "the new result; the earlier file replaced"
                out.append(f"| {c.what} | `{_escape(_command(c.argv))}` | {code} | `{gets}` | "
                           f"`cli/test_reliability.py::test_case[{c.id}]` |")
        for r in ROWS:
            if r.section == section:
                out.append(f"| {r.what} | | | {r.gets} | `{r.test}` |")
    return "\n".join(out) + "\n"


def test_the_page_lists_every_case_as_run():
    """docs/reliability.md holds one row per case, each with a line that holds the case's fragment,
    and one per row checked elsewhere, whose test exists: rewrite it with
    ``python tests/cli/test_reliability.py`` after changing a case."""
    text = PAGE.read_text(encoding="utf-8")
    for c in CASES:
        row = next((line for line in text.splitlines() if f"test_case[{c.id}]" in line), None)
        assert row is not None, f"{c.id} is not on the page: python tests/cli/test_reliability.py"
        assert _escape(c.line) in row and f"| {c.code} |" in row, f"the page's row of {c.id} is stale"
    for r in ROWS:
        assert f"`{r.test}`" in text, f"{r.test} is not on the page"
        file, name = r.test.split("::")
        assert re.search(rf"def {re.escape(name)}\b", (ROOT / "tests" / file).read_text()), f"no test {r.test}"


if __name__ == "__main__":
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        found = run_all(Path(tmp))
    wrong = [c.id for c in CASES if found[c.id][0] != c.code or (c.code and c.line not in " ".join(found[c.id][1]))
             or found[c.id][2]]
    if wrong:
        sys.exit(f"these cases do not hold, the page is not written: {', '.join(wrong)}")
    PAGE.write_text(page(found), encoding="utf-8")
    print(f"wrote {PAGE} ({len(CASES)} cases run, {len(ROWS)} rows checked elsewhere)")
