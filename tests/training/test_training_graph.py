"""The static-shape training step (the one a CUDA graph captures) against the eager loop: on the
CPU it runs eagerly and must give the same parameters and losses, step for step, to the bit."""

import numpy as np
import pytest
import torch

from ultraboneudf.config import preset
from ultraboneudf.training import EpochSampler, Expansion, train, train_many
from ultraboneudf.training.graph import EpochDraw, LrSchedule, graph_capture_blocker
from ultraboneudf.training.samplers import learning_rate

from test_training_many import _data, _nets


def _cfg(name, kind="tangent"):
    cfg = preset(name)
    cfg.train.iters, cfg.train.batch, cfg.train.warmup, cfg.train.threads = 40, 200, 5, 1
    cfg.loss.kind = kind
    if name == "robust":
        cfg.loss.os_rows = 32          # L_OS rows drawn each step, after the anchors
    return cfg


def _same(a: torch.nn.Module, b: torch.nn.Module) -> bool:
    return all(torch.equal(p, q) for p, q in zip(a.parameters(), b.parameters()))


# fast: the epoch sampler over several passes, warm start, far term, 128 anchors drawn a step;
# robust: also L_OS rows drawn a step; official: the strided sampler, every anchor, broadcast L_GS;
# the pull and CAP-UDF losses (no expansion)
@pytest.mark.parametrize("name,kind", [("fast", "tangent"), ("robust", "tangent"), ("official", "tangent"),
                                       ("fast", "pull"), ("fast", "capudf")])
def test_the_static_step_equals_the_eager_step_step_for_step(name, kind):
    cfg = _cfg(name, kind)
    data = _data(0)
    runs = {}
    for static in (False, True):
        net = _nets(1)[0]
        runs[static] = net, train(net, data, cfg.loss, cfg.train, seed=3, log_every=1, static=static)
    (eager_net, eager), (static_net, static) = runs[False], runs[True]
    assert static.step == eager.step == "eager"          # the CPU never captures a graph
    assert static.history == eager.history                # every step's every term, to the bit
    assert len(static.history["total"]) == cfg.train.iters
    assert _same(static_net, eager_net)


def test_the_static_step_trains_several_scans_as_the_eager_loop():
    """K scans of different query, anchor and surface counts: one static step for all of them."""
    cfg = _cfg("robust")
    cfg.loss.os_rows = 0                                  # every surface point, padded with a mask
    datas, seeds = [_data(0), _data(1, bump=0.05)], [3, 4]
    eager_nets, eager = train_many(_nets(2), datas, cfg.loss, cfg.train, seeds, log_every=1, static=False)
    static_nets, static = train_many(_nets(2), datas, cfg.loss, cfg.train, seeds, log_every=1, static=True)
    for a, b, ra, rb in zip(eager_nets, static_nets, eager, static):
        assert rb.history == ra.history and _same(a, b)


def test_the_learning_rate_table_is_the_schedule():
    schedule = LrSchedule(2e-3, 7, 30, torch.device("cpu"))
    for i in range(30):
        schedule.advance()
        assert float(schedule.lr) == learning_rate(i, 2e-3, 7, 30)
    assert int(schedule.step) == 30


def test_the_epoch_draw_gives_the_samplers_rows():
    """Four passes of 1,000 queries in batches of 300 (one left over each pass)."""
    device = torch.device("cpu")
    sampler = EpochSampler(1000, 300, torch.Generator().manual_seed(5), device)
    draw = EpochDraw(EpochSampler(1000, 300, torch.Generator().manual_seed(5), device))
    for _ in range(12):
        draw.before()
        assert torch.equal(draw(), sampler())


def test_the_step_runs_eagerly_where_no_graph_can_be_captured():
    assert "CUDA device" in graph_capture_blocker(torch.device("cpu"))
    cfg = _cfg("fast")
    with pytest.raises(ValueError, match="expansion and checkpoints"):
        train(_nets(1)[0], _data(0), cfg.loss, cfg.train, 0, static=True,
              expansion=Expansion(10, 400, lambda net, data: data.static_targets))


@pytest.mark.gpu
@pytest.mark.parametrize("scans", [1, 3])
def test_the_cuda_graph_replays_the_eager_step(scans):
    """On CUDA the captured step replays what the eager step computes (the same draws from the
    same generators): the loss histories agree to float32 rounding; several scans in one graph."""
    cfg = _cfg("robust")
    cfg.train.iters = 60
    datas = [_data(k, bump=0.05 * k) for k in range(scans)]
    for d in datas:
        for name in ("surface", "queries", "anchors", "anchor_targets", "static_targets", "static_distance"):
            setattr(d, name, getattr(d, name).cuda())
    seeds = list(range(3, 3 + scans))
    histories = {}
    for static in (False, True):
        nets = [n.cuda() for n in _nets(scans)]
        if scans == 1:
            results = [train(nets[0], datas[0], cfg.loss, cfg.train, seeds[0], log_every=1, static=static)]
        else:
            _, results = train_many(nets, datas, cfg.loss, cfg.train, seeds, log_every=1, static=static)
        histories[static] = results
        assert {r.step for r in results} == {"cuda graph" if static else "eager"}
    for graphed, eager in zip(histories[True], histories[False]):
        assert graphed.history.keys() == eager.history.keys()
        for key in eager.history:
            np.testing.assert_allclose(graphed.history[key], eager.history[key], rtol=1e-3, atol=1e-6)


@pytest.mark.gpu
def test_a_step_that_cannot_be_captured_runs_eagerly_and_says_why(monkeypatch):
    """A host read inside the step (here planted) makes the capture fail: the run goes on eagerly
    from that step, with the same result, and names the reason."""
    from ultraboneudf.training import loop

    real = loop.loss_terms

    def reads_back(*args, **kwargs):
        terms = real(*args, **kwargs)
        float(terms["total"].sum())                       # a host read: not allowed in a capture
        return terms

    cfg = _cfg("fast")
    data = _data(0)
    for name in ("surface", "queries", "anchors", "anchor_targets", "static_targets", "static_distance"):
        setattr(data, name, getattr(data, name).cuda())
    eager = train(_nets(1)[0].cuda(), data, cfg.loss, cfg.train, 3, log_every=1, static=False)
    monkeypatch.setattr(loop, "loss_terms", reads_back)
    failed = train(_nets(1)[0].cuda(), data, cfg.loss, cfg.train, 3, log_every=1, static=True)
    assert failed.step.startswith("eager (the CUDA graph capture failed")
    for key in eager.history:
        np.testing.assert_allclose(failed.history[key], eager.history[key], rtol=1e-3, atol=1e-6)


def test_the_sidecar_names_the_schedule_and_how_the_steps_ran():
    """A run with the GPU budget (here on the CPU, as a GPU session checks accuracy without one)."""
    import ultraboneudf

    rng = np.random.default_rng(0)
    theta = rng.uniform(np.pi / 4, 3 * np.pi / 4, 2000)
    cloud = np.c_[20 * np.cos(theta), rng.uniform(0, 30, 2000), 20 * np.sin(theta)]
    small = {"train.iters": 40, "train.batch": 16, "extract.max_depth": 5, "model.hidden": (32, 32)}
    cpu = ultraboneudf.reconstruct(cloud, preset="fast", device="cpu", seed=0, **small)
    gpu = ultraboneudf.reconstruct(cloud, preset="fast", device="cpu", seed=0, train__budget="gpu", **small)
    assert cpu.method_info == {"budget": "cpu", "iters": 40, "batch": 16, "lr": 2e-3, "warmup": 400,
                               "gs_anchors": 128, "os_rows": 0, "train_step": "eager", "train_threads": 1}
    assert {k: gpu.method_info[k] for k in ("budget", "iters", "batch", "lr", "gs_anchors")} == \
        {"budget": "gpu", "iters": 10, "batch": 256, "lr": 4e-3, "gs_anchors": 512}
    assert len(gpu.history["total"]) == 2 and gpu.sidecar()["config"]["train"]["iters"] == 40
