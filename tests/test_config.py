import json

import pytest

from ultraboneudf.config import Config, apply_overrides, preset
from ultraboneudf.errors import InputError


def test_presets_differ_where_paper_and_code_disagree():
    off, pap = preset("official"), preset("paper")
    assert off.loss.tangent_norm == "l1" and pap.loss.tangent_norm == "l2"
    assert off.data.grid_queries == 30_000 and pap.data.grid_queries == 0
    assert off.data.anchor_squared_target and not pap.data.anchor_squared_target
    assert off.extract.valid_threshold == 0.01 and pap.extract.valid_threshold == 0.002
    assert off.extract.max_depth == pap.extract.max_depth == 9
    assert pap.extract.plane_factor == 0.15 and pap.extract.sv_threshold == 0.08
    assert off.loss.gs_form == "broadcast" and pap.loss.gs_form == "per_anchor"


def test_overrides_by_section_bare_name_and_string():
    cfg = preset("official")
    apply_overrides(cfg, {"iters": 10, "extract__max_depth": 7}, ["loss.lambda_gs=0", "model.hidden=64,64"])
    assert cfg.train.iters == 10 and cfg.extract.max_depth == 7
    assert cfg.loss.lambda_gs == 0.0 and cfg.model.hidden == (64, 64)
    apply_overrides(cfg, assignments=["data.anchor_squared_target=false"])
    assert cfg.data.anchor_squared_target is False


@pytest.mark.parametrize("item", ["nope.iters=1", "train.nope=1", "iters=abc", "iters", "batch=2"])
def test_bad_overrides_raise_input_error(item):
    with pytest.raises(InputError):
        apply_overrides(preset("official"), assignments=[item])


def test_config_json_round_trip():
    cfg = apply_overrides(preset("fast"), {"lambda_gs": 0.5})
    again = Config.from_dict(json.loads(json.dumps(cfg.to_dict())))
    assert again == cfg


def test_unknown_preset():
    with pytest.raises(InputError, match="unknown preset"):
        preset("turbo")
