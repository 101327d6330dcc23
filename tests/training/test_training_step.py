"""The optimised training step (hand-written input gradient, fused Adam) against the plain one
(autograd double backward, default Adam), and the cheap batch draws of the ``fast`` preset."""

import numpy as np
import pytest
import torch

from ultraboneudf.config import preset
from ultraboneudf.errors import InputError
from ultraboneudf.fields.mlp import DistanceMLP, value_and_grad
from ultraboneudf.geometry.queries import anchors, gaussian_queries, grid_queries, query_spread
from ultraboneudf.training import EpochSampler, TrainingData, train


@pytest.mark.parametrize("skip,abs_output", [((), True), ((2,), True), ((3,), False), ((3,), True)])
def test_explicit_input_gradient_equals_autograd_to_second_order(skip, abs_output):
    net = DistanceMLP((32, 64, 64), skip=skip, abs_output=abs_output,
                      generator=torch.Generator().manual_seed(0)).double()
    x = torch.randn(300, 3, dtype=torch.float64) * 0.5
    u1, g1 = value_and_grad(net, x.clone(), create_graph=True, explicit=False)
    u2, g2 = value_and_grad(net, x.clone(), create_graph=True, explicit=True)
    torch.testing.assert_close(u2, u1, rtol=0, atol=1e-14)
    torch.testing.assert_close(g2, g1, rtol=0, atol=1e-13)
    # a loss of the gradient differentiated in the weights: the double-backward path of training
    p1 = torch.autograd.grad((g1.square().sum(1) - 1).abs().mean() + u1.mean(), list(net.parameters()))
    p2 = torch.autograd.grad((g2.square().sum(1) - 1).abs().mean() + u2.mean(), list(net.parameters()))
    for a, b in zip(p1, p2):
        torch.testing.assert_close(b, a, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("skip", [(), (2,)])
def test_one_sweep_over_all_rows_equals_separate_evaluations(skip):
    """The step's value-only rows (anchors, surface points) ride on the queries' forward sweep:
    values, input gradients of the first rows and the weight gradients of a loss on both equal
    separate evaluations (float64: to rounding)."""
    from ultraboneudf.training.scans import OneScan, evaluate_rows

    net = DistanceMLP((32, 64, 64), skip=skip, generator=torch.Generator().manual_seed(2)).double()
    gen = torch.Generator().manual_seed(3)
    q, a, s = (torch.randn(n, 3, generator=gen, dtype=torch.float64) * 0.5 for n in (40, 25, 30))
    u1, g1 = value_and_grad(net, q.clone(), create_graph=True)
    ua1, us1 = net(a), net(s)
    model = OneScan(net)
    u2, g2, (ua2, us2) = evaluate_rows(model, q[None], [a[None], s[None]], model.weights())
    assert u2.shape == (1, 40) and g2.shape == (1, 40, 3) and ua2.shape == (1, 25) and us2.shape == (1, 30)
    for mine, theirs in ((u2[0], u1), (g2[0], g1), (ua2[0], ua1), (us2[0], us1)):
        torch.testing.assert_close(mine, theirs, rtol=0, atol=1e-13)
    def loss(u, g, ua, us):
        return (g.square().sum(1) - 1).abs().mean() + u.mean() + ua.square().mean() + us.abs().mean()
    p1 = torch.autograd.grad(loss(u1, g1, ua1, us1), list(net.parameters()))
    p2 = torch.autograd.grad(loss(u2[0], g2[0], ua2[0], us2[0]), list(net.parameters()))
    for x, y in zip(p1, p2):
        torch.testing.assert_close(y, x, rtol=1e-10, atol=1e-12)


def test_explicit_gradient_without_graph_is_detached():
    net = DistanceMLP((16, 16), generator=torch.Generator().manual_seed(1))
    u, g = value_and_grad(net, torch.randn(10, 3), create_graph=False)
    assert not u.requires_grad and not g.requires_grad and g.shape == (10, 3)


def _plane_data(seed=0):
    """A 40×40 patch of the plane z = 0.1 in unit space with the preset's query recipe."""
    rng = np.random.default_rng(seed)
    surface = np.c_[rng.uniform(-0.5, 0.5, (1600, 2)), np.full(1600, 0.1)]
    sigma = query_spread(surface, 50)
    queries = np.concatenate([gaussian_queries(surface, sigma, 20, rng), grid_queries(2000, rng)])
    a, t = anchors(surface, "official", 10, True, 0.1)
    f = lambda v: torch.as_tensor(v, dtype=torch.float32)  # noqa: E731
    return TrainingData(surface=f(surface), queries=f(queries), anchors=f(a), anchor_targets=f(t))


@pytest.mark.parametrize("tangent_norm", ["l1", "l2"])
def test_optimised_and_plain_steps_give_the_same_losses_for_50_iterations(tangent_norm):
    data = _plane_data()
    histories = {}
    for step in ("plain", "optimised"):
        cfg = preset("official")
        cfg.loss.tangent_norm, cfg.loss.gs_form = tangent_norm, "per_anchor"
        cfg.train.iters, cfg.train.batch, cfg.train.warmup, cfg.train.step = 50, 500, 5, step
        net = DistanceMLP((64, 128, 128), generator=torch.Generator().manual_seed(4))
        histories[step] = train(net, data, cfg.loss, cfg.train, seed=7, log_every=1).history
    plain, opt = histories["plain"], histories["optimised"]
    assert len(plain["total"]) == 50
    # fp32: the two steps differ only in summation order (fused vs. foreach Adam, mm vs. autograd's mm)
    np.testing.assert_allclose(opt["total"], plain["total"], rtol=2e-4, atol=1e-7)
    np.testing.assert_allclose(opt["gs"], plain["gs"], rtol=2e-4, atol=1e-7)
    assert opt["total"][-1] < 0.5 * opt["total"][0]   # and it trains


def test_epoch_sampler_sees_every_query_once_per_pass():
    s = EpochSampler(1000, 300, torch.Generator().manual_seed(0), torch.device("cpu"))
    first = torch.cat([s() for _ in range(3)])          # 900 of the first permutation
    assert len(torch.unique(first)) == 900
    fourth = s()                                         # 100 left < 300: a new permutation
    assert len(fourth) == 300 and len(torch.unique(fourth)) == 300
    assert int(first.max()) < 1000 and int(fourth.max()) < 1000


def test_anchor_subset_and_unknown_choices():
    data = _plane_data()
    cfg = preset("fast")
    cfg.train.iters, cfg.train.batch, cfg.train.warmup = 20, 200, 2
    cfg.loss.gs_anchors, cfg.loss.warm_start, cfg.loss.lambda_far = 16, 0.0, 0.0
    net = DistanceMLP((32, 32), generator=torch.Generator().manual_seed(0))
    hist = train(net, data, cfg.loss, cfg.train, seed=0, log_every=1).history
    assert len(hist["gs"]) == 20 and all(np.isfinite(hist["gs"]))
    cfg.train.sampler = "shuffled"
    with pytest.raises(InputError, match="unknown train.sampler"):
        train(net, data, cfg.loss, cfg.train, seed=0)
    cfg.train.sampler, cfg.train.step = "epoch", "compiled"
    with pytest.raises(InputError, match="unknown train.step"):
        train(net, data, cfg.loss, cfg.train, seed=0)


def test_warm_start_regresses_the_static_distance_first():
    data = _plane_data()
    cfg = preset("fast")
    cfg.train.iters, cfg.train.batch, cfg.train.warmup, cfg.train.lr = 200, 250, 10, 5e-3
    cfg.loss.warm_start, cfg.loss.lambda_far = 0.5, 0.0
    net = DistanceMLP((32, 32), generator=torch.Generator().manual_seed(0))
    with pytest.raises(ValueError, match="static distances"):
        train(net, data, cfg.loss, cfg.train, seed=0)
    data.set_nearest_targets()
    hist = train(net, data, cfg.loss, cfg.train, seed=0, log_every=1).history
    assert len(hist["warm"]) == 100 and len(hist["tangent"]) == 100
    assert hist["warm"][-1] < 0.5 * hist["warm"][0]
    # after the warm start the field vanishes on the plane and grows off it like the distance
    x = torch.tensor([[0.0, 0.0, 0.1], [0.2, -0.1, 0.1], [0.0, 0.0, 0.25], [0.1, 0.1, -0.05]])
    u = net(x).detach()
    assert float(u[:2].max()) < 0.03 and abs(float(u[2]) - 0.15) < 0.05 and abs(float(u[3]) - 0.15) < 0.05


def test_far_term_is_the_static_distance_error_beyond_the_threshold():
    from ultraboneudf.geometry.neighbors import NearestIndex
    from ultraboneudf.training import OneScan, StepDraw, loss_terms

    data = _plane_data()
    index = NearestIndex(data.surface)
    data.set_nearest_targets()
    cfg = preset("fast").loss
    cfg.lambda_far, cfg.far_threshold, cfg.lambda_gs = 2.0, 0.05, 0.0
    net = DistanceMLP((16, 16), generator=torch.Generator().manual_seed(2))
    batch = torch.arange(0, 4000, 7)
    q = data.queries[batch]
    terms = {k: v[0] for k, v in loss_terms(OneScan(net), [data], StepDraw([batch]), cfg, [index], None, None).items()}
    d = (q - data.static_targets[batch]).norm(dim=1)
    far = d > 0.05
    assert 0 < int(far.sum()) < len(q)
    expected = ((net(q) - d).abs() * far).sum() / len(q)
    torch.testing.assert_close(terms["far"], expected.detach(), rtol=1e-5, atol=1e-7)
    torch.testing.assert_close(terms["total"], terms["tangent"] + 2.0 * terms["far"])


def test_broadcast_global_shape_loss_is_the_reference_mse_and_its_closed_form():
    """The reference's ``nn.MSELoss()(u (G, 1), t (G,))`` broadcasts to G × G pairs."""
    import warnings

    from ultraboneudf.training.losses import global_shape_loss

    g = torch.Generator().manual_seed(0)
    u, t = torch.rand(50, generator=g), torch.rand(50, generator=g) ** 2
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)   # PyTorch warns about the broadcast
        reference = torch.nn.MSELoss()(u[:, None], t)
    torch.testing.assert_close(global_shape_loss(u, t, "broadcast"), reference)
    closed = ((u - t.mean()) ** 2).mean() + ((t - t.mean()) ** 2).mean()
    torch.testing.assert_close(global_shape_loss(u, t, "broadcast"), closed)
    torch.testing.assert_close(global_shape_loss(u, t, "per_anchor"), ((u - t) ** 2).mean())
    assert float(global_shape_loss(t, t, "per_anchor")) == 0.0 < float(global_shape_loss(t, t, "broadcast"))
    with pytest.raises(ValueError, match="form"):
        global_shape_loss(u, t, "pairs")


def test_training_threads_are_restored():
    from ultraboneudf.training import cpu_threads

    before = torch.get_num_threads()
    with cpu_threads(1):
        assert torch.get_num_threads() == 1
    assert torch.get_num_threads() == before
    with pytest.raises(RuntimeError):
        with cpu_threads(1):
            raise RuntimeError("boom")
    assert torch.get_num_threads() == before


def test_training_threads_never_exceed_the_process_setting():
    """A preset's thread count is an upper bound: a process limited to one thread (a benchmark's
    ``--threads 1``, ``OMP_NUM_THREADS=1``) trains on one, and the sidecar says so."""
    import ultraboneudf
    from ultraboneudf.training import cpu_threads

    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        with cpu_threads(2) as used:
            assert used == torch.get_num_threads() == 1
        rng = np.random.default_rng(0)
        theta = rng.uniform(np.pi / 4, 3 * np.pi / 4, 1500)
        cloud = np.c_[20 * np.cos(theta), rng.uniform(0, 30, 1500), 20 * np.sin(theta)]
        rec = ultraboneudf.reconstruct(cloud, device="cpu", seed=0, train__iters=20, extract__max_depth=5)
        assert rec.config.train.threads == 2 and rec.method_info["train_threads"] == 1
    finally:
        torch.set_num_threads(before)
    with cpu_threads(before + 1) as used:
        assert used == before


def test_subnormals_are_flushed_on_the_cpu_inside_the_block_only():
    """FUNSR's discriminator drives Adam's second moments below float32's normal range, where a CPU
    computes many times slower; the block flushes them to zero and leaves the default (kept) after,
    also when the block raises."""
    from ultraboneudf.training import flush_denormals

    tiny = torch.tensor([1e-30], dtype=torch.float32)
    if not torch.set_flush_denormal(False):
        pytest.skip("this CPU cannot flush subnormals")
    assert float(tiny * 1e-10) > 0.0  # 1e-40: subnormal, kept by default
    with flush_denormals(torch.device("cpu")):
        assert float(tiny * 1e-10) == 0.0
    assert float(tiny * 1e-10) > 0.0
    with pytest.raises(RuntimeError):
        with flush_denormals(torch.device("cpu")):
            raise RuntimeError("boom")
    assert float(tiny * 1e-10) > 0.0


def test_a_diverging_loss_stops_training_naming_the_step_and_the_setting():
    """A loss that is no longer finite (here from anchor targets at infinity) stops the loop at the
    next recorded step with one message, instead of training on NaN."""
    from ultraboneudf.errors import InputError

    data = _plane_data()
    data.anchor_targets[:] = float("inf")
    cfg = preset("fast")
    cfg.train.iters, cfg.train.batch, cfg.train.lr = 300, 4000, 2e-3
    cfg.loss.warm_start, cfg.loss.lambda_far = 0.0, 0.0
    net = DistanceMLP((16, 16), generator=torch.Generator().manual_seed(0))
    with pytest.raises(InputError, match=r"training diverged: the loss is not finite at step 1 of 300; "
                                         r"lower train.lr \(now 0.002\)"):
        train(net, data, cfg.loss, cfg.train, seed=0)
