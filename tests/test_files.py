"""Atomic writes: the target is replaced whole or not at all, no temporary file is left."""

from __future__ import annotations

import json

import numpy as np
import pytest

from emlpack._files import atomic_path, try_lock, write_json_atomic, write_text_atomic


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


def test_handle_writers_npz_and_kept_permissions(tmp_path):
    from emlpack._files import atomic_write, write_npz_atomic

    target = tmp_path / "rows.csv"
    atomic_write(target, lambda fh: fh.write("a,b\r\n1,2\n"))
    assert target.read_bytes() == b"a,b\r\n1,2\n"  # no newline translation
    target.chmod(0o600)
    atomic_write(target, lambda fh: fh.write("x"))
    assert target.stat().st_mode & 0o777 == 0o600  # the replaced file's permissions are kept

    def fail(fh):
        fh.write("partial")
        raise ValueError("bad row")

    with pytest.raises(ValueError):
        atomic_write(target, fail)
    assert target.read_text() == "x"
    write_npz_atomic(tmp_path / "a.npz", compressed=True, x=np.arange(4), s="text")
    with np.load(tmp_path / "a.npz") as d:
        np.testing.assert_array_equal(d["x"], np.arange(4))
        assert str(d["s"]) == "text"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.npz", "rows.csv"]


def test_figures_are_written_atomically_in_the_format_of_the_suffix(tmp_path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from emlpack._files import write_figure_atomic

    fig, ax = plt.subplots()
    ax.plot([0, 1], [1, 0])
    write_figure_atomic(tmp_path / "a.png", fig)
    write_figure_atomic(tmp_path / "a.svg", fig)
    plt.close(fig)
    assert (tmp_path / "a.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert b"<svg" in (tmp_path / "a.svg").read_bytes()[:1000]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.png", "a.svg"]  # no temporaries


def test_a_lock_is_exclusive_and_dies_with_its_holder(tmp_path):
    """One holder at a time (also another open of the same file in this process); a killed
    holder leaves no stale lock."""
    import os
    import subprocess
    import sys

    path = tmp_path / "sub" / "x.lock"
    fd = try_lock(path)
    assert fd is not None and try_lock(path) is None
    os.close(fd)
    holder = subprocess.Popen([sys.executable, "-c", (
        "import sys, time; from emlpack._files import try_lock\n"
        f"assert try_lock({str(path)!r}) is not None; print('held', flush=True); time.sleep(60)")],
        stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        assert try_lock(path) is None
    finally:
        holder.kill()
        holder.wait()
    fd = try_lock(path)
    assert fd is not None
    os.close(fd)
