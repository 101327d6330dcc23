"""The method registry, each method's defaults, the baselines' networks (Appendix C parameter
counts), losses, sampling and normals. Training runs live in test_baselines.py beside it."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from ultraboneudf.config import DEPTH_WIDTHS, PRESETS, Config, apply_overrides, model_widths, preset
from ultraboneudf.errors import InputError
from ultraboneudf.fields.mlp import DistanceMLP, count_parameters
from ultraboneudf.training.losses import (consistency_chamfer_loss, lsgan_discriminator_loss, lsgan_generator_loss,
                                 pull_loss, sign_consistency_loss)
from ultraboneudf.methods import METHODS, get_method
from ultraboneudf.methods.capudf import capudf_samples, even_subsample
from ultraboneudf.methods.funsr import Discriminator
from ultraboneudf.geometry.normals import orient_tangent_plane, orient_toward, pca_normals
from ultraboneudf.methods.ultraboneudf import build_network

ALL = ("ultraboneudf", "capudf", "funsr", "carotidudf", "poisson", "vanilla_udf", "ultraboneudf_pull")


def configured(method: str, preset_name: str = "official") -> Config:
    cfg = preset(preset_name)
    get_method(method).configure(cfg)
    return cfg


def test_registry_has_every_method_of_the_issue():
    assert set(METHODS) == set(ALL)
    with pytest.raises(InputError, match="unknown method"):
        get_method("nope")


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_ultraboneudf_presets_unchanged_by_configure(name):
    assert configured("ultraboneudf", name).to_dict() == preset(name).to_dict()


@pytest.mark.parametrize("method,expected", [
    ("ultraboneudf", 191_042), ("capudf", 463_100), ("funsr", 463_100), ("carotidudf", 463_874),
    ("vanilla_udf", 191_042), ("ultraboneudf_pull", 191_042)])
def test_appendix_c_parameter_counts_of_each_methods_network(method, expected):
    assert count_parameters(build_network(configured(method), 0, torch.device("cpu"))) == expected


def test_funsr_discriminator_and_total_parameters():
    disc = Discriminator()
    assert count_parameters(disc) == 132_353
    assert count_parameters(build_network(configured("funsr"), 0, torch.device("cpu"))) + 132_353 == 595_453


def test_skip_layer_widths_and_forward():
    net = DistanceMLP((256,) * 8, skip=(4,))
    assert net.layers[3].v.shape == (253, 256) and net.layers[4].v.shape == (256, 256)
    x = torch.randn(7, 3)
    # the forward pass equals the written-out IGR skip: layer 4 sees [h, x]/√2
    h = x
    for i, layer in enumerate(net.layers):
        if i == 4:
            h = torch.cat([h, x], dim=-1) / math.sqrt(2.0)
        h = layer(h)
        if i < len(net.layers) - 1:
            h = torch.relu(h)
    assert torch.allclose(net(x), h.squeeze(-1).abs())
    with pytest.raises(ValueError):
        DistanceMLP((64, 64), skip=(3,))
    cfg = configured("capudf")
    cfg.model.depth = 3
    with pytest.raises(InputError, match="model.skip"):
        build_network(cfg, 0, torch.device("cpu"))


def test_depth_rule_through_the_config():
    cfg = preset("official")
    apply_overrides(cfg, assignments=["model.depth=4"])
    assert model_widths(cfg.model) == DEPTH_WIDTHS[:4] == (64, 128, 128, 256)
    assert count_parameters(build_network(cfg, 0, torch.device("cpu"))) == 58_946
    cfg.model.depth = 11
    with pytest.raises(InputError, match="depth"):
        model_widths(cfg.model)


def test_ablation_switches_through_set():
    cfg = configured("ultraboneudf")
    apply_overrides(cfg, assignments=["loss.kind=pull", "loss.lambda_gs=0", "loss.lambda_os=0.1",
                                      "loss.lambda_eik=1", "model.skip=4", "extract.mode=udf2sdf"])
    assert (cfg.loss.kind, cfg.loss.lambda_gs, cfg.loss.lambda_os, cfg.loss.lambda_eik) == ("pull", 0.0, 0.1, 1.0)
    assert count_parameters(build_network(cfg, 0, torch.device("cpu"))) == 190_652  # §1.5 cross-check


def test_method_defaults_follow_the_spec():
    cap, fun, car = configured("capudf"), configured("funsr"), configured("carotidudf")
    assert (cap.train.iters, cap.capudf.expand_at, cap.train.batch, cap.capudf.expand_batch) == (60_000, 40_000, 5_000, 20_000)
    assert (cap.extract.mode, cap.grid.resolution, cap.grid.box) == ("capudf_mc", 256, "surface")
    assert (fun.train.iters, fun.loss.pull_norm, fun.model.abs_output, fun.extract.mode) == (15_000, "unsquared", False, "sdf_mc")
    assert fun.data.voxel_size_mm == 0.0
    assert (car.train.iters, car.loss.kind, car.loss.lambda_gs, car.grid.udf2sdf) == (30_000, "pull", 0.0, "normal-sign")
    assert configured("ultraboneudf_pull").extract.mode == preset("official").extract.mode
    assert configured("vanilla_udf").extract.mode == "udf2sdf"
    fast = configured("capudf", "fast")
    assert fast.capudf.expand_at == (2 * fast.train.iters) // 3


def test_consistency_chamfer_matches_the_full_matrix_value_and_gradient():
    g = torch.Generator().manual_seed(0)
    a = torch.randn(50, 3, generator=g, dtype=torch.float64)
    b0 = torch.randn(40, 3, generator=g, dtype=torch.float64)
    b1 = b0.clone().requires_grad_(True)
    ours = consistency_chamfer_loss(a, b1)
    ours.backward()
    b2 = b0.clone().requires_grad_(True)
    d = torch.cdist(a, b2)
    ref = 0.5 * (d.min(dim=1).values.mean() + d.min(dim=0).values.mean())
    ref.backward()
    assert torch.allclose(ours, ref) and torch.allclose(b1.grad, b2.grad)


def test_pull_norms_and_funsr_terms():
    moved, target = torch.tensor([[3.0, 4.0, 0.0]]), torch.zeros(1, 3)
    assert pull_loss(moved, target).item() == pytest.approx(25.0)
    assert pull_loss(moved, target, "unsquared").item() == pytest.approx(5.0)
    g_hat = torch.tensor([[0.6, 0.8, 0.0], [-0.6, -0.8, 0.0]])
    offsets = torch.tensor([[3.0, 4.0, 0.0], [3.0, 4.0, 0.0]])
    assert sign_consistency_loss(g_hat, offsets, torch.zeros(2, 3)).item() == pytest.approx(1.0)  # 0 and 2
    assert sign_consistency_loss(g_hat[:1], torch.zeros(1, 3), torch.zeros(1, 3)).item() == pytest.approx(1.0)
    assert lsgan_discriminator_loss(torch.ones(4), torch.zeros(4)).item() == 0.0
    assert lsgan_generator_loss(torch.full((4,), 0.5)).item() == pytest.approx(0.25)


def test_capudf_samples_follow_section_3_1():
    rng = np.random.default_rng(0)
    surface = rng.normal(size=(1234, 3)) * 0.1
    p, q = capudf_samples(surface, 20_000, 50, rng)
    assert len(p) == 1200 and len(q) == (20_000 // 1200) * 1200
    assert len(np.unique(p, axis=0)) == 1200  # a random subset without replacement
    with pytest.raises(InputError):
        capudf_samples(surface[:59], 20_000, 50, rng)


def test_even_subsample_hits_the_count_and_spreads():
    pts = np.random.default_rng(0).uniform(size=(50_000, 3))
    sub = even_subsample(pts, 2_000)
    assert abs(len(sub) - 2_000) <= 40
    from scipy.spatial import cKDTree
    nn_sub = cKDTree(sub).query(sub, k=2)[0][:, 1].min()
    rand = pts[:len(sub)]
    assert nn_sub > cKDTree(rand).query(rand, k=2)[0][:, 1].min()  # no near-duplicates, unlike random


def test_normals_on_a_sphere_are_radial_and_consistent():
    d = np.random.default_rng(2).normal(size=(3000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    p = 0.3 * d
    raw = pca_normals(p, p, radius=0.05, max_nn=30)
    assert np.abs((raw * d).sum(axis=1)).min() > 0.95
    oriented = orient_tangent_plane(p, raw, 15)
    dots = (oriented * d).sum(axis=1)
    assert (dots > 0).all() or (dots < 0).all()
    assert ((orient_toward(p, raw, np.zeros_like(p)) * d).sum(axis=1) < 0).all()  # toward the centre


def test_pca_normals_of_a_plane():
    rng = np.random.default_rng(3)
    p = np.c_[rng.uniform(-0.5, 0.5, (2000, 2)), np.zeros(2000)]
    n = pca_normals(p, p, radius=0.5, max_nn=1000)
    assert np.abs(n[:, 2]).min() > 0.999


def test_the_budget_field_not_the_preset_name_sets_the_baselines_schedule():
    from ultraboneudf.pipeline import configure

    cpu = configure("robust", "capudf")
    assert cpu.train.budget == "auto" and cpu.train.iters == preset("robust").train.iters
    assert cpu.capudf.expand_at == 2 * cpu.train.iters // 3 and cpu.grid.resolution == 128
    # the same preset asked for the published schedule (the method reads the field it is given)
    cfg = preset("robust")
    cfg.train.budget = "reference"
    get_method("capudf").configure(cfg)
    assert (cfg.train.iters, cfg.capudf.expand_at, cfg.grid.resolution) == (60_000, 40_000, 256)
    funsr = configure("official", "funsr")
    assert funsr.train.budget == "reference" and funsr.train.iters == 15_000 and funsr.grid.resolution == 256
