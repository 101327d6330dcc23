"""A result is put in place as a unit: a signal right after any file operation of the commit leaves
either the earlier result or the new one, complete, and never a temporary file; a process killed
outright leaves a journal that the next commit undoes or finishes."""

import json
import os
import signal
import subprocess
import sys
import textwrap

import pytest

from ultraboneudf.io import Commit, WriteError, commit as commit_module
from ultraboneudf.io.commit import recover


def _state(folder):
    """``{relative path: bytes}`` of every file under ``folder`` (folders as ``/``-ended names)."""
    out = {}
    for root, dirs, files in os.walk(folder):
        for name in dirs:
            out[os.path.relpath(os.path.join(root, name), folder) + "/"] = None
        for name in files:
            path = os.path.join(root, name)
            with open(path, "rb") as fh:
                out[os.path.relpath(path, folder)] = fh.read()
    return out


_CHILD = textwrap.dedent("""
    import os, signal, sys
    from pathlib import Path
    from ultraboneudf.io import commit
    from ultraboneudf.cli import _signals_raise, Terminated

    stop, sig, folder, fresh = int(sys.argv[1]), getattr(signal, sys.argv[2]), Path(sys.argv[3]), sys.argv[4] == "1"
    signal.signal(signal.SIGINT, signal.default_int_handler)   # a background runner may ignore it
    steps = []

    def hook(what):
        steps.append(what)
        if len(steps) == stop:
            os.kill(os.getpid(), sig)

    commit._STEP_HOOK = hook
    code = 0
    try:
        with _signals_raise(), commit.Commit() as c:
            c.write(folder / "bone.ply", b"new mesh")
            c.write(folder / "bone.ply.json", b"new sidecar")
            c.remove(folder / "bone.ply.ckpt")
            sweep = c.folder(folder / "sweep")
            (sweep / "frame.png").write_bytes(b"new frame")
            c.commit()
    except KeyboardInterrupt:
        code = 130
    except Terminated as exc:
        code = 128 + exc.signum
    print(len(steps), file=sys.stderr)
    sys.exit(code)
""")


def _earlier(folder):
    (folder / "bone.ply").write_bytes(b"old mesh")
    (folder / "bone.ply.json").write_bytes(b"old sidecar")
    (folder / "bone.ply.ckpt").write_bytes(b"old checkpoint")
    (folder / "sweep").mkdir()
    (folder / "sweep" / "frame.png").write_bytes(b"old frame")
    (folder / "sweep" / "old_only.png").write_bytes(b"old frame 2")


NEW = {"bone.ply": b"new mesh", "bone.ply.json": b"new sidecar", "sweep/": None, "sweep/frame.png": b"new frame"}


def _run(tmp_path, stop, sig, fresh):
    folder = tmp_path / f"out{stop}{sig}{fresh}"
    folder.mkdir()
    if not fresh:
        _earlier(folder)
    before = _state(folder)
    res = subprocess.run([sys.executable, "-c", _CHILD, str(stop), sig, str(folder), "1" if fresh else "0"],
                         capture_output=True, text=True, timeout=60)
    return folder, before, res


@pytest.mark.parametrize("fresh", [True, False], ids=["new", "replacing"])
@pytest.mark.parametrize("sig", ["SIGINT", "SIGTERM"])
def test_a_signal_after_every_step_leaves_the_earlier_or_the_new_result(tmp_path, sig, fresh):
    folder, before, res = _run(tmp_path, 0, sig, fresh)        # no signal: count the steps
    assert res.returncode == 0, res.stderr
    steps = int(res.stderr.split()[-1])
    assert _state(folder) == NEW and steps >= (8 if fresh else 14)
    outcomes = set()
    for stop in range(1, steps + 1):
        folder, before, res = _run(tmp_path, stop, sig, fresh)
        code = 128 + getattr(signal, sig)
        assert res.returncode == code, (stop, res.stderr)
        after = _state(folder)
        assert after in (before, NEW), (stop, sorted(after))      # never a mix, never a temporary
        outcomes.add("new" if after == NEW else "earlier")
    assert outcomes == {"new", "earlier"}     # the signal lands before and after the moment it counts


_KILLED = _CHILD.replace("os.kill(os.getpid(), sig)", "os.kill(os.getpid(), signal.SIGKILL)")


@pytest.mark.parametrize("fresh", [True, False], ids=["new", "replacing"])
def test_a_process_killed_outright_is_undone_or_finished_by_the_next_commit(tmp_path, fresh):
    """SIGKILL cannot be held: after it the folder may hold staged files and a journal; the next
    commit into that folder (or the check before a run) puts the earlier or the new result back whole."""
    steps = int(_run(tmp_path, 0, "SIGINT", fresh)[2].stderr.split()[-1])
    for stop in range(1, steps + 1):
        folder = tmp_path / f"killed{stop}{fresh}"
        folder.mkdir()
        if not fresh:
            _earlier(folder)
        before = _state(folder)
        res = subprocess.run([sys.executable, "-c", _KILLED, str(stop), "SIGINT", str(folder),
                              "1" if fresh else "0"], capture_output=True, timeout=60)
        assert res.returncode == -signal.SIGKILL
        recover(folder)
        assert _state(folder) in (before, NEW), (stop, sorted(_state(folder)))


def test_a_full_disk_puts_the_earlier_files_back(tmp_path, monkeypatch):
    """A rename that fails half-way through (the file system refuses) undoes the renames before it."""
    _earlier(tmp_path)
    before = _state(tmp_path)
    real = os.replace

    def replace(src, dst):
        if str(dst).endswith(".json"):
            raise OSError(28, "No space left on device")
        real(src, dst)

    monkeypatch.setattr(os, "replace", replace)
    with pytest.raises(WriteError, match="No space left on device"), Commit() as c:
        c.write(tmp_path / "bone.ply", b"new mesh")
        c.write(tmp_path / "bone.ply.json", b"new sidecar")
        c.commit()
    assert _state(tmp_path) == before


def test_staged_files_of_a_dead_process_are_removed_and_a_live_ones_kept(tmp_path):
    """Only this machine's: on storage shared by a cluster another machine's process ids mean nothing here."""
    from ultraboneudf.io.commit import _HOST

    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True,
                          text=True).stdout.strip()
    (tmp_path / f".bone.ply.{dead}-{_HOST}-0a1b2c3d.ubtmp").write_bytes(b"half")
    kept = [f".bone.ply.{os.getpid()}-{_HOST}-0a1b2c3d.ubtmp", f".bone.ply.{dead}-ffffff-0a1b2c3d.ubtmp",
            "notes.ubtmp"]
    for name in kept:
        (tmp_path / name).write_bytes(b"being written, or a user's file")
    recover(tmp_path)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(kept)


def test_a_journal_marked_done_is_finished(tmp_path):
    """Killed after the moment the new result counts: its backups are dropped, nothing restored."""
    from ultraboneudf.io.commit import _HOST

    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True,
                          text=True).stdout.strip()
    (tmp_path / "bone.ply").write_bytes(b"new")
    backup = tmp_path / f".bone.ply.{dead}-{_HOST}-00000000.ubold"
    backup.write_bytes(b"old")
    entry = {"target": str(tmp_path / "bone.ply"), "staged": str(tmp_path / f".bone.ply.{dead}-{_HOST}-1.ubtmp"),
             "backup": str(backup), "existed": True}
    (tmp_path / f".ultraboneudf-commit.{dead}-{_HOST}-00000000.done").write_text(json.dumps([entry]))
    recover(tmp_path)
    assert _state(tmp_path) == {"bone.ply": b"new"}


def test_leaving_the_block_without_commit_removes_what_was_staged(tmp_path):
    with pytest.raises(RuntimeError), Commit() as c:
        c.write(tmp_path / "a.txt", b"a")
        c.folder(tmp_path / "d")
        raise RuntimeError
    assert list(tmp_path.iterdir()) == []
    assert commit_module._STEP_HOOK is None
