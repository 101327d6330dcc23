"""The data-safety battery: every command tried as a hostile user would, from the command line, each
case in a fresh process, the folder's state checked after it.

    python benchmarks/safety_battery.py                       # prints a Markdown table
    python benchmarks/safety_battery.py --src /other/checkout/src --only refusals
    python benchmarks/safety_battery.py --quick               # one signal per commit step set

Classes: an input destroyed; user files overwritten; half-written output on a signal (SIGINT and
SIGTERM right after every file operation of the commit, through the commit's step hook); paths out
of their folder; tracebacks; hangs; wrong answers; late or multi-line refusals; exit codes of a full
disk (a real one: a small tmpfs filled at the moment named, where mounting is allowed; else the file
system's error injected at that moment). Each row: the command, its exit code, the first line it
printed on stderr, seconds and peak memory of the process, and whether the contract held (``ok``).
"""

from __future__ import annotations

import argparse
import os
import shutil
import signal
import statistics
import struct
import subprocess
import sys
import tempfile
import textwrap
import time
import zlib
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROWS: list[dict] = []
SRC = HERE.parent / "src"
FAST = ["--preset", "fast", "--iters", "200", "--set", "train.batch=500", "--set", "extract.max_depth=6",
        "--set", "model.hidden=32,32", "--set", "train.threads=1", "--quiet"]


# ------------------------------------------------------------------------------------------------
# running one command


_HOOKED = textwrap.dedent("""
    import os, signal, sys
    signal.signal(signal.SIGINT, signal.default_int_handler)
    stop, action = int(sys.argv[1]), sys.argv[2]
    steps = []
    try:
        from ultraboneudf.io import commit
    except ImportError:
        commit = None
    if commit is not None and hasattr(commit, "_STEP_HOOK"):
        def hook(what):
            steps.append(what)
            if len(steps) == stop:
                if action.startswith("SIG"):
                    os.kill(os.getpid(), getattr(signal, action))
                else:                                  # a shell command: fill the disk now
                    os.system(action)
        commit._STEP_HOOK = hook
    from ultraboneudf.cli import main
    try:
        code = main(sys.argv[3:])
    finally:
        print(f"STEPS {len(steps)} {'|'.join(steps)}", file=sys.stderr)
    sys.exit(code)
""")


def run(argv: list[str], cwd: Path, *, hook: tuple[int, str] | None = None, timeout: float = 300,
        stdin=None) -> dict:
    """Run ``ultraboneudf ARGV`` in ``cwd`` (with the commit step hook: stop at step N with a signal
    or a shell command); exit code, stderr lines, seconds, peak resident MB."""
    env = {**os.environ, "PYTHONPATH": str(SRC), "ULTRABONEUDF_PROGRESS_S": "0"}
    if hook is None:
        cmd = [sys.executable, "-m", "ultraboneudf.cli", *argv]
    else:
        cmd = [sys.executable, "-c", _HOOKED, str(hook[0]), hook[1], *argv]
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, cwd=cwd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            stdin=stdin or subprocess.DEVNULL)
    try:
        out, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, err = proc.communicate()
        return {"code": "hang", "lines": [f"killed after {timeout:.0f} s"], "s": timeout, "mb": 0, "steps": []}
    seconds = time.perf_counter() - t0
    lines = [l for l in err.decode(errors="replace").splitlines() if l.strip()]
    steps = []
    for l in lines:
        if l.startswith("STEPS "):
            parts = l.split(" ", 2)
            steps = parts[2].split("|") if len(parts) > 2 and parts[2] else []
    lines = [l for l in lines if not l.startswith("STEPS ")]
    return {"code": proc.returncode, "lines": lines, "s": seconds, "mb": None, "steps": steps,
            "stdout": out.decode(errors="replace")}


def peak_of(argv: list[str], cwd: Path) -> float:
    """Peak resident MB of one command, alone in a fresh interpreter that reports it."""
    code = ("import resource, subprocess, sys; subprocess.run(sys.argv[1:], capture_output=True); "
            "print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024)")
    env = {**os.environ, "PYTHONPATH": str(SRC)}
    res = subprocess.run([sys.executable, "-c", code, sys.executable, "-m", "ultraboneudf.cli", *argv],
                         cwd=cwd, env=env, capture_output=True, text=True, timeout=600)
    try:
        return float(res.stdout.strip().splitlines()[-1])
    except (ValueError, IndexError):
        return float("nan")


def row(cls: str, case: str, res: dict, ok: bool, note: str = "") -> None:
    first = res["lines"][0] if res["lines"] else ""
    ROWS.append({"class": cls, "case": case, "code": res["code"], "line": first, "lines": len(res["lines"]),
                 "s": res["s"], "ok": ok, "note": note})
    mark = "ok" if ok else "BROKEN"
    print(f"[{mark}] {cls}: {case} -> {res['code']} ({res['s']:.1f} s) {first[:150]}", file=sys.stderr)


def one_line_refusal(res: dict) -> bool:
    return res["code"] == 2 and len(res["lines"]) == 1 and "Traceback" not in res["lines"][0]


def before_work(argv: list[str], cwd: Path) -> bool:
    """The same command without ``--quiet`` reports no stage of work (reading frames, segmenting,
    training…) before its refusal: every line it prints is the refusal itself."""
    res = run([a for a in argv if a != "--quiet"], cwd)
    return res["code"] == 2 and all(line.startswith("ultraboneudf ") for line in res["lines"])


def listing(folder: Path) -> dict[str, bytes | None]:
    out = {}
    for root, dirs, files in os.walk(folder):
        for d in dirs:
            out[os.path.relpath(os.path.join(root, d), folder) + "/"] = None
        for f in files:
            p = os.path.join(root, f)
            out[os.path.relpath(p, folder)] = Path(p).read_bytes() if os.path.isfile(p) else b"<special>"
    return out


def stray(folder: Path) -> list[str]:
    """Temporary or staged names left anywhere under ``folder``."""
    return [k for k in listing(folder) if any(t in k for t in (".tmp", ".ubtmp", ".ubold", "ultraboneudf-commit"))]


# ------------------------------------------------------------------------------------------------
# fixtures


def fixtures(root: Path) -> dict:
    import numpy as np
    import trimesh

    rng = np.random.default_rng(0)
    theta = rng.uniform(np.pi / 4, 3 * np.pi / 4, 3000)
    np.savetxt(root / "in.xyz", np.c_[20 * np.cos(theta), rng.uniform(0, 40, 3000), 20 * np.sin(theta)])
    trimesh.creation.icosphere(subdivisions=3, radius=20).export(root / "gt.ply")
    trimesh.creation.icosphere(subdivisions=3, radius=20.5).export(root / "recon.ply")
    trimesh.creation.capsule(height=40, radius=10).export(root / "capsule.ply")
    res = run(["simulate", "capsule.ply", "-o", "sim", "--frames", "8", "--width-px", "96", "--height-px", "120",
               "--spacing-mm", "0.3", "--seed", "1", "--quiet"], root)
    assert res["code"] == 0, res
    (root / "results.csv").write_text("method,specimen,reconstruction,cd_mm,hd95_mm\n" + "".join(
        f"{m},s{i % 3},r{i},{1 + 0.1 * i + (m == 'B')},{2 + 0.1 * i}\n" for i in range(9) for m in "AB"))
    return {}


def png_bomb(path: Path, width: int = 60000, height: int = 60000) -> None:
    """A PNG whose header declares ``width`` × ``height`` grey pixels with a few rows of data: a few
    hundred bytes on disk, 3.6 GB once decoded."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    raw = zlib.compress(b"\0" * (width + 1) * 16, 9)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0))
                     + chunk(b"IDAT", raw) + chunk(b"IEND", b""))


# ------------------------------------------------------------------------------------------------
# the classes


def inputs_and_user_files(root: Path) -> None:
    cls = "an input destroyed"
    poses = (root / "sim" / "poses.csv").read_bytes()
    res = run(["sweep2points", "sim", "-o", "sim/poses.csv", "--quiet"], root)
    row(cls, "`sweep2points sim -o sim/poses.csv`", res,
        one_line_refusal(res) and (root / "sim" / "poses.csv").read_bytes() == poses)
    (root / "sim" / "poses.csv").write_bytes(poses)             # for the cases after, if it was lost

    cls = "user files overwritten"
    cases = [
        ("pts.ply", ["sweep2points", "sim", "-o", "pts.ply", "--quiet"], "`sweep2points sim -o pts.ply` over a user's `pts.ply`"),
        ("photo.png", ["render", "recon.ply", "-o", "photo.png"], "`render recon.ply -o photo.png` over a user's PNG"),
        ("notes.json", ["evaluate", "recon.ply", "--gt", "gt.ply", "--json", "notes.json", "--samples", "20000",
                        "--quiet"], "`evaluate recon.ply --gt gt.ply --json notes.json` over a user's notes"),
        ("report.md", ["stats", "results.csv", "--baseline", "A", "-o", "report.md"],
         "`stats results.csv --baseline A -o report.md` over a user's report"),
    ]
    for name, argv, label in cases:
        (root / name).write_bytes(b"the user's own " + name.encode())
        res = run(argv, root)
        kept = (root / name).read_bytes() == b"the user's own " + name.encode()
        row(cls, label, res, one_line_refusal(res) and kept and not (root / (name + ".json")).exists())
        res = run([*argv, "--overwrite"], root)
        row(cls, label.split(" over ")[0] + " `--overwrite` (the user means it)", res,
            res["code"] == 0 and (root / name).read_bytes() != b"the user's own " + name.encode()
            and (root / (name + ".json")).exists())
        before = listing(root)
        res = run(argv, root)                                  # an earlier output of ours: replaced
        row(cls, label.split(" over ")[0] + " again (over its own earlier output)", res,
            res["code"] == 0 and set(listing(root)) == set(before))
        for gone in (name, name + ".json"):
            (root / gone).unlink(missing_ok=True)
    (root / "demo").mkdir()
    (root / "demo" / "demo_points.xyz").write_text("the user's points\n")
    res = run(["demo", "--out", "demo", *FAST], root)
    row(cls, "`demo --out demo` with a user's `demo/demo_points.xyz`", res,
        one_line_refusal(res) and (root / "demo" / "demo_points.xyz").read_text() == "the user's points\n"
        and before_work(["demo", "--out", "demo", *FAST], root), "before any work")
    shutil.rmtree(root / "demo")
    (root / "out.ply.ckpt").write_text("the user's file\n")
    res = run(["reconstruct", "in.xyz", "-o", "out.ply", "--checkpoint-every", "50", *FAST], root)
    row(cls, "`reconstruct in.xyz -o out.ply --checkpoint-every 50` with a user's `out.ply.ckpt`", res,
        one_line_refusal(res) and (root / "out.ply.ckpt").read_text() == "the user's file\n"
        and not (root / "out.ply").exists())
    (root / "out.ply.ckpt").unlink(missing_ok=True)


def _pair_consistent(folder: Path, name: str) -> str | None:
    """``None`` when ``name`` and its sidecar are absent together or present and describing each
    other (the mesh's SHA-256 recorded in the sidecar, where the sidecar records one)."""
    import hashlib
    import json

    mesh, side = folder / name, folder / (name + ".json")
    if mesh.exists() != side.exists():
        return f"{name} without its sidecar" if mesh.exists() else f"a sidecar without {name}"
    if mesh.exists():
        meta = json.loads(side.read_text())
        if "sha256" in meta and hashlib.sha256(mesh.read_bytes()).hexdigest() != meta["sha256"]:
            return f"{name} beside a sidecar that describes another file"
    return None


def signals(root: Path, quick: bool) -> None:
    cls = "half-written output on a signal"
    sigs = ["SIGTERM"] if quick else ["SIGINT", "SIGTERM"]
    # reconstruct with checkpoints, new and over an earlier output: every step of every write
    for earlier in (False, True):
        work = root / f"sig_rec_{int(earlier)}"
        work.mkdir()
        shutil.copy(root / "in.xyz", work / "in.xyz")
        argv = ["reconstruct", "in.xyz", "-o", "out.ply", "--checkpoint-every", "50", *FAST]
        if earlier:
            assert run(argv[:4] + FAST + ["--seed", "7"], work)["code"] == 0
        base = listing(work)
        steps = run(argv, work, hook=(0, "SIGTERM"))["steps"]
        (work / "out.ply").unlink(), (work / "out.ply.json").unlink()
        if earlier:
            for k, v in base.items():
                (work / k).write_bytes(v)
        broken = []
        for sig in sigs:
            for k in range(1, len(steps) + 1):
                res = run(argv, work, hook=(k, sig))
                problem = _pair_consistent(work, "out.ply")
                left = stray(work)
                code_ok = res["code"] == 128 + getattr(signal, sig) and len(res["lines"]) == 1
                if problem or left or not code_ok:
                    broken.append(f"{sig} after {steps[k - 1]}: {problem or left or res['code']}")
                for gone in ("out.ply", "out.ply.json", "out.ply.ckpt"):
                    (work / gone).unlink(missing_ok=True)
                for k2, v in base.items():
                    (work / k2).write_bytes(v)
        res = {"code": "—", "lines": [f"{len(steps)} steps × {len(sigs)} signals: " +
                                      ("every state the earlier or the new result, no temporary file"
                                       if not broken else "; ".join(broken[:3]))], "s": 0, "mb": 0}
        row(cls, f"`reconstruct in.xyz -o out.ply --checkpoint-every 50` {'over an earlier output' if earlier else 'new'}: "
                 f"{'/'.join(sigs)} after each of its {len(steps)} file operations (3 checkpoints, then the mesh)",
            res, not broken)
    # sweep2points with overlays; simulate over an earlier simulation; stats; render; evaluate --json
    multi = [
        ("`sweep2points sim -o pts.ply --overlays sheets`", ["sweep2points", "sim", "-o", "pts.ply", "--overlays",
                                                            "sheets", "--quiet"], ["pts.ply", "pts.ply.json", "sheets"]),
        ("`simulate capsule.ply -o sim2` over an earlier sim2", ["simulate", "capsule.ply", "-o", "sim2", "--frames",
                                                               "6", "--width-px", "96", "--height-px", "120",
                                                               "--quiet"], ["sim2"]),
        ("`stats results.csv --baseline A -o report.md`", ["stats", "results.csv", "--baseline", "A", "-o",
                                                            "report.md"], ["report.md", "report.md.json"]),
    ]
    for label, argv, outs in multi:
        work = root / f"sig_{outs[0].replace('.', '_')}"
        work.mkdir()
        for name in ("sim", "capsule.ply", "results.csv"):
            src = root / name
            (shutil.copytree if src.is_dir() else shutil.copy)(src, work / name)
        assert run(argv + (["--seed", "5"] if "simulate" in argv else []), work)["code"] == 0
        if "simulate" not in argv:  # new for the others, over the earlier simulation for simulate
            for o in outs:
                (shutil.rmtree if (work / o).is_dir() else os.unlink)(work / o)
        before = listing(work)
        first = run(argv, work, hook=(0, "SIGTERM"))
        steps, after_new = first["steps"], listing(work)
        broken = []
        for sig in sigs:
            for k in range(1, len(steps) + 1):
                for o in outs:
                    p = work / o
                    if p.exists():
                        (shutil.rmtree if p.is_dir() else os.unlink)(p)
                for name, data in before.items():
                    if name.endswith("/"):
                        (work / name).mkdir(parents=True, exist_ok=True)
                for name, data in before.items():
                    if not name.endswith("/"):
                        (work / name).write_bytes(data)
                res = run(argv, work, hook=(k, sig))
                now = listing(work)
                same_as = ("earlier" if now == before else
                           "new" if set(now) == set(after_new) and all(
                               now[n] == after_new[n] for n in now if "sha256" not in str(n) and not n.endswith(".json")
                               and "/ultraboneudf.json" not in n) else None)
                if same_as is None or stray(work) or res["code"] != 128 + getattr(signal, sig):
                    extra = sorted(set(now) ^ set(before if same_as != "new" else after_new))[:3]
                    broken.append(f"{sig} after {steps[k - 1]}: {extra or res['code']}")
        res = {"code": "—", "lines": [f"{len(steps)} steps × {len(sigs)} signals: " +
                                      ("every state the earlier or the new result, no temporary file"
                                       if not broken else "; ".join(broken[:3]))], "s": 0, "mb": 0}
        row(cls, f"{label}: {'/'.join(sigs)} after each of its {len(steps)} file operations", res, not broken)


def paths(root: Path) -> None:
    cls = "paths out of their folder"
    import numpy as np

    ds = root / "ds"
    ds.mkdir()
    np.savez(ds / "a.npz", points=np.loadtxt(root / "in.xyz"))
    shutil.copy(root / "gt.ply", ds / "a_gt.ply")
    for uid in ("../../x", "/abs/x", "sub/x"):
        (ds / "manifest.csv").write_text(f"id,specimen,input,gt\n{uid},s,a.npz,a_gt.ply\n")
        before = listing(root.parent)
        res = run(["bench", "run", "--dataset", "ds/manifest.csv", "--out", "runs", "--method", "ultraboneudf",
                   "--set", "train.iters=50", "--quiet"], root)
        row(cls, f"`bench run` with manifest id `{uid}`", res,
            one_line_refusal(res) and listing(root.parent).keys() == before.keys())
    frames = "".join(f"Seq_Frame{i:04d}_ImageToReferenceTransform = 0.2 0 0 0 0 0.2 0 0 0 0 1 {3 * i} 0 0 0 1\n"
                     f"Seq_Frame{i:04d}_ImageToReferenceTransformStatus = OK\n" for i in range(2))
    (root / "sim_outside.mhd").write_text("ObjectType = Image\nNDims = 3\nDimSize = 4 4 2\nElementType = MET_UCHAR\n"
                                          + frames + "ElementDataFile = ../../etc/hostname\n")
    res = run(["sweep2points", "sim_outside.mhd", "-o", "o.ply", "--quiet"], root)
    row(cls, "`sweep2points` of a MetaIO header whose `ElementDataFile` is `../../etc/hostname`", res,
        one_line_refusal(res))


def tracebacks(root: Path) -> None:
    cls = "tracebacks, exit 1"
    (root / "o1.ply.ckpt").mkdir()
    res = run(["reconstruct", "in.xyz", "-o", "o1.ply", "--checkpoint-every", "50", *FAST], root)
    row(cls, "`--checkpoint-every` where `OUT.ckpt` is a folder", res, one_line_refusal(res)
        and before_work(["reconstruct", "in.xyz", "-o", "o1.ply", "--checkpoint-every", "50", *FAST], root),
        "before any work")
    long = "b" * 250 + ".ply"
    res = run(["reconstruct", "in.xyz", "-o", long, *FAST], root)
    row(cls, "an output name of 254 characters (`bbb….ply`)", res,
        one_line_refusal(res) and not (root / long).exists())
    res = run(["config", "--update-docs", "missing.md"], root)
    row(cls, "`config --update-docs missing.md`", res, one_line_refusal(res))
    bomb = root / "sim_bomb"
    shutil.copytree(root / "sim", bomb)
    frame = sorted((bomb / "frames").iterdir())[3]
    png_bomb(frame)
    argv = ["sweep2points", "sim_bomb", "-o", "bomb.ply", "--segment", "classical", "--quiet"]
    res = run(argv, root)
    mb = peak_of(argv, root)
    row(cls, f"a PNG decompression bomb among the sweep's frames (`{frame.name}`: 60000×60000 px in "
             f"{frame.stat().st_size} bytes)", res, one_line_refusal(res) and mb < 2000, f"{mb:.0f} MB peak")
    big = root / "big.xyz"
    with open(big, "w") as fh:
        fh.write("".join(f"{x:.4f} {x * 2:.4f} {x * 3 % 7:.4f}\n" for x in range(2000)))
    os.truncate(big, 20 * 10**9)  # sparse: 20 GB that take no disk
    res = run(["reconstruct", "big.xyz", "-o", "big_out.ply", *FAST], root)
    mb = peak_of(["reconstruct", "big.xyz", "-o", "big_out.ply", *FAST], root)
    row(cls, "a 20 GB text cloud (sparse file: 2,000 lines, then zeros)", res,
        one_line_refusal(res) and mb < 500, f"{mb:.0f} MB peak")
    script = ("import resource, runpy, sys; resource.setrlimit(resource.RLIMIT_AS, (4 << 30, 4 << 30)); "
              "sys.argv = ['ultraboneudf'] + sys.argv[1:]; runpy.run_module('ultraboneudf.cli', run_name='__main__')")
    env = {**os.environ, "PYTHONPATH": str(SRC)}
    t0 = time.perf_counter()
    p = subprocess.run([sys.executable, "-c", script, "reconstruct", "big.xyz", "-o", "big_out.ply", *FAST],
                       cwd=root, env=env, capture_output=True, text=True, timeout=600)
    capped = {"code": p.returncode, "lines": [l for l in p.stderr.splitlines() if l.strip()],
              "s": time.perf_counter() - t0, "mb": 0}
    row(cls, "a 20 GB text cloud under a 4 GiB address-space cap (`ulimit -v`)", capped,
        one_line_refusal(capped))
    big.unlink()


def hangs(root: Path) -> None:
    cls = "hangs"
    for name, argv in (("fifo.xyz", ["reconstruct", "fifo.xyz", "-o", "f.ply", *FAST]),
                       ("fifo.ply", ["evaluate", "fifo.ply", "--gt", "gt.ply", "--quiet"]),
                       ("fifo2.ply", ["render", "fifo2.ply", "-o", "f.png"]),
                       ("fifo.csv", ["stats", "fifo.csv", "--baseline", "A"])):
        os.mkfifo(root / name)
        res = run(argv, root, timeout=30)
        row(cls, f"a named pipe (FIFO) as the input: `{' '.join(argv[:3])}`", res, one_line_refusal(res))
        (root / name).unlink()
    res = run(["reconstruct", "in.xyz", "-o", "/dev/null/x.ply", *FAST], root, timeout=30)
    row(cls, "an output inside a device (`-o /dev/null/x.ply`)", res, one_line_refusal(res))


def wrong_answers(root: Path) -> None:
    cls = "wrong answers, exit 0"
    import numpy as np
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=3, radius=20.5)
    v = m.vertices.copy()
    v[5] = np.nan
    trimesh.Trimesh(v, m.faces, process=False).export(root / "nan.ply")
    res = run(["render", "nan.ply", "--gt", "gt.ply", "-o", "nan.png"], root)
    row(cls, "`render` of a mesh with a NaN vertex", res, one_line_refusal(res) and not (root / "nan.png").exists())
    res = run(["evaluate", "nan.ply", "--gt", "gt.ply", "--samples", "20000", "--quiet"], root)
    row(cls, "`evaluate` of a mesh with a NaN vertex", res, one_line_refusal(res))
    lines = trimesh.exchange.ply.export_ply(m, encoding="ascii").decode().splitlines()
    (root / "short.ply").write_text("\n".join(lines[:-30]) + "\n")
    res = run(["evaluate", "short.ply", "--gt", "gt.ply", "--samples", "20000", "--quiet"], root)
    row(cls, "`evaluate` of an ASCII PLY whose header promises 30 more faces than it holds", res,
        one_line_refusal(res))
    (root / "short_v.ply").write_text("\n".join(lines[:lines.index("end_header") + 50]) + "\n")
    res = run(["evaluate", "short_v.ply", "--gt", "gt.ply", "--samples", "20000", "--quiet"], root)
    row(cls, "`evaluate` of an ASCII PLY cut inside its vertices", res, one_line_refusal(res))
    for setting in ("n_frames=-3", "width_px=0", "tilt_deg=nan", "pred_gap_fraction=1.5"):
        res = run(["simulate", "capsule.ply", "-o", "never", "--set", setting, "--quiet"], root)
        row(cls, f"`simulate --set {setting}`", res, one_line_refusal(res) and not (root / "never").exists())


def late_refusals(root: Path) -> None:
    cls = "refused late, in several lines"
    import numpy as np

    work = root / "ckpt"
    work.mkdir()
    shutil.copy(root / "in.xyz", work / "in.xyz")
    argv = ["reconstruct", "in.xyz", "-o", "out.ply", "--checkpoint-every", "50", *FAST]
    made = run(argv, work, hook=(3, "SIGTERM"))                    # stopped after its first checkpoint
    assert (work / "out.ply.ckpt").exists(), made
    ckpt = (work / "out.ply.ckpt").read_bytes()
    other = work / "other.xyz"
    other.write_bytes((work / "in.xyz").read_bytes().replace(b"\n", b"\n", 1) + b"0 0 0\n")
    variants = [
        ("another seed", argv + ["--resume", "--seed", "7"]),
        ("another `--set`", argv + ["--resume", "--set", "loss.lambda_gs=0.5"]),
        ("another preset", ["reconstruct", "in.xyz", "-o", "out.ply", "--checkpoint-every", "50", "--preset", "robust",
                            "--iters", "200", "--quiet", "--resume"]),
        ("another method", argv + ["--resume", "--method", "capudf"]),
        ("another input", ["reconstruct", "other.xyz", "-o", "out.ply", *argv[4:], "--resume"]),
        ("another iteration count", argv + ["--resume", "--iters", "300"]),
        ("a file that is not a checkpoint", None),
        ("a checkpoint cut short", None),
    ]
    for label, args in variants:
        if label == "a file that is not a checkpoint":
            (work / "out.ply.ckpt").write_text("not a checkpoint\n")
            args = argv + ["--resume"]
        elif label == "a checkpoint cut short":
            (work / "out.ply.ckpt").write_bytes(ckpt[: len(ckpt) // 2])
            args = argv + ["--resume"]
        else:
            (work / "out.ply.ckpt").write_bytes(ckpt)
        res = run(args, work)
        row(cls, f"`--resume` with a checkpoint of {label}", res,
            one_line_refusal(res) and "out.ply.ckpt" in res["lines"][0] and not (work / "out.ply").exists()
            and before_work(args, work), "before any work")
    (work / "out.ply.ckpt").write_bytes(ckpt)
    res = run(argv + ["--resume"], work)
    row(cls, "`--resume` with its own checkpoint (goes through, checkpoint removed)", res,
        res["code"] == 0 and not (work / "out.ply.ckpt").exists() and (work / "out.ply").exists())

    (root / "garbage.onnx").write_bytes(os.urandom(2000))
    (root / "garbage.pt").write_bytes(os.urandom(2000))
    masks = root / "few_masks"
    masks.mkdir()
    for f in sorted((root / "sim" / "masks").iterdir())[:5]:
        shutil.copy(f, masks / ("m" + f.name))
    np.save(root / "masks.npy", np.zeros((3, 120, 96), dtype=bool))
    for label, extra in (("`--detector bad_key=1`", ["--detector", "bad_key=1"]),
                         ("`--segment garbage.onnx`", ["--segment", "garbage.onnx"]),
                         ("`--segment garbage.pt`", ["--segment", "garbage.pt"]),
                         ("`--masks` with 5 masks for 8 frames", ["--masks", "few_masks"]),
                         ("`--masks masks.npy` of 3 frames for 8", ["--masks", "masks.npy"])):
        argv = ["sweep2points", "sim", "-o", "o.ply", *extra, "--quiet"]
        res = run(argv, root)
        row(cls, label, res, one_line_refusal(res) and before_work(argv, root), "before reading a frame")
    res = run(["reconstruct", "bad\nname.xyz", "-o", "o.ply", *FAST], root)
    row(cls, "a newline in a file name (`$'bad\\nname.xyz'`)", res, one_line_refusal(res) and "\\n" in res["lines"][0])


def exit_codes(root: Path) -> None:
    cls = "exit codes"
    disk = root / "disk"
    disk.mkdir()
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=80m", "tmpfs", str(disk)],
                             capture_output=True).returncode == 0
    try:
        shutil.copy(root / "in.xyz", disk / "in.xyz")
        argv = ["reconstruct", "in.xyz", "-o", "out.ply", *FAST]
        steps = run(argv, disk, hook=(0, "true"))["steps"]
        for f in ("out.ply", "out.ply.json"):
            (disk / f).unlink()
        for label, at in (("while the mesh is written", 1), ("after the mesh, while its sidecar is written", 2)):
            # fill the disk right after the staged file is created (the mesh's, or the sidecar's)
            created = [i + 1 for i, s in enumerate(steps) if s.startswith("create")][at - 1]
            fill = (f"dd if=/dev/zero of={disk}/filler bs=1M count=100 2>/dev/null" if mounted
                    else "python3 -c 'raise SystemExit'")
            res = run(argv, disk, hook=(created - 1 if at == 2 else created, fill)) if mounted else \
                {"code": "n/a", "lines": ["tmpfs cannot be mounted here"], "s": 0, "mb": 0}
            left = sorted(set(listing(disk)) - {"in.xyz", "filler"})
            row(cls, f"a full disk {label}", res,
                res["code"] == 1 and len(res["lines"]) == 1 and "No space left" in res["lines"][0] and not left,
                "real tmpfs of 80 MB filled at that moment" if mounted else "")
            (disk / "filler").unlink(missing_ok=True)
        if mounted:
            with open(disk / "filler", "wb") as fh:
                fh.write(b"\0" * (40 << 20))
        res = run(argv, disk) if mounted else {"code": "n/a", "lines": [""], "s": 0, "mb": 0}
        row(cls, "a disk with less than 64 MB free before any work", res, one_line_refusal(res))
    finally:
        if mounted:
            subprocess.run(["umount", str(disk)])
    for sig in ("SIGINT", "SIGTERM", "SIGHUP"):
        res = run(["reconstruct", "in.xyz", "-o", "sig.ply", *FAST], root, hook=(1, sig))
        row(cls, f"{sig} while the mesh is staged", res, res["code"] == 128 + getattr(signal, sig)
            and len(res["lines"]) == 1 and not (root / "sig.ply").exists() and not stray(root))


def refusal_cost(root: Path) -> None:
    """Seconds and peak memory of refusals that need no work."""
    cls = "cost of a refusal"
    (root / "user.png").write_text("the user's picture\n")
    for label, argv in (("missing input", ["reconstruct", "nothing.xyz", "-o", "o.ply"]),
                        ("unknown --set key", ["reconstruct", "in.xyz", "-o", "o.ply", "--set", "train.bogus=1"]),
                        ("a user's file at the output", ["render", "recon.ply", "-o", "user.png"]),
                        ("`--detector bad_key=1`", ["sweep2points", "sim", "-o", "d.ply", "--detector", "bad_key=1"]),
                        ("`simulate --set n_frames=-3`", ["simulate", "capsule.ply", "-o", "n", "--set", "n_frames=-3"])):
        times = [run(argv, root)["s"] for _ in range(3)]
        res = run(argv, root)
        res["s"] = statistics.median(times)
        mb = peak_of(argv, root)
        row(cls, f"{label}: `{' '.join(argv)}`", res, one_line_refusal(res), f"median of 3: {res['s']:.2f} s, "
                                                                              f"{mb:.0f} MB peak")


CLASSES = {"refusals": [inputs_and_user_files, paths, tracebacks, hangs, wrong_answers, late_refusals],
           "signals": [signals], "exit": [exit_codes], "cost": [refusal_cost]}


def main() -> None:
    global SRC
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--src", type=Path, default=SRC, help="the package's src folder to test")
    p.add_argument("--only", default=None, help=f"comma-separated classes: {', '.join(CLASSES)}")
    p.add_argument("--quick", action="store_true", help="SIGTERM only in the signal class")
    p.add_argument("--keep", action="store_true", help="keep the work folder")
    args = p.parse_args()
    SRC = args.src.resolve()
    root = Path(tempfile.mkdtemp(prefix="ubu-battery-")) / "w"
    root.mkdir()
    try:
        fixtures(root)
        for name, funcs in CLASSES.items():
            if args.only and name not in args.only.split(","):
                continue
            for f in funcs:
                try:
                    f(root) if f is not signals else f(root, args.quick)
                except Exception as exc:  # an earlier version may leave the folder unusable
                    ROWS.append({"class": f.__name__, "case": "(the rest of this class)", "code": "—",
                                 "line": f"the battery stopped: {type(exc).__name__}: {exc}", "lines": 1,
                                 "s": 0, "ok": False, "note": ""})
    finally:
        if not args.keep:
            shutil.rmtree(root.parent, ignore_errors=True)
        else:
            print(f"work folder: {root}", file=sys.stderr)
    print("| class | case (command as run) | exit | what the user gets (stderr, first line) | s | contract |")
    print("| --- | --- | --- | --- | --- | --- |")
    for r in ROWS:
        line = r["line"].replace("|", "\\|")
        if len(line) > 220:
            line = line[:217] + "…"
        more = f" (+{r['lines'] - 1} lines)" if r["lines"] > 1 else ""
        note = f"; {r['note']}" if r["note"] else ""
        print(f"| {r['class']} | {r['case']} | {r['code']} | `{line}`{more} | {r['s']:.1f} | "
              f"{'kept' if r['ok'] else '**broken**'}{note} |")
    kept = sum(r["ok"] for r in ROWS)
    print(f"\n{kept} of {len(ROWS)} cases kept the contract.")


if __name__ == "__main__":
    main()
