"""Model checkpoints: round trip, safe loading, clear errors for foreign files."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
import torch

from emlpack.nn import EMLP, ModelConfig
from emlpack.nn.checkpoint import CheckpointError, load_model, read_checkpoint, save_model
from emlpack.structure import Structure

CONFIG = ModelConfig(short_range={"n_features": 8, "n_filters": 4, "n_rbf": 4, "n_interactions": 1})


def methane() -> Structure:
    pos = np.array([[0, 0, 0], [0.63, 0.63, 0.63], [-0.63, -0.63, 0.63],
                    [-0.63, 0.63, -0.63], [0.63, -0.63, -0.63]])
    return Structure([6, 1, 1, 1, 1], pos, 0.6 * pos[1:], field=[0.1, 0, 0])


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
    payload["config"]["n_features"] = 16
    torch.save(payload, path)
    with pytest.raises(CheckpointError, match="inconsistent checkpoint"):
        load_model(path)
