"""A killed training run resumes from its checkpoint and ends where the uninterrupted run ends."""

import json
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import torch

from ultraboneudf import checkpoints
from ultraboneudf.checkpoints import Checkpoint
from ultraboneudf.config import preset
from ultraboneudf.errors import InputError
from ultraboneudf.fields.mlp import DistanceMLP
from ultraboneudf.geometry.queries import anchors, gaussian_queries, grid_queries, query_spread
from ultraboneudf.progress import Progress
from ultraboneudf.training import TrainingData, train


def _data():
    rng = np.random.default_rng(3)
    xy = rng.uniform(-0.4, 0.4, (800, 2))
    surface = np.c_[xy, 0.1 + 0.05 * np.sin(6 * xy[:, 0])]
    queries = np.concatenate([gaussian_queries(surface, query_spread(surface, 50), 20, rng),
                              grid_queries(1000, rng)])
    a, t = anchors(surface, "official", 10, True, 0.1)
    f = lambda v: torch.as_tensor(v, dtype=torch.float32)  # noqa: E731
    d = TrainingData(surface=f(surface), queries=f(queries), anchors=f(a), anchor_targets=f(t))
    d.set_nearest_targets()
    return d


def _net():
    return DistanceMLP((32, 64, 64), radius=0.1, generator=torch.Generator().manual_seed(5))


class _Killed(Exception):
    pass


class _KillAt(Progress):
    """A progress whose training stage stops the run (as a signal would) after ``steps`` steps."""

    def __init__(self, steps):
        super().__init__(quiet=True)
        self.steps = steps

    def stage(self, description, total=None, start=0):
        from contextlib import contextmanager

        @contextmanager
        def killing():
            done = [0]

            def advance(n=1):
                done[0] += n
                if done[0] >= self.steps:
                    raise _Killed
            yield advance
        return killing()


@pytest.mark.parametrize("sampler,warm", [("epoch", 0.1), ("strided", 0.0)])
def test_a_killed_and_resumed_run_equals_the_uninterrupted_one(tmp_path, sampler, warm):
    cfg = preset("fast")
    cfg.train.iters, cfg.train.batch, cfg.train.warmup, cfg.train.sampler = 240, 300, 20, sampler
    cfg.loss.warm_start, cfg.loss.lambda_os, cfg.loss.os_rows = warm, 10.0, 64
    whole = _net()
    ref = train(whole, _data(), cfg.loss, cfg.train, seed=7, log_every=10)

    ckpt = Checkpoint(tmp_path / "run.ckpt", every=50)
    first = _net()
    with pytest.raises(_Killed):
        train(first, _data(), cfg.loss, cfg.train, seed=7, log_every=10, checkpoint=ckpt, progress=_KillAt(130))
    saved = checkpoints.read(ckpt.path)
    assert saved["step"] == 100                                  # the last save before the kill

    again = _net()                                               # a new process: fresh weights
    res = train(again, _data(), cfg.loss, cfg.train, seed=7, log_every=10,
                checkpoint=Checkpoint(ckpt.path, every=50, resume=True))
    for a, b in zip(whole.state_dict().values(), again.state_dict().values()):
        assert torch.equal(a, b)
    assert res.history["total"] == pytest.approx(ref.history["total"], rel=0, abs=0)   # continuous
    assert len(res.history["total"]) == len(ref.history["total"])


def test_a_checkpoint_of_another_run_is_refused(tmp_path):
    cfg = preset("fast")
    cfg.train.iters, cfg.train.batch, cfg.train.warmup = 60, 300, 5
    ckpt = Checkpoint(tmp_path / "run.ckpt", every=20)
    train(_net(), _data(), cfg.loss, cfg.train, seed=7, checkpoint=ckpt)
    assert ckpt.path.exists()                                    # saved at 20 and 40 (not at the end)
    with pytest.raises(InputError, match="made by another run"):
        train(_net(), _data(), cfg.loss, cfg.train, seed=8, checkpoint=Checkpoint(ckpt.path, resume=True))
    ckpt.path.write_bytes(b"not a checkpoint")
    with pytest.raises(InputError, match="not a training checkpoint of ultraboneudf"):
        train(_net(), _data(), cfg.loss, cfg.train, seed=7, checkpoint=Checkpoint(ckpt.path, resume=True))


def _cloud(path):
    rng = np.random.default_rng(0)
    theta = rng.uniform(np.pi / 4, 3 * np.pi / 4, 3000)
    np.savetxt(path, np.c_[20 * np.cos(theta), rng.uniform(0, 40, 3000), 20 * np.sin(theta)])
    return path


def test_cli_run_killed_by_sigterm_resumes_to_the_same_mesh(tmp_path):
    src = _cloud(tmp_path / "in.xyz")
    common = ["reconstruct", str(src), "--preset", "fast", "--iters", "1500", "--set", "train.threads=1",
              "--set", "extract.max_depth=7"]
    cli = [sys.executable, "-m", "ultraboneudf.cli"]
    out = tmp_path / "whole.ply"
    assert subprocess.run([*cli, *common, "-o", str(out), "--quiet"], capture_output=True).returncode == 0

    killed = tmp_path / "resumed.ply"
    ckpt = tmp_path / "resumed.ply.ckpt"
    proc = subprocess.Popen([*cli, *common, "-o", str(killed), "--checkpoint-every", "200", "--quiet"],
                            stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 300
    while not ckpt.exists() and time.time() < deadline and proc.poll() is None:
        time.sleep(0.05)
    assert proc.poll() is None, "the run ended before its first checkpoint"
    proc.send_signal(signal.SIGTERM)
    proc.wait(timeout=60)
    assert proc.returncode != 0 and ckpt.exists() and not killed.exists()

    res = subprocess.run([*cli, *common, "-o", str(killed), "--checkpoint-every", "200", "--resume"],
                         capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    assert "resumed from" in res.stderr and not ckpt.exists()     # removed once the mesh is written
    assert killed.read_bytes() == out.read_bytes()
    side = json.loads((tmp_path / "resumed.ply.json").read_text())
    whole = json.loads((tmp_path / "whole.ply.json").read_text())
    assert side["loss_history"] == whole["loss_history"] and len(side["loss_history"]["total"]) == 16


def test_methods_without_the_shared_loop_refuse_checkpoints_before_any_work(tmp_path):
    src = _cloud(tmp_path / "in.xyz")
    for method in ("funsr", "poisson"):
        res = subprocess.run([sys.executable, "-m", "ultraboneudf.cli", "reconstruct", str(src), "-o",
                              str(tmp_path / "o.ply"), "--method", method, "--checkpoint-every", "10"],
                             capture_output=True, text=True)
        assert res.returncode == 2 and f"method {method} cannot checkpoint its training" in res.stderr
        assert len(res.stderr.strip().splitlines()) == 1


@pytest.mark.parametrize("stage,sweep,sig", [
    pytest.param(stage, sweep, sig, id=f"{stage}-{sig.name}")
    for stage, sweep, sig in [("read frames", True, signal.SIGINT), ("segment", True, signal.SIGINT),
                              ("training", False, signal.SIGINT), ("UDF clean", False, signal.SIGINT),
                              ("read frames", True, signal.SIGTERM), ("UDF clean", False, signal.SIGTERM)]])
def test_a_signal_at_each_stage_leaves_no_output(tmp_path, stage, sweep, sig):
    """SIGINT (Ctrl-C) or SIGTERM (a scheduler, a shutdown) as soon as a stage reports: exit 128 + the
    signal's number and one line; neither mesh nor sidecar nor a stray temporary."""
    import os

    from ultraboneudf.sweep import Sweep, write_sweep
    from ultraboneudf.sweep.transforms import rigid_from_euler

    if sweep:
        n = 150
        masks = np.zeros((n, 120, 160), dtype=bool)
        masks[:, 60, 20:140] = True
        images = (masks * 200 + 20).astype(np.uint8)
        poses = np.stack([rigid_from_euler([0, 0, 0.5 * i], [0, 0, 0]) for i in range(n)])  # 0.5 mm apart along z
        src = tmp_path / "sweep"
        write_sweep(Sweep(image_to_world=poses, spacing_mm=0.2, image_size=(160, 120), images=images,
                          pixel_offset=0.5), src)          # no masks: the classical detector segments
    else:
        src = _cloud(tmp_path / "in.xyz")
    out = tmp_path / "out" / "bone.ply"
    out.parent.mkdir()
    env = {**os.environ, "ULTRABONEUDF_PROGRESS_S": "0"}
    proc = subprocess.Popen([sys.executable, "-m", "ultraboneudf.cli", "reconstruct", str(src), "-o", str(out),
                             "--preset", "fast", "--iters", "300", "--set", "extract.min_leaf_mm=0",
                             "--set", "extract.max_depth=9"],
                            stderr=subprocess.PIPE, text=True, env=env,
                            # a runner started in the background hands its children SIGINT ignored
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    seen = []
    for line in proc.stderr:
        seen.append(line)
        if line.startswith(f"{stage}:"):
            proc.send_signal(sig)
            break
    rest = proc.communicate(timeout=120)[1]
    assert any(s.startswith(f"{stage}:") for s in seen), "".join(seen)[-2000:]
    assert proc.returncode == 128 + sig, "".join(seen) + rest
    assert ("interrupted" if sig == signal.SIGINT else "stopped by SIGTERM") in rest and "Traceback" not in rest
    assert list(out.parent.iterdir()) == []
