"""``key=value`` overrides (emlpack.overrides): YAML values, nested paths, clear errors, and the
same parser behind the training configuration and the labeling recipes."""

import pytest

from emlpack.errors import InputError
from emlpack.overrides import OverrideError, apply_overrides, nested, parse_override


def test_values_are_yaml_and_keys_dotted_paths():
    assert parse_override("training.lr=1e-3") == (["training", "lr"], 1e-3)  # YAML 1.1: a string
    assert parse_override("x=-2.5E+2") == (["x"], -250.0)
    assert parse_override("name=1e3x") == (["name"], "1e3x")
    assert parse_override("seeds=[0, 2]") == (["seeds"], [0, 2])
    assert parse_override("prepare.optimize=false") == (["prepare", "optimize"], False)
    assert parse_override("dir=") == (["dir"], None)
    assert parse_override("notes=a=b") == (["notes"], "a=b")  # only the first = splits
    assert nested(["a", "b"], 3) == {"a": {"b": 3}}


def test_apply_sets_in_place_and_adds_missing_mappings():
    cfg = {"training": {"lr": 1.0, "steps": 5}, "seeds": [0]}
    out = apply_overrides(cfg, ["training.lr=0.5", "md.time_fs=10", "seeds=[1, 2]"])
    assert out is cfg
    assert cfg == {"training": {"lr": 0.5, "steps": 5}, "seeds": [1, 2], "md": {"time_fs": 10}}


@pytest.mark.parametrize("text, match", [
    ("training.lr", "expected key=value"),
    ("training..lr=1", "empty part"),
    ("seeds=[0, 1", "not valid YAML"),
    ("seeds.first=1", "'seeds' is not a mapping"),
])
def test_bad_overrides_are_one_line_input_errors(text, match):
    with pytest.raises(OverrideError, match=match) as info:
        apply_overrides({"seeds": [0]}, [text])
    assert isinstance(info.value, InputError) and "\n" not in str(info.value)


def test_training_config_refuses_unknown_keys_recipes_accept_new_ones():
    from emlpack.qm.recipe import load_recipe
    from emlpack.train.config import ConfigError, load_config

    assert load_config(None, ["training.max_epochs=7"])["training"]["max_epochs"] == 7
    with pytest.raises(ConfigError, match="unknown config key 'training.max_epoch'"):
        load_config(None, ["training.max_epoch=7"])
    with pytest.raises(OverrideError, match="expected key=value"):
        load_config(None, ["training.max_epochs"])
    recipe = load_recipe(None, ["level=tiny", "prepare.optimize=false"])
    assert recipe["level"] == "tiny" and recipe["prepare"]["optimize"] is False


def test_a_config_file_reads_exponent_floats_as_floats(tmp_path):
    from emlpack.train.config import load_config

    path = tmp_path / "train.yaml"
    path.write_text("training:\n  lr: 3e-4\n")
    assert load_config(path)["training"]["lr"] == 3e-4


@pytest.mark.parametrize("override, match", [
    ("training.lr=fast", "training.lr must be a number >= 0, got 'fast'"),
    ("training.lr=-1.0e-3", "training.lr must be a number >= 0"),
    ("training.decay_epochs=0", "training.decay_epochs must be a positive number"),
    ("training.max_time_minutes=ten", "training.max_time_minutes must be a positive number"),
    ("training.decay_factor=2", r"training.decay_factor must be in \(0, 1\]"),
    ("training.patience=0", "training.patience must be a positive integer or null"),
    ("loss.forces=true", "loss.forces must be a number >= 0, got True"),
])
def test_the_training_config_refuses_bad_numbers_before_training(override, match):
    from emlpack.train.config import ConfigError, load_config

    with pytest.raises(ConfigError, match=match):
        load_config(None, [override])
    assert load_config(None, ["training.max_time_minutes=null", "training.patience=null",
                              "training.lr=0.0"])["training"]["lr"] == 0.0


def test_the_training_device_is_checked_before_training(monkeypatch):
    import torch

    from emlpack.train.config import ConfigError, load_config, training_device

    with pytest.raises(ConfigError, match="training.device must be auto, cpu, cuda or cuda:N,"
                                          " got 'gpu'"):
        load_config(None, ["training.device=gpu"])
    with pytest.raises(ConfigError, match="training.device must be .* got 'meta'"):
        load_config(None, ["training.device=meta"])
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(ConfigError, match="training.device=cuda: PyTorch sees no CUDA GPU"):
        load_config(None, ["training.device=cuda"])
    assert training_device("auto") == torch.device("cpu")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    assert training_device("auto") == torch.device("cuda", 0)
    assert training_device("cuda:1") == torch.device("cuda", 1)
    # torchrun: a GPU per process, or the CPU when there are fewer GPUs than processes
    monkeypatch.setenv("LOCAL_RANK", "1")
    monkeypatch.setenv("LOCAL_WORLD_SIZE", "2")
    assert training_device("auto") == torch.device("cpu")
    with pytest.raises(ConfigError, match="2 processes on this node and 1 GPU"):
        training_device("cuda")
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    assert training_device("auto") == training_device("cuda") == torch.device("cuda", 1)
