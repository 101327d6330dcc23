import json
import re
from dataclasses import fields

import numpy as np
import pytest

from ultraboneudf.config import Config, DataConfig, apply_overrides, choices, preset, validate
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


def _every_field():
    cfg = Config()
    return [(section.name, f.name) for section in fields(cfg)
            for f in fields(getattr(cfg, section.name))]


def _bad_value(section, name):
    """A value of the wrong type (or an unknown mode) for the field, as typed after --set."""
    obj = getattr(Config(), section)
    if choices(obj, name):
        return "bogus"
    current = getattr(obj, name)
    if isinstance(current, bool):
        return "maybe"
    if isinstance(current, int):
        return "1.5"
    if isinstance(current, float):
        return "abc"
    if isinstance(current, tuple):
        return "a,b"
    raise AssertionError(f"{section}.{name}: a field that is neither a mode nor a number, flag or list")


def test_every_string_field_is_a_validated_mode():
    for section, name in _every_field():
        if isinstance(getattr(getattr(Config(), section), name), str):
            assert choices(getattr(Config(), section), name), f"{section}.{name} is a free string"


@pytest.mark.parametrize("key", [f"{s}.{n}" for s, n in _every_field()])
def test_bad_set_on_every_field_exits_2_with_one_line(key, tmp_path, capsys):
    from ultraboneudf.cli import main

    cloud = tmp_path / "in.xyz"
    np.savetxt(cloud, np.random.default_rng(0).normal(size=(50, 3)) * 10)
    bad = _bad_value(*key.split("."))
    assert main(["reconstruct", str(cloud), "-o", str(tmp_path / "out.ply"), "--quiet",
                 "--set", f"{key}={bad}"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and key in err
    allowed = choices(getattr(Config(), key.split(".")[0]), key.split(".")[1])
    if allowed:
        assert ", ".join(allowed) in err
    assert not (tmp_path / "out.ply").exists()


def test_unknown_key_exits_2(tmp_path, capsys):
    from ultraboneudf.cli import main

    cloud = tmp_path / "in.xyz"
    np.savetxt(cloud, np.random.default_rng(0).normal(size=(50, 3)) * 10)
    for item in ("train.nope=1", "nope.iters=1", "nope=1"):
        assert main(["reconstruct", str(cloud), "-o", str(tmp_path / "o.ply"), "--set", item]) == 2
        assert "nope" in capsys.readouterr().err


def test_a_key_of_an_earlier_version_names_its_new_place():
    from ultraboneudf.config import MOVED_KEYS

    cfg = Config()
    for old, new in MOVED_KEYS.items():
        section, name = new.split(".")
        assert hasattr(getattr(cfg, section), name), new          # every new place exists
        with pytest.raises(InputError, match=f"'{old}' is now '{new}'"):
            apply_overrides(Config(), assignments=[f"{old}=1"])


def test_modes_checked_on_construction_and_before_a_run():
    with pytest.raises(InputError, match="data.subset 'bogus'; choose one of official, fps, all"):
        DataConfig(subset="bogus")
    cfg = preset("fast")
    cfg.extract.mode = "marching"  # assigned after construction: validate() catches it
    with pytest.raises(InputError, match="extract.mode 'marching'"):
        validate(cfg)
    cfg = preset("fast")
    cfg.loss.lambda_gs = float("nan")
    with pytest.raises(InputError, match="loss.lambda_gs=nan"):
        validate(cfg)
    cfg = preset("fast")
    cfg.grid.resolution = 1           # checked before training, not when the grid extractor runs
    with pytest.raises(InputError, match=r"grid.resolution=1 \(at least 2\)"):
        validate(cfg)
    cfg = preset("robust")
    cfg.extract.trim_normal_mm = -1.0
    with pytest.raises(InputError, match=r"extract.trim_normal_mm=-1.0 \(finite and 0 or more\)"):
        validate(cfg)
    cfg = preset("fast")
    cfg.extract.trim_normal_mm = 1.0  # the fast preset fits no local planes to measure along
    with pytest.raises(InputError, match="extract.trim_normal_mm needs the local planes"):
        validate(cfg)
    cfg = preset("fast")
    cfg.extract.trim_rim_mm = 1.0  # nor a surface with rims
    with pytest.raises(InputError, match="extract.trim_rim_mm needs the local planes"):
        validate(cfg)
    cfg.extract.trim_rim_mm = float("nan")
    with pytest.raises(InputError, match=r"extract.trim_rim_mm=nan \(finite and 0 or more\)"):
        validate(cfg)
    for angle in (45.0, 90.0):        # steep planes lie beyond the 60° the planes accept
        cfg = preset("robust")
        cfg.data.steep_planes_deg = angle
        with pytest.raises(InputError, match=r"data.steep_planes_deg=.* \(0 \(none\) or an angle between 60"):
            validate(cfg)


def test_every_field_has_a_docstring_and_the_config_command_prints_it(capsys):
    from ultraboneudf.cli import main
    from ultraboneudf.config import field_docs

    for section in fields(Config()):
        docs = field_docs(type(getattr(Config(), section.name)))
        assert all(docs.values()), [k for k, v in docs.items() if not v]
    assert main(["config", "--method", "capudf", "--changed", "--set", "train.iters=123"]) == 0
    out = capsys.readouterr().out
    assert "train.iters = 123" in out and "loss.kind = capudf" in out
    assert "data.voxel_size_mm" not in out                 # unchanged from the default: not listed
    assert "Optimiser steps" in out
    assert main(["config", "--set", "data.subset=bogus"]) == 2


def test_the_generated_tables_of_docs_methods_are_up_to_date():
    """docs/methods.md's tables are generated from the dataclasses and the methods' ``configure``:
    regenerating them changes nothing, so the page cannot drift from the code."""
    from pathlib import Path

    from ultraboneudf.cli.cmd_config import BLOCK, update_docs

    text = (Path(__file__).resolve().parents[1] / "docs" / "methods.md").read_text()
    assert len(BLOCK.findall(text)) >= 10
    assert update_docs(text) == text, "run: ultraboneudf config --update-docs docs/methods.md"


def test_update_docs_rewrites_a_block_with_the_fields_a_method_changes(tmp_path, capsys):
    from ultraboneudf.cli import main

    page = tmp_path / "page.md"
    page.write_text("# x\n<!-- config method=capudf -->\nstale\n<!-- end config -->\ntail\n")
    assert main(["config", "--update-docs", str(page)]) == 0
    text = page.read_text()
    assert "stale" not in text and text.endswith("<!-- end config -->\ntail\n")
    assert "| `loss.kind=capudf` | `tangent` → `capudf` | `tangent` (UltraBoneUDF" in text
    assert "train.budget" not in text                       # unchanged by the method: not listed
    assert main(["config", "--update-docs", str(page)]) == 0
    assert "up to date" in capsys.readouterr().out

def test_the_budget_follows_the_device_unless_set():
    from ultraboneudf.config import resolve_budget, training_schedule

    cfg = preset("robust")
    assert cfg.train.budget == "auto" and preset("official").train.budget == "reference"
    assert resolve_budget("auto", "cpu") == "cpu" and resolve_budget("auto", "cuda") == "gpu"
    assert resolve_budget("cpu", "cuda") == "cpu" and resolve_budget("gpu", "cpu") == "gpu"
    # the CPU trains the preset's own schedule (the sections themselves, budget resolved)
    loss, train = training_schedule(cfg.loss, cfg.train, "cpu")
    assert loss is cfg.loss and (train.iters, train.batch, train.lr, train.budget) == (10_000, 250, 2e-3, "cpu")
    # a GPU: a quarter of the steps and of the warm-up, 16 times the queries, twice the rate, and as
    # many anchors and surface rows over the run
    loss, train = training_schedule(cfg.loss, cfg.train, "cuda")
    assert (train.budget, train.iters, train.batch, train.warmup, train.lr) == ("gpu", 2_500, 4_000, 100, 4e-3)
    assert (loss.gs_anchors, loss.os_rows) == (4 * cfg.loss.gs_anchors, 4 * cfg.loss.os_rows)
    assert cfg.train.iters == 10_000 and cfg.loss.os_rows == 256          # the config is not changed
    official = preset("official")
    assert training_schedule(official.loss, official.train, "cuda") == (official.loss, official.train)


def test_one_key_value_parser_names_the_option_the_item_and_the_problem():
    from ultraboneudf.config import parse_key_values

    assert parse_key_values(["a=1", " b = x,y ", "a=2"], "--opt") == {"a": "2", "b": "x,y"}
    types = {"n": int, "size": float, "axis": tuple[float, ...], "name": str | None}
    assert parse_key_values(["n=3", "size=0.5", "axis=1,0,0", "name=none"], "--opt", types, "thing") == \
        {"n": 3, "size": 0.5, "axis": (1.0, 0.0, 0.0), "name": None}
    for item, message in (("n", "--opt 'n': expected KEY=VALUE"), ("=3", "--opt '=3': expected KEY=VALUE"),
                          ("m=1", "--opt 'm=1': unknown thing 'm'; things: axis, n, name, size"),
                          ("n=1.5", "--opt 'n=1.5': bad value '1.5' for thing 'n' (expected an integer)"),
                          ("size=big", "--opt 'size=big': bad value 'big' for thing 'size' (expected a number)")):
        with pytest.raises(InputError) as err:
            parse_key_values([item], "--opt", types, "thing")
        assert str(err.value) == message


def test_the_parser_serves_set_simulate_and_detector_alike():
    from ultraboneudf.cli.cmd_simulate import parse_assignments
    from ultraboneudf.cli.sweep_input import parse_kv

    assert parse_kv(["high=0.4", "min_depth_mm=8"]) == {"high": 0.4, "min_depth_mm": 8.0}
    for call, item, words in ((parse_kv, "high=x", "--detector 'high=x': bad value 'x' for detector option 'high'"),
                              (parse_kv, "bogus=1", "--detector 'bogus=1': unknown detector option 'bogus'"),
                              (parse_assignments, "seed=1.5", "--set 'seed=1.5': bad value '1.5' for simulator option"),
                              (lambda items: apply_overrides(preset("fast"), None, items), "train.nope=1",
                               "--set 'train.nope=1': unknown config key 'train.nope'")):
        with pytest.raises(InputError, match=re.escape(words)):
            call([item])
