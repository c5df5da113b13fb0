"""Model checkpoints: round trip (every short-range family), safe loading, clear errors for
foreign files; format-1 files (SchNet before the families: the committed pretrained members and
benchmark fixture) load unchanged."""

from __future__ import annotations

import pickle
from pathlib import Path

import numpy as np
import pytest
import torch

from emlpack.nn import EMLP, ModelConfig
from emlpack.nn.checkpoint import CheckpointError, load_model, read_checkpoint, save_model
from emlpack.structure import Structure
from tests.nn.helpers import FAMILIES, as_format_1, random_model

ROOT = Path(__file__).resolve().parents[2]
#: committed checkpoints written in format 1 (flat SchNet config, ``schnet.*`` weights)
FORMAT_1_FILES = [ROOT / "benchmarks" / "fixtures" / "eqm7_small_trained.pt",
                  *sorted((ROOT / "src" / "emlpack" / "pretrained" / "mini-eqm7").glob("*.pt"))]

CONFIG = ModelConfig(short_range={"n_features": 8, "n_filters": 4, "n_rbf": 4, "n_interactions": 1})


def methane() -> Structure:
    pos = np.array([[0, 0, 0], [0.63, 0.63, 0.63], [-0.63, -0.63, 0.63],
                    [-0.63, 0.63, -0.63], [0.63, -0.63, -0.63]])
    return Structure([6, 1, 1, 1, 1], pos, 0.6 * pos[1:], field=[0.1, 0, 0])


@pytest.mark.parametrize("family", FAMILIES)
def test_round_trip_of_every_family(tmp_path, family):
    model = random_model(family=family)
    path = save_model(model, tmp_path / "m.pt")
    payload = read_checkpoint(path)
    assert payload["format_version"] == 2 and payload["config"]["family"] == family
    assert all(k.startswith("short_range.") for k in payload["state_dict"])
    loaded = load_model(path)
    assert loaded.config == model.config
    s = methane()
    assert loaded.evaluate(s)["energy"] == model.evaluate(s)["energy"]


def test_format_1_files_load_as_format_2(tmp_path):
    """A format-1 file (flat config, ``schnet.*`` weights) of a model gives the same model:
    the same config, weights and energies."""
    torch.manual_seed(0)
    model = EMLP(CONFIG).double()
    old = as_format_1(save_model(model, tmp_path / "m.pt", metadata={"note": "x"}))
    raw = torch.load(old, weights_only=True)
    assert raw["format_version"] == 1 and "n_features" in raw["config"]
    assert "schnet.embedding.weight" in raw["state_dict"]
    payload = read_checkpoint(old)
    assert payload["format_version"] == 2 and payload["config"] == CONFIG.to_dict()
    assert set(payload["state_dict"]) == set(model.state_dict())
    assert payload["metadata"] == {"note": "x"}
    loaded = load_model(old)
    assert loaded.config == CONFIG
    assert loaded.evaluate(methane())["energy"] == model.evaluate(methane())["energy"]


@pytest.mark.parametrize("path", FORMAT_1_FILES, ids=lambda p: p.name)
def test_committed_format_1_checkpoints_load_unchanged(path):
    """The shipped mini-eqm7 members and the benchmark fixture (format 1 on disk): their
    weights come back bit for bit under ``short_range.*``, their flat config as SchNet's."""
    raw = torch.load(path, map_location="cpu", weights_only=True)
    assert raw["format_version"] == 1
    model = load_model(path, dtype=None)
    assert model.config.family == "schnet"
    for key in ("n_features", "n_filters", "n_rbf", "n_interactions", "message_norm"):
        assert model.config.short_range[key] == raw["config"][key]
    assert model.config.cutoff == raw["config"]["cutoff"]
    state = model.state_dict()
    assert len(state) == len(raw["state_dict"])
    for key, value in raw["state_dict"].items():
        assert torch.equal(state["short_range." + key.removeprefix("schnet.")], value), key
    assert np.isfinite(model.double().evaluate(methane())["energy"])


def test_round_trip(tmp_path):
    torch.manual_seed(0)
    model = EMLP(CONFIG).double()
    path = save_model(model, tmp_path / "m.pt", metadata={"note": "x"})
    payload = read_checkpoint(path)
    assert payload["config"] == CONFIG.to_dict()
    assert payload["units"]["energy"] == "eV" and payload["emlpack_version"]
    assert payload["metadata"] == {"note": "x"}
    loaded = load_model(path)
    assert loaded.config == CONFIG
    a, b = model.evaluate(methane()), loaded.evaluate(methane())
    assert a["energy"] == b["energy"]
    np.testing.assert_array_equal(a["forces"], b["forces"])
    assert not list(tmp_path.glob("*.tmp"))
    # the same model and metadata give the same bytes, whatever the file's name
    again = save_model(model, tmp_path / "other.pt", metadata={"note": "x"})
    assert again.read_bytes() == path.read_bytes()


def test_foreign_files_are_refused(tmp_path):
    text = tmp_path / "notes.pt"
    text.write_text("hello")
    with pytest.raises(CheckpointError, match="notes.pt: not an emlpack model checkpoint"):
        load_model(text)
    other = tmp_path / "state.pt"
    torch.save({"weights": torch.zeros(2)}, other)
    with pytest.raises(CheckpointError, match="no 'emlpack-model' marker"):
        load_model(other)
    with pytest.raises(CheckpointError, match="no such checkpoint"):
        load_model(tmp_path / "missing.pt")


class _Evil:
    def __reduce__(self):
        return (print, ("executed",))


def test_unsafe_pickle_is_not_executed(tmp_path, capsys):
    path = tmp_path / "evil.pt"
    torch.save({"format": "emlpack-model", "payload": _Evil()}, path)
    with pytest.raises(CheckpointError, match="cannot be read safely"):
        load_model(path)
    assert "executed" not in capsys.readouterr().out
    raw = tmp_path / "raw.pt"
    raw.write_bytes(pickle.dumps(_Evil()))
    with pytest.raises(CheckpointError):
        load_model(raw)
    assert "executed" not in capsys.readouterr().out


def test_inconsistent_checkpoint(tmp_path):
    model = EMLP(CONFIG)
    path = save_model(model, tmp_path / "m.pt")
    payload = torch.load(path, weights_only=True)
    payload["config"]["short_range"]["n_features"] = 16
    torch.save(payload, path)
    with pytest.raises(CheckpointError, match="inconsistent checkpoint"):
        load_model(path)
