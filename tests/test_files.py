"""Atomic writes: the target is replaced whole or not at all, no temporary file is left."""

from __future__ import annotations

import json

import numpy as np
import pytest

from emlpack._files import atomic_path, write_json_atomic, write_text_atomic


def test_a_failed_write_leaves_the_old_file_and_no_temporary(tmp_path):
    target = tmp_path / "out.json"
    write_json_atomic(target, {"a": 1})
    with pytest.raises(RuntimeError), atomic_path(target) as tmp:
        tmp.write_text("partial")
        raise RuntimeError("killed")
    assert json.loads(target.read_text()) == {"a": 1}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.json"]


def test_writers_that_want_a_file_name(tmp_path):
    target = tmp_path / "sub" / "arrays.npz"
    with atomic_path(target, suffix=".npz") as tmp:
        assert not tmp.exists()  # the writer creates it (h5py refuses an empty file)
        np.savez(tmp, x=np.arange(3))
    with np.load(target) as d:
        np.testing.assert_array_equal(d["x"], np.arange(3))
    write_text_atomic(target.with_suffix(".txt"), "é\n")
    assert target.with_suffix(".txt").read_text() == "é\n"
    assert sorted(p.name for p in target.parent.iterdir()) == ["arrays.npz", "arrays.txt"]
