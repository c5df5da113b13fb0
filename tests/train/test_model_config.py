"""The training config's ``model`` section: family + nested short-range parameters, the
version-1 flat spelling (SchNet), family overrides on a config file, clear errors."""

from __future__ import annotations

import logging
from pathlib import Path

import pytest

from emlpack.nn.potential import ModelConfig, nest_flat_keys
from emlpack.nn.short_range import family_defaults
from emlpack.train.config import ConfigError, dump_config, load_config
from tests.nn.helpers import FAMILIES

ROOT = Path(__file__).resolve().parents[2]
CONFIG_FILES = [*sorted((ROOT / "configs").glob("*.yaml")),
                *sorted((ROOT / "examples").glob("*/train.yaml"))]


@pytest.mark.parametrize("path", CONFIG_FILES, ids=lambda p: f"{p.parent.name}/{p.name}")
def test_committed_config_files_load(path, tmp_path):
    """Every committed training config resolves to a SchNet model section with every
    parameter, and the resolved config (what a run saves as config.yaml) loads to itself."""
    import yaml

    from emlpack.overrides import load_yaml

    cfg = load_config(path)
    model = cfg["model"]
    assert model["family"] == "schnet"
    assert set(model["short_range"]) == set(family_defaults("schnet"))
    # the file's values arrive where they belong (flat SchNet keys: under short_range)
    written = nest_flat_keys(load_yaml(path.read_text()).get("model", {}))
    for key, value in written.pop("short_range", {}).items():
        assert model["short_range"][key] == value, key
    for key, value in written.items():
        assert model[key] == value, key
    ModelConfig.from_dict(model)
    saved = tmp_path / "config.yaml"
    dump_config(cfg, saved)
    again = load_config(saved)
    assert again["model"] == model
    assert yaml.safe_load(saved.read_text())["model"]["family"] == "schnet"


def test_flat_and_nested_overrides_set_the_same_parameter():
    flat = load_config(None, ["model.n_features=24", "model.cutoff=3.5"])
    nested = load_config(None, ["model.short_range.n_features=24", "model.cutoff=3.5"])
    assert flat["model"] == nested["model"]
    assert flat["model"]["short_range"]["n_features"] == 24
    assert flat["model"]["cutoff"] == 3.5


@pytest.mark.parametrize("family", FAMILIES)
def test_a_family_override_starts_from_that_familys_defaults(family, caplog):
    """``model.family=X`` on a SchNet config file: X's defaults, then the
    ``model.short_range.*`` overrides (in any order); the file's SchNet parameters are left
    out with a warning when the family changes."""
    path = ROOT / "configs" / "small_cpu.yaml"
    key, value = next(iter(family_defaults(family).items()))
    numeric = isinstance(value, int | float) and not isinstance(value, bool)
    bumped = value + 1 if numeric else value
    with caplog.at_level(logging.WARNING, logger="emlpack.train.config"):
        cfg = load_config(path, [f"model.short_range.{key}={bumped}", f"model.family={family}"])
    model = cfg["model"]
    assert model["family"] == family
    changed = family != "schnet"
    # the same family: the file's own SchNet parameters stay
    start = family_defaults(family) if changed else load_config(path)["model"]["short_range"]
    assert model["short_range"] == {**start, key: bumped}
    assert ("are not used" in caplog.text) == changed
    assert model["elements"] == [1, 6, 7, 8] and model["cutoff"] == 4.0


@pytest.mark.parametrize("overrides, match", [
    (["model.family=nope"], "model.family must be one of schnet"),
    (["model.short_range.n_layers=3"], r"'schnet' has no parameter\(s\) \['n_layers'\]"),
    (["model.family=radial", "model.n_features=8"], "family 'radial' takes"
                                                    " model.short_range.n_features"),
    (["model.n_layers=3"], "unknown config key 'model.n_layers'"),
    (["model.cutoff.x=3"], "'model.cutoff' is not a mapping"),
])
def test_bad_model_overrides_are_refused_in_one_line(overrides, match):
    with pytest.raises(ConfigError, match=match) as info:
        load_config(None, overrides)
    assert "\n" not in str(info.value)


def test_a_bad_model_section_in_a_file_names_it(tmp_path):
    path = tmp_path / "train.yaml"
    path.write_text("model:\n  family: radial\n  n_features: 8\n")
    with pytest.raises(ConfigError, match="model: .*family 'radial' takes its parameters"):
        load_config(path)
    path.write_text("model:\n  short_range:\n    n_layers: 3\n")
    with pytest.raises(ConfigError, match=r"model: .*no parameter\(s\) \['n_layers'\]"):
        load_config(path)
