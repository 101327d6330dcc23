import math

import pytest
import torch

from ultraboneudf.fields.mlp import DistanceMLP, MLPField, count_parameters, value_and_grad
from ultraboneudf.training import StridedSampler, learning_rate

WIDTHS = [64, 128, 128, 256, 256, 256, 256, 256, 256, 256]


def test_official_network_has_191042_parameters():
    assert count_parameters(DistanceMLP()) == 191_042
    assert count_parameters(DistanceMLP(weight_norm=False)) == 189_953


@pytest.mark.parametrize("depth,count", [(2, 8_898), (3, 25_538), (4, 58_946), (5, 124_994), (6, 191_042),
                                         (7, 257_090), (8, 323_138), (9, 389_186), (10, 455_234)])
def test_depth_rule_parameter_counts(depth, count):
    assert count_parameters(DistanceMLP(tuple(WIDTHS[:depth]))) == count


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_geometric_init_is_roughly_a_sphere_sdf(seed):
    x = torch.randn(4000, 3) * 0.4
    signed = DistanceMLP(abs_output=False, generator=torch.Generator().manual_seed(seed))(x).detach()
    # before the absolute value the output grows with ‖x‖ like ‖x‖ − 0.5 (IGR initialisation)
    assert torch.corrcoef(torch.stack([signed, x.norm(dim=1)]))[0, 1] > 0.85
    assert (signed - (x.norm(dim=1) - 0.5)).abs().mean() < 0.25
    unsigned = DistanceMLP(generator=torch.Generator().manual_seed(seed))(x).detach()
    torch.testing.assert_close(unsigned, signed.abs())


def test_weight_norm_leaves_initial_function_unchanged():
    gen = torch.Generator().manual_seed(3)
    a = DistanceMLP(weight_norm=True, generator=gen)
    b = DistanceMLP(weight_norm=False, generator=torch.Generator().manual_seed(3))
    x = torch.randn(100, 3)
    torch.testing.assert_close(a(x), b(x), rtol=1e-5, atol=1e-6)


def test_value_and_grad_matches_finite_differences():
    net = DistanceMLP(generator=torch.Generator().manual_seed(1)).double()
    # seeded: a central difference that straddles a ReLU kink would fail by chance
    x = torch.randn(20, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(5)) * 0.3
    u, g = value_and_grad(net, x.clone(), create_graph=False)
    eps = 1e-6
    for k in range(3):
        dx = torch.zeros(3, dtype=torch.float64)
        dx[k] = eps
        fd = (net(x + dx) - net(x - dx)) / (2 * eps)
        torch.testing.assert_close(g[:, k], fd.detach(), rtol=1e-4, atol=1e-6)
    field = MLPField(net)
    u2, g2 = field.value_and_grad(x, chunk=7)
    torch.testing.assert_close(u2, u.detach())
    torch.testing.assert_close(g2, g)


def test_learning_rate_values_of_appendix_c():
    lr = lambda i: learning_rate(i, 1e-3, 1_000, 30_000)  # noqa: E731
    assert lr(0) == 0.0
    assert math.isclose(lr(500), 5e-4)
    assert math.isclose(lr(1_000), 1e-3)
    assert math.isclose(lr(15_500), 5e-4)
    assert 0 < lr(29_999) < 1e-11 and math.isclose(lr(29_999), 2.93e-12, rel_tol=0.01)


def test_strided_sampler_one_residue_distinct_rows():
    gen = torch.Generator().manual_seed(0)
    s = StridedSampler(430_000, 5_000, gen, torch.device("cpu"))
    assert s.rows == 42_999
    seen = set()
    for _ in range(30):
        idx = s()
        assert len(idx) == 5_000 and len(torch.unique(idx)) == 5_000
        residues = torch.unique(idx % 10)
        assert len(residues) == 1
        seen.add(int(residues))
        assert int(idx.max()) < 429_990
    assert len(seen) > 5
