"""HDF5 dataset store: ragged records, random access, all-or-nothing appends, extxyz."""

from __future__ import annotations

import os
import pickle
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest

from emlpack.data import store as store_mod
from emlpack.data.store import DatasetStore, StoreError
from emlpack.structure import Structure
from tests.conftest import ROOT, shared_path


def _methane(i: int, with_labels: bool = True) -> Structure:
    rng = np.random.default_rng(i)
    pos = np.array([[0, 0, 0], [0.63, 0.63, 0.63], [-0.63, -0.63, 0.63], [-0.63, 0.63, -0.63],
                    [0.63, -0.63, -0.63]], float) + 0.01 * rng.normal(size=(5, 3))
    return Structure(
        numbers=[6, 1, 1, 1, 1], positions=pos, pairs=0.5 * pos[1:],
        field=rng.normal(size=3) * 0.1, energy=-1100.0 - i if with_labels else None,
        forces=rng.normal(size=(5, 3)) if with_labels else None,
        pair_forces=np.zeros((4, 3)) if with_labels else None,
        info={"key": f"ch4/{i}", "molecule_id": "ch4", "kind": "nms600", "level": "tiny",
              "wall_time": 1.5},
    )


def _water_crystal() -> Structure:
    return Structure(
        numbers=[8, 1, 1], positions=[[0, 0, 0], [0.96, 0, 0], [-0.24, 0.93, 0]],
        pairs=[[0.3, 0, 0], [0, 0.3, 0], [0, 0, 0.3], [0, 0, -0.3]], cell=np.eye(3) * 5.0,
        pbc=True, energy=-5.0, forces=np.zeros((3, 3)), stress=np.eye(3) * 1e-3,
        info={"key": "ice/0", "molecule_id": "ice", "kind": "cell-nms"},
    )


def test_round_trip_ragged_records(tmp_path):
    path = tmp_path / "s.h5"
    items = [_methane(0), _water_crystal(), _methane(1, with_labels=False)]
    with DatasetStore(path, "a") as st:
        assert st.append(items) == 3
    with DatasetStore(path) as st:
        assert len(st) == 3 and st.keys() == ["ch4/0", "ice/0", "ch4/1"]
        for ref, got in zip(items, st, strict=True):
            np.testing.assert_array_equal(got.numbers, ref.numbers)
            np.testing.assert_array_equal(got.positions, ref.positions)
            np.testing.assert_array_equal(got.pairs, ref.pairs)
            np.testing.assert_array_equal(got.field, ref.field)
            assert got.pbc == ref.pbc and got.energy == ref.energy
            for name in ("forces", "stress"):
                a, b = getattr(ref, name), getattr(got, name)
                assert (a is None and b is None) or np.array_equal(a, b)
        for k, bulk in enumerate(st):  # iteration reads whole columns: same as one by one
            one = st[k]
            assert bulk.source == one.source and bulk.info.keys() == one.info.keys()
            for key, value in bulk.info.items():
                assert np.array_equal(value, one.info[key], equal_nan=key == "wall_time")
            for name in ("numbers", "positions", "pairs", "cell", "field", "forces", "stress"):
                a, b = getattr(bulk, name), getattr(one, name)
                assert (a is None and b is None) or np.array_equal(a, b)
        assert st[1].info["kind"] == "cell-nms" and st[-1].info["key"] == "ch4/1"
        np.testing.assert_array_equal(st[1].cell, np.eye(3) * 5.0)
        assert st[0].info["wall_time"] == 1.5 and "record 2" in st[2].source
        with pytest.raises(IndexError, match="record 3 out of range"):
            st.record(3)
        with pytest.raises(StoreError, match="read-only"):
            st.append(_methane(5))


def test_append_in_batches_and_unique_keys(tmp_path):
    path = tmp_path / "s.h5"
    with DatasetStore(path, "a") as st:
        for i in range(5):
            st.append(_methane(i))
        with pytest.raises(StoreError, match="key 'ch4/2' is already stored"):
            st.append(_methane(2))
        st.add_failures([{"key": "ch4/9", "molecule_id": "ch4", "kind": "nms600",
                          "reason": "SCF not converged"}])
        st.set_reference("CH4", -1101.3, "pbe0/aug-cc-pvtz")
        st.set_metadata(recipe="nms600: 100\n")
    with DatasetStore(path) as st:
        assert len(st) == 5 and st.done_keys() == {f"ch4/{i}" for i in (0, 1, 2, 3, 4, 9)}
        assert st.failures()[0]["reason"] == "SCF not converged"
        assert st.references() == {"CH4": {"energy": -1101.3, "level": "pbe0/aug-cc-pvtz"}}
        assert st.metadata["recipe"] == "nms600: 100\n"
        assert st.metadata["unit_field"] == "V/angstrom"
        np.testing.assert_array_equal(st[3].positions, _methane(3).positions)


def test_interrupted_append_leaves_no_partial_record(tmp_path, monkeypatch):
    """A crash between the data write and the commit: the record is absent, nothing else lost."""
    path = tmp_path / "s.h5"
    with DatasetStore(path, "a") as st:
        st.append([_methane(0), _methane(1)])
    real = store_mod._write_rows

    def crash_on_records(group, columns, start):
        real(group, columns, start)
        if group.name == "/records":
            raise KeyboardInterrupt("simulated crash after the data, before the commit")

    st = DatasetStore(path, "a")
    monkeypatch.setattr(store_mod, "_write_rows", crash_on_records)
    with pytest.raises(KeyboardInterrupt):
        st.append(_methane(2))
    monkeypatch.setattr(store_mod, "_write_rows", real)
    with DatasetStore(path) as ro:  # a reader sees only committed records
        assert len(ro) == 2 and ro.keys() == ["ch4/0", "ch4/1"]
    st.close()
    with DatasetStore(path, "a") as st:  # the next writer drops the uncommitted rows
        assert st.file["cores/positions"].shape[0] == 10
        st.append(_methane(2))
        assert len(st) == 3
        np.testing.assert_array_equal(st[2].positions, _methane(2).positions)


def test_kill_9_during_appends_keeps_a_consistent_store(tmp_path):
    """A writer killed with SIGKILL: every committed record is complete and readable."""
    path = tmp_path / "s.h5"
    script = textwrap.dedent(f"""
        import sys
        sys.path.insert(0, {str(ROOT)!r})
        from tests.data.test_store import _methane
        from emlpack.data.store import DatasetStore
        st = DatasetStore({str(path)!r}, "a")
        i = 0
        while True:
            st.append([_methane(i), _methane(i + 1)])
            i += 2
            if i == 20:
                print("ready", flush=True)
    """)
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "ready"
    time.sleep(0.3)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    with DatasetStore(path, "a") as st:
        n = len(st)
        assert n >= 20 and n % 2 == 0
        assert st.keys() == [f"ch4/{i}" for i in range(n)]
        for i in (0, n // 2, n - 1):
            np.testing.assert_array_equal(st[i].positions, _methane(i).positions)
        st.append(_methane(n))
        assert len(st) == n + 1


def test_one_writer_at_a_time(tmp_path):
    path = tmp_path / "s.h5"
    with DatasetStore(path, "a") as st:
        st.append(_methane(0))
        with pytest.raises(StoreError, match="another process is writing"):
            DatasetStore(path, "a")
        assert len(DatasetStore(path)) == 1  # readers are welcome
    with DatasetStore(path, "a") as st:  # the lock is released on close
        st.append(_methane(1))


def test_store_survives_pickle_and_rejects_other_files(tmp_path):
    path = tmp_path / "s.h5"
    DatasetStore(path, "a").append(_methane(0))
    st = pickle.loads(pickle.dumps(DatasetStore(path)))
    assert len(st) == 1
    bad = tmp_path / "bad.h5"
    bad.write_text("not hdf5")
    with pytest.raises(StoreError, match="bad.h5: cannot open"):
        DatasetStore(bad)
    with pytest.raises(StoreError, match="no such dataset store"):
        DatasetStore(tmp_path / "missing.h5")


def test_extxyz_round_trip_of_paper_frames(tmp_path):
    src = shared_path("data/eqm7_pbe0_subset.xyz")
    store = DatasetStore.from_extxyz(src, tmp_path / "s.h5", index="395:405",
                                     level="pbe0/aug-cc-pvtz")
    assert len(store) == 10 and store[0].info["key"] == "eqm7_pbe0_subset.xyz:0"
    assert store[9].n_pairs == 10  # ethanol: 10 valence pairs, core centres removed
    out = tmp_path / "back.xyz"
    assert store.to_extxyz(out, convention="reference") == 10
    from emlpack.io.extxyz import read_structures

    ref = read_structures(src, "395:405")
    back = read_structures(out)
    for a, b in zip(ref, back, strict=True):
        np.testing.assert_allclose(b.positions, a.positions, atol=1e-8)
        np.testing.assert_allclose(b.pairs, a.pairs, atol=1e-8)
        np.testing.assert_allclose(b.field, a.field, rtol=1e-12)
        assert b.energy == pytest.approx(a.energy, abs=1e-9)
        np.testing.assert_allclose(b.forces, a.forces, atol=1e-8)


def test_float32_compressed_store_is_small_and_reads_back_float64(tmp_path):
    """Shards of a large campaign: float32 positions and forces, gzip; records come back as
    float64 within float32 rounding, energies and fields exactly."""
    structures = [_methane(i) for i in range(200)]
    sizes = {}
    for name, kw in {"plain": {}, "packed": {"precision": "float32", "compress": True}}.items():
        path = tmp_path / f"{name}.h5"
        with DatasetStore(path, "a", compact=True, **kw) as st:
            st.append(structures)
        sizes[name] = path.stat().st_size
        with DatasetStore(path) as st:
            back = list(st)
            assert st.metadata["precision"] == kw.get("precision", "float64")
        for a, b in zip(back, structures, strict=True):
            assert a.positions.dtype == np.float64 and a.forces.dtype == np.float64
            tol = 0 if name == "plain" else 1e-6
            np.testing.assert_allclose(a.positions, b.positions, rtol=tol, atol=tol)
            np.testing.assert_allclose(a.forces, b.forces, rtol=tol, atol=tol)
            np.testing.assert_allclose(a.pairs, b.pairs, rtol=tol, atol=tol)
            assert a.energy == b.energy and np.array_equal(a.field, b.field)
    assert sizes["packed"] < 0.5 * sizes["plain"]
    assert sizes["packed"] / len(structures) < 2000  # bytes per configuration
    with pytest.raises(ValueError, match="precision"):
        DatasetStore(tmp_path / "x.h5", "a", precision="float16")


def test_polarizability_label_round_trip_and_stores_without_the_column(tmp_path):
    """The optional ``polarizability`` column (e·Å²/V): labelled records read back exactly,
    unlabelled ones as None; a store written before the column existed reads as unlabelled
    and gains the column (NaN before) with its first labelled record."""
    import h5py

    alpha = np.array([[1.1, 0.1, -0.2], [0.1, 1.3, 0.05], [-0.2, 0.05, 0.9]])
    labelled = _methane(0).copy(polarizability=alpha)
    path = tmp_path / "s.h5"
    with DatasetStore(path, "a") as st:
        st.append([labelled, _methane(1)])
    with DatasetStore(path) as st:
        got = list(st)
        np.testing.assert_array_equal(got[0].polarizability, alpha)
        np.testing.assert_array_equal(st.structure(0).polarizability, alpha)
        assert got[1].polarizability is None and st.structure(1).polarizability is None
        assert st.metadata["unit_polarizability"] == "e*angstrom^2/V"
    old = tmp_path / "old.h5"
    with DatasetStore(old, "a") as st:
        st.append([_methane(2)])
    with h5py.File(old, "r+") as f:  # as written before the column existed
        del f["records/polarizability"]
        del f.attrs["unit_polarizability"]
    with DatasetStore(old) as st:
        assert st[0].polarizability is None and next(iter(st)).polarizability is None
    with DatasetStore(old, "a") as st:
        st.append([_methane(3)])  # no label: the old layout stays
    with h5py.File(old, "r") as f:
        assert "polarizability" not in f["records"]
    with DatasetStore(old, "a") as st:
        st.append([labelled.copy(info={**labelled.info, "key": "ch4/labelled"})])
    with DatasetStore(old) as st:
        assert [s.polarizability is None for s in st] == [True, True, False]
        np.testing.assert_array_equal(st[2].polarizability, alpha)
        assert st.metadata["unit_polarizability"] == "e*angstrom^2/V"


def test_a_frozen_shard_list_reads_those_shards_and_counts_them_without_labels(tmp_path):
    """``read_shards(folder, shards)`` reads the named shards only (a growing set's frozen
    list), ``shard_counts`` gives their configurations and molecules from the text columns
    (hydride references left out), and a named shard that is not there is one error naming
    it."""
    from emlpack.data.shards import read_shards, shard_counts
    from tests.examples.eqm7_data import PER_MOLECULE, tiny_dataset

    folder = tiny_dataset(tmp_path / "set", shards=2)
    first = read_shards(folder, ["0000.h5"])
    assert [p.name for p in first.shards] == ["0000.h5"] and first.hydrides is not None
    assert len(first.structures) == 3 * PER_MOLECULE
    assert shard_counts(folder, ["0000.h5"]) == {"shards": ["0000.h5"],
                                                 "configurations": 3 * PER_MOLECULE,
                                                 "molecules": 3}
    counts = shard_counts(folder)
    assert counts["configurations"] == len(read_shards(folder).structures) == 6 * PER_MOLECULE
    assert counts["shards"] == ["0000.h5", "0001.h5"] and counts["molecules"] == 6
    with DatasetStore(folder / "shards" / "0000.h5") as store:
        assert store.text_column("kind").count("hydride") == 4
        with pytest.raises(StoreError, match="no text column 'energy'"):
            store.text_column("energy")
    with pytest.raises(StoreError, match=r"no shard\(s\) 0007.h5 in shards/"):
        read_shards(folder, ["0000.h5", "0007.h5"])


# ------------------------------------------------------------------ packed shards (format 2)
def _labelled_records() -> list[Structure]:
    """Records with every kind of column filled: NaN and None labels, a charge, a crystal
    with stress, a polarizability, non-ASCII text."""
    alpha = np.array([[1.1, 0.1, -0.2], [0.1, 1.3, 0.05], [-0.2, 0.05, 0.9]])
    m = _methane(3)
    charged = m.copy(charge=2.0, pairs=m.pairs[:3], pair_forces=m.pair_forces[:3])
    charged.info = {**charged.info, "key": "ch4-/3", "molecule_id": "méthane"}
    return [_methane(0), _water_crystal(), _methane(1, with_labels=False),
            _methane(2).copy(polarizability=alpha), charged]


def _assert_same_record(got: dict, ref: dict) -> None:
    """Every field of two :meth:`DatasetStore.record` dicts equal, bit for bit (NaN = NaN)."""
    assert got.keys() == ref.keys()
    for name, value in ref.items():
        if isinstance(value, (str, bool)):
            assert got[name] == value, name
        else:
            assert got[name].dtype == value.dtype and got[name].shape == value.shape, name
            assert got[name].tobytes() == value.tobytes(), name


@pytest.mark.parametrize("precision", ["float64", "float32"])
def test_packed_shard_reads_back_every_field_as_the_appendable_store(tmp_path, precision):
    """write_packed → DatasetStore: records, iteration, keys, failures, references and
    metadata equal to the same data appended to an appendable store of that precision."""
    records = _labelled_records()
    failures = [{"key": "ch4/9", "molecule_id": "ch4", "kind": "nms600",
                 "reason": "SCF not converged"}]
    references = {"CH4": {"energy": -1101.3, "level": "pbe0/aug-cc-pvtz"},
                  "H2": {"energy": -31.7, "level": "pbe0/aug-cc-pvtz"}}
    meta = {"recipe": "nms600: 100\n", "run_wall_s": 12.5, "run_workers": np.int64(2),
            "run_host": "x"}
    old = tmp_path / "appendable.h5"
    with DatasetStore(old, "a", compact=True, precision=precision, compress=True) as st:
        st.append(records)
        st.add_failures(failures)
        for name, ref in references.items():
            st.set_reference(name, ref["energy"], ref["level"])
        st.set_metadata(**meta)
    new = store_mod.write_packed(tmp_path / "packed.h5", records, failures, references, meta,
                                 precision=precision)
    with DatasetStore(old) as a, DatasetStore(new) as b:
        assert len(b) == len(a) == len(records) and b.keys() == a.keys()
        for i in range(len(a)):
            _assert_same_record(b.record(i), a.record(i))
        for sa, sb in zip(a, b, strict=True):  # whole columns at once: the same structures
            assert sb.info.keys() == sa.info.keys()
            assert all(np.array_equal(sb.info[k], v, equal_nan=k == "wall_time")
                       for k, v in sa.info.items())
            assert sb.source.endswith(sa.source.rsplit(",", 1)[1])
            for name in ("numbers", "positions", "pairs", "forces", "pair_forces", "cell",
                         "field", "stress", "polarizability", "energy", "charge", "pbc"):
                va, vb = getattr(sa, name), getattr(sb, name)
                assert (va is None and vb is None) or np.array_equal(va, vb), name
        assert b.failures() == a.failures() == failures
        assert b.references() == a.references() == references
        ma, mb = a.metadata, b.metadata
        assert mb.pop("format_version") == store_mod.PACKED_VERSION
        assert ma.pop("format_version") == store_mod.FORMAT_VERSION
        assert mb == ma and mb["run_workers"] == 2 and mb["unit_field"] == "V/angstrom"
        assert b.storage == {"format_version": 2, "precision": precision, "compress": True}
    if precision == "float32":  # float32 keeps ~1e-7 relative; energies, fields exact
        with DatasetStore(new) as b:
            np.testing.assert_allclose(b[0].positions, records[0].positions, rtol=1e-6)
            assert b[0].energy == records[0].energy
            np.testing.assert_array_equal(b[0].field, records[0].field)


def test_packed_shard_is_small_and_written_once(tmp_path):
    """30 small-molecule records: ≤ 2 kB per configuration with its HDF5 overhead (the
    appendable layout: ~3 kB each); a packed file cannot be appended to, and is left as it was
    (no lock file beside it)."""
    records = [_methane(i) for i in range(30)]
    path = store_mod.write_packed(tmp_path / "0000.h5", records, precision="float32")
    old = tmp_path / "old.h5"
    with DatasetStore(old, "a", compact=True, precision="float32", compress=True) as st:
        st.append(records)
    assert path.stat().st_size / 30 < 1000 < old.stat().st_size / 30
    before = path.read_bytes()
    with pytest.raises(StoreError, match="packed shard is written once"):
        DatasetStore(path, "a")
    with pytest.raises(StoreError, match="already stored"):
        store_mod.write_packed(tmp_path / "dup.h5", [_methane(0), _methane(0)])
    assert path.read_bytes() == before and sorted(p.name for p in tmp_path.iterdir()) == [
        "0000.h5", "old.h5", "old.h5.lock"]
    plain = store_mod.write_packed(tmp_path / "plain.h5", records, compress=False)
    with DatasetStore(plain) as st:
        assert not st.storage["compress"] and st.keys() == [s.info["key"] for s in records]


def test_packed_shard_of_failures_only_and_of_many_chunks(tmp_path):
    """A shard with failures and no record reads as empty; one of 1200 records (several
    chunks per table) reads every record back in any order."""
    failed = [{"key": "m0/0", "molecule_id": "m0", "kind": "nms600", "reason": "x" * 2000}]
    path = store_mod.write_packed(tmp_path / "f.h5", [], failed)
    with DatasetStore(path) as st:
        assert len(st) == 0 and list(st) == [] and st.keys() == [] and st.references() == {}
        assert st.failures()[0]["reason"].endswith("...") and st.done_keys() == {"m0/0"}
    records = [_methane(i) for i in range(1200)]
    path = store_mod.write_packed(tmp_path / "big.h5", records)
    import h5py

    with h5py.File(path) as f:
        assert f["records"].chunks[0] < 1200 and f["cores"].chunks[0] < 6000
    with DatasetStore(path) as st:
        for i in (1199, 0, 457, 800):
            np.testing.assert_array_equal(st[i].positions, records[i].positions)
            np.testing.assert_array_equal(st[i].forces, records[i].forces)
        assert [s.info["key"] for s in st] == [s.info["key"] for s in records]


@pytest.mark.parametrize("name", ["qm7-pbe0-def2svpd", "beta-glycine", "mini-eqm7"])
def test_committed_shards_read_as_stored_and_repack_bit_for_bit(tmp_path, name):
    """A committed shard of each data set (appendable layout, never rewritten): the reader
    returns its columns as h5py stores them, and the same records packed again read back
    identical (float32 columns too: float32 → float64 → float32 is exact) in a file at most a
    third of the size."""
    import h5py

    from emlpack.data.shards import shard_paths

    paths = shard_paths(ROOT / "datasets" / name)
    if not paths:
        pytest.skip(f"datasets/{name} has no shards in this checkout")
    shard = paths[0]
    with DatasetStore(shard) as st, h5py.File(shard, "r", locking=False) as f:
        assert st.storage["format_version"] == store_mod.FORMAT_VERSION
        n, n_cores = int(f.attrs["n_records"]), int(f.attrs["n_cores"])
        assert st.keys() == [k.decode() for k in f["records/key"][:n]]
        bulk = np.concatenate([s.positions for s in st])
        assert bulk.tobytes() == f["cores/positions"][:n_cores].astype(np.float64).tobytes()
        records = [st.record(i) for i in range(len(st))]
        structures, layout = list(st), st.storage
        failures, references, meta = st.failures(), st.references(), st.metadata
    packed = store_mod.write_packed(
        tmp_path / shard.name, structures, failures, references,
        {k: v for k, v in meta.items() if k.startswith("run_") or k == "recipe"},
        precision=layout["precision"], compress=True)
    with DatasetStore(packed) as st:
        assert st.keys() == [r["key"] for r in records] and st.failures() == failures
        for i, ref in enumerate(records):
            _assert_same_record(st.record(i), ref)
        assert st.metadata.get("recipe") == meta.get("recipe")
    assert packed.stat().st_size < shard.stat().st_size / 3
