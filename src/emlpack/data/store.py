"""HDF5 dataset store: an append-only file of ragged eMLP records, readable by index.

Layout (all in emlpack's public units: Å, eV, eV/Å, V/Å, eV/Å^3, e)::

    /cores/numbers (n_cores_total,) int16      /cores/positions, /cores/forces (.., 3)
    /pairs/positions (n_pairs_total, 3)        /pairs/forces (n_pairs_total, 3)
    /records/{core_start, n_cores, pair_start, n_pairs, energy, field(3), cell(3,3), pbc,
              charge, stress(3,3), molecule_id, kind, level, key, wall_time,
              polarizability(3,3)}
    /failures/{key, molecule_id, kind, reason}
    /references/{name, energy, level}          (e.g. the hydrides H2, CH4, NH3, H2O)

Missing labels are NaN (``energy``, ``forces``, ``stress``, ``polarizability``). The
``polarizability`` column (e·Å²/V, clamped nuclei) is optional: stores written before it
existed read as unlabelled, and the first record with one adds the column (NaN for the records
before it). Each record has a unique ``key``
(e.g. ``"qm7-0003/nms800/0017"``), which makes labeling resumable.

Crash safety: the number of committed rows of every group is an attribute of the file
(``n_records``, ``n_cores``, ``n_pairs``, ...). An append writes and flushes the data beyond
the committed end first and only then moves the counters (and flushes again). A process killed
in between leaves rows beyond the counters, which readers ignore and the next writer
overwrites: a record is either fully there or absent. (HDF5 has no journal; a kill during the
flush of HDF5's own metadata could still damage the file, which is why writers batch records
and flush rarely relative to the work between them.)

The reader is torch-free; open one :class:`DatasetStore` per process (it reopens itself after a
fork, so it can be shared with data-loader workers).
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from emlpack._files import atomic_path, try_lock
from emlpack.errors import EmlpackError
from emlpack.structure import Structure

if TYPE_CHECKING:
    import h5py
    from numpy.typing import DTypeLike

FORMAT = "emlpack-store"
FORMAT_VERSION = 1
UNITS = {
    "positions": "angstrom", "energy": "eV", "forces": "eV/angstrom", "field": "V/angstrom",
    "stress": "eV/angstrom^3", "charge": "e", "cell": "angstrom (rows are lattice vectors)",
    "wall_time": "s", "polarizability": "e*angstrom^2/V",
}

_REC_FLOAT = {"energy": (), "field": (3,), "cell": (3, 3), "charge": (), "stress": (3, 3),
              "wall_time": ()}
#: record columns that a store may lack (written before they existed): NaN when absent
_REC_OPTIONAL = {"polarizability": (3, 3)}
_REC_INT = {"core_start": np.int64, "n_cores": np.int32, "pair_start": np.int64,
            "n_pairs": np.int32, "pbc": np.bool_}
#: fixed-length UTF-8 text columns (bytes). Variable-length strings live in HDF5's global heap,
#: which a killed writer leaves inconsistent ("bad heap index"); fixed length keeps every row
#: inside its own dataset.
_STR_LEN = {"molecule_id": 128, "kind": 32, "level": 64, "key": 128, "reason": 1024, "name": 32}
_REC_STR = ("molecule_id", "kind", "level", "key")
_FAIL_STR = ("key", "molecule_id", "kind", "reason")
_REF_STR = ("name", "level")


class StoreError(EmlpackError, RuntimeError):
    """A problem with a dataset store file; the message names the file."""


class DatasetStore:
    """An HDF5 dataset store.

    Args:
        path: the ``.h5`` file.
        mode: ``"r"`` (read only) or ``"a"`` (read and append; created when missing).
        compact: create a new file with small chunks (for stores of tens of records, such
            as campaign shards: ~20 kB instead of ~1 MB when empty).
        precision: ``"float64"`` or ``"float32"``: the type of the per-particle columns
            (positions, forces) of a new file; energies, fields, cells and stresses stay
            float64. Records read back are float64 either way. float32 keeps positions to
            ~1e-6 Å and forces to ~1e-7 relative: enough for training labels, not for
            replaying an optimisation bit for bit.
        compress: create a new file with gzip + shuffle filters (write-once shards: with
            ``float32`` a small molecule's record takes ~0.5-1 kB instead of ~2-4 kB).
    """

    def __init__(self, path: str | os.PathLike, mode: str = "r", compact: bool = False,
                 precision: str = "float64", compress: bool = False) -> None:
        if mode not in ("r", "a"):
            raise ValueError(f"mode must be 'r' or 'a', got {mode!r}")
        self.path = Path(path)
        self.mode = mode
        self._file = None
        self._pid = None
        self._key_cache: set[str] | None = None
        self._lock_fd: int | None = None
        self._compact = bool(compact)
        if precision not in ("float64", "float32"):
            raise ValueError(f"precision must be 'float64' or 'float32', got {precision!r}")
        self._precision = precision
        self._compress = bool(compress)
        if mode == "r" and not self.path.exists():
            raise StoreError(f"{self.path}: no such dataset store")
        self._open()

    # ------------------------------------------------------------------ file handling
    def _open(self) -> None:
        import h5py

        if self.mode == "a" and not self.path.exists():
            with atomic_path(self.path) as tmp, h5py.File(tmp, "w") as f:
                _create_layout(f, chunk_scale=1 / 16 if self._compact else 1.0,
                               precision=self._precision, compress=self._compress)
        try:
            if self.mode == "a":
                self._lock_writer()
            # HDF5's own locking would stop readers from watching a store being written (and
            # mixes badly within one process); one writer at a time is ensured by _lock_writer
            self._file = h5py.File(self.path, "r" if self.mode == "r" else "r+", locking=False)
        except OSError as exc:
            raise StoreError(f"{self.path}: cannot open as an HDF5 dataset store: {exc}") from None
        self._pid = os.getpid()
        if self._file.attrs.get("format") != FORMAT:
            raise StoreError(f"{self.path}: not an emlpack dataset store")
        version = int(self._file.attrs.get("format_version", -1))
        if version != FORMAT_VERSION:
            raise StoreError(f"{self.path}: store format version {version} is not supported")
        if self.mode == "a":
            self._truncate_uncommitted()

    def _lock_writer(self) -> None:
        """Hold an exclusive lock on ``STORE.lock`` while appending (one writer at a time)."""
        if getattr(self, "_lock_fd", None) is not None:
            return
        fd = try_lock(str(self.path) + ".lock")
        if fd is None:
            raise StoreError(f"{self.path}: another process is writing to this store")
        self._lock_fd = fd

    @property
    def file(self) -> h5py.File:
        """The open ``h5py.File`` (reopened in a forked child process)."""
        if self._pid != os.getpid():
            self._file = None
            self._open()
        return self._file

    def close(self) -> None:
        """Close the file and release the writer lock (only in the process that opened them)."""
        if self._file is not None and self._pid == os.getpid():
            self._file.close()
        self._file = None
        if getattr(self, "_lock_fd", None) is not None and self._pid == os.getpid():
            os.close(self._lock_fd)
        self._lock_fd = None

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:  # noqa: BLE001 - interpreter shutdown
            pass

    def __enter__(self) -> DatasetStore:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __getstate__(self):
        return {"path": self.path, "mode": "r"}

    def __setstate__(self, state: dict) -> None:
        self.__init__(state["path"], state["mode"])

    def _truncate_uncommitted(self) -> None:
        """Drop rows written beyond the committed counters by an interrupted writer."""
        f = self._file
        committed = {
            "cores": f.attrs["n_cores"], "pairs": f.attrs["n_pairs"],
            "records": f.attrs["n_records"], "failures": f.attrs["n_failures"],
            "references": f.attrs["n_references"],
        }
        for group, n in committed.items():
            for ds in f[group].values():
                if ds.shape[0] != n:
                    ds.resize(int(n), axis=0)
        f.flush()

    # ------------------------------------------------------------------ reading
    def __len__(self) -> int:
        return int(self.file.attrs["n_records"])

    def __getitem__(self, index: int) -> Structure:
        return self.structure(index)

    def __iter__(self) -> Iterator[Structure]:
        """Every record in order; each column is read once for all of them (one record at a
        time took ~20 HDF5 reads each: 2.2 s CPU for 1030 records of mini-eqm7)."""
        n = len(self)
        if n == 0:
            return
        f = self.file
        rec = f["records"]
        cols = {name: rec[name][:n] for name in (*_REC_INT, *_REC_FLOAT, *_REC_STR,
                                                 *_present(rec, _REC_OPTIONAL))}
        cores = {name: f[f"cores/{name}"][:] for name in ("numbers", "positions", "forces")}
        pairs = {name: f[f"pairs/{name}"][:] for name in ("positions", "forces")}
        for i in range(n):
            yield self._structure(self._record_from(cols, cores, pairs, i), i)

    @staticmethod
    def _record_from(cols: dict, cores: dict, pairs: dict, index: int) -> dict:
        c0, nc = int(cols["core_start"][index]), int(cols["n_cores"][index])
        p0, npair = int(cols["pair_start"][index]), int(cols["n_pairs"][index])
        out = {
            "numbers": np.array(cores["numbers"][c0:c0 + nc], dtype=np.int64),
            "positions": np.array(cores["positions"][c0:c0 + nc], dtype=np.float64),
            "forces": np.array(cores["forces"][c0:c0 + nc], dtype=np.float64),
            "pairs": np.array(pairs["positions"][p0:p0 + npair], dtype=np.float64),
            "pair_forces": np.array(pairs["forces"][p0:p0 + npair], dtype=np.float64),
            "pbc": bool(cols["pbc"][index]),
        }
        for name in _REC_FLOAT:
            out[name] = np.asarray(cols[name][index], dtype=np.float64)
        for name, shape in _REC_OPTIONAL.items():
            out[name] = (np.asarray(cols[name][index], dtype=np.float64) if name in cols
                         else np.full(shape, np.nan))
        for name in _REC_STR:
            out[name] = _text(cols[name][index])
        return out

    def record(self, index: int) -> dict:
        """Arrays of record ``index`` (reads only that record from disk)."""
        n = len(self)
        if not -n <= index < n:
            raise IndexError(f"{self.path}: record {index} out of range (store has {n})")
        index %= n
        f = self.file
        rec = f["records"]
        c0, nc = int(rec["core_start"][index]), int(rec["n_cores"][index])
        p0, npair = int(rec["pair_start"][index]), int(rec["n_pairs"][index])
        cols = {name: rec[name][index:index + 1]
                for name in (*_REC_INT, *_REC_FLOAT, *_REC_STR, *_present(rec, _REC_OPTIONAL))}
        cols["core_start"], cols["pair_start"] = np.array([0]), np.array([0])
        cores = {name: f[f"cores/{name}"][c0:c0 + nc] for name in ("numbers", "positions",
                                                                   "forces")}
        pairs = {name: f[f"pairs/{name}"][p0:p0 + npair] for name in ("positions", "forces")}
        return self._record_from(cols, cores, pairs, 0)

    def structure(self, index: int) -> Structure:
        """Record ``index`` as a :class:`Structure` (NaN labels become ``None``)."""
        n = len(self)
        return self._structure(self.record(index), index % n if n else index)

    def _structure(self, r: dict, index: int) -> Structure:
        energy = float(r["energy"])
        forces = r["forces"] if np.all(np.isfinite(r["forces"])) else None
        pair_forces = r["pair_forces"] if np.all(np.isfinite(r["pair_forces"])) else None
        stress = r["stress"] if np.all(np.isfinite(r["stress"])) else None
        alpha = r["polarizability"]
        alpha = alpha if np.all(np.isfinite(alpha)) else None
        return Structure(
            numbers=r["numbers"], positions=r["positions"], pairs=r["pairs"], cell=r["cell"],
            pbc=r["pbc"], field=r["field"], charge=float(r["charge"]),
            energy=energy if np.isfinite(energy) else None, forces=forces,
            pair_forces=pair_forces, stress=stress, polarizability=alpha,
            info={k: r[k] for k in (*_REC_STR, "wall_time")},
            source=f"{self.path}, record {index}",
        )

    def keys(self) -> list[str]:
        """Keys of the committed records, in order."""
        return self.text_column("key")

    def text_column(self, name: str) -> list[str]:
        """One text column (``molecule_id``, ``kind``, ``level`` or ``key``) of the committed
        records, in order, without reading their arrays."""
        if name not in _REC_STR:
            raise StoreError(f"{self.path}: no text column {name!r} (known: {_REC_STR})")
        return [_text(k) for k in self.file[f"records/{name}"][: len(self)]]

    def failures(self) -> list[dict]:
        """Recorded failures: dicts with key, molecule_id, kind and reason."""
        g = self.file["failures"]
        n = int(self.file.attrs["n_failures"])
        cols = {name: g[name][:n] for name in _FAIL_STR}
        return [{name: _text(cols[name][i]) for name in _FAIL_STR} for i in range(n)]

    def done_keys(self) -> set[str]:
        """Keys already finished: stored records and recorded failures."""
        return set(self.keys()) | {f["key"] for f in self.failures()}

    def references(self) -> dict[str, dict]:
        """Reference energies (eV) by name, e.g. the hydrides, with their level of theory."""
        g = self.file["references"]
        n = int(self.file.attrs["n_references"])
        out = {}
        for i in range(n):
            out[_text(g["name"][i])] = {"energy": float(g["energy"][i]),
                                        "level": _text(g["level"][i])}
        return out

    @property
    def metadata(self) -> dict:
        """File attributes (format, units, and e.g. the labeling recipe as YAML text)."""
        return {k: _text(v) if isinstance(v, bytes) else v for k, v in self.file.attrs.items()}

    # ------------------------------------------------------------------ writing
    def _writable(self):
        if self.mode != "a":
            raise StoreError(f"{self.path}: opened read-only")
        return self.file

    def append(self, structures: Structure | Iterable[Structure],
               keys: Iterable[str] | None = None) -> int:
        """Append structures as one all-or-nothing batch; return the new number of records.

        ``structure.info`` may hold ``molecule_id``, ``kind``, ``level``, ``wall_time`` and
        ``key``; ``keys`` overrides the latter. Keys must be unique within the store.
        """
        if isinstance(structures, Structure):
            structures = [structures]
        structures = list(structures)
        if not structures:
            return len(self)
        keys = [str(s.info.get("key", "")) for s in structures] if keys is None else list(keys)
        if len(keys) != len(structures):
            raise ValueError("append: as many keys as structures are needed")
        if self._key_cache is None:
            self._key_cache = set(self.keys())
        existing = set(self._key_cache)
        for k in keys:
            if not k:
                raise StoreError(f"{self.path}: every record needs a non-empty key")
            if k in existing:
                raise StoreError(f"{self.path}: a record with key {k!r} is already stored")
            existing.add(k)
        f = self._writable()
        n_rec, n_c, n_p = (int(f.attrs[a]) for a in ("n_records", "n_cores", "n_pairs"))
        core_len = [s.n_cores for s in structures]
        pair_len = [s.n_pairs for s in structures]
        core_start = n_c + np.concatenate([[0], np.cumsum(core_len)[:-1]])
        pair_start = n_p + np.concatenate([[0], np.cumsum(pair_len)[:-1]])
        nan3 = np.full((3, 3), np.nan)

        def forces_of(s: Structure, attr: str, n: int):
            value = getattr(s, attr)
            return np.full((n, 3), np.nan) if value is None else value

        cores = {
            "numbers": np.concatenate([s.numbers for s in structures]).astype(np.int16),
            "positions": np.concatenate([s.positions for s in structures]),
            "forces": np.concatenate([forces_of(s, "forces", s.n_cores) for s in structures]),
        }
        pairs = {
            "positions": np.concatenate([s.pairs for s in structures]).reshape(-1, 3),
            "forces": np.concatenate(
                [forces_of(s, "pair_forces", s.n_pairs) for s in structures]
            ).reshape(-1, 3),
        }
        recs = {
            "core_start": core_start, "n_cores": core_len, "pair_start": pair_start,
            "n_pairs": pair_len, "pbc": [s.pbc for s in structures],
            "energy": [np.nan if s.energy is None else s.energy for s in structures],
            "field": [s.field for s in structures],
            "cell": [s.cell for s in structures],
            "charge": [s.charge for s in structures],
            "stress": [nan3 if s.stress is None else s.stress for s in structures],
            "wall_time": [float(s.info.get("wall_time", np.nan)) for s in structures],
            "molecule_id": [str(s.info.get("molecule_id", "")) for s in structures],
            "kind": [str(s.info.get("kind", "")) for s in structures],
            "level": [str(s.info.get("level", "")) for s in structures],
            "key": keys,
        }
        alphas = [nan3 if s.polarizability is None else s.polarizability for s in structures]
        if "polarizability" in f["records"] or any(s.polarizability is not None
                                                   for s in structures):
            recs["polarizability"] = alphas
            _add_optional_column(f["records"], "polarizability", n_rec)
        _write_rows(f["cores"], cores, n_c)
        _write_rows(f["pairs"], pairs, n_p)
        _write_rows(f["records"], recs, n_rec)
        f.flush()  # data first ...
        f.attrs["n_cores"] = n_c + sum(core_len)
        f.attrs["n_pairs"] = n_p + sum(pair_len)
        f.attrs["n_records"] = n_rec + len(structures)
        f.flush()  # ... then the commit
        self._key_cache.update(keys)
        return n_rec + len(structures)

    def add_failures(self, failures: Iterable[dict]) -> None:
        """Record failed configurations (dicts with key, molecule_id, kind, reason)."""
        failures = list(failures)
        if not failures:
            return
        f = self._writable()
        n = int(f.attrs["n_failures"])
        cols = {name: [str(d.get(name, "")) for d in failures] for name in _FAIL_STR}
        _write_rows(f["failures"], cols, n)
        f.flush()
        f.attrs["n_failures"] = n + len(failures)
        f.flush()

    def set_reference(self, name: str, energy: float, level: str) -> None:
        """Store a reference energy (eV), e.g. of an isolated hydride at ``level``."""
        f = self._writable()
        n = int(f.attrs["n_references"])
        _write_rows(f["references"],
                    {"name": [name], "energy": [float(energy)], "level": [level]}, n)
        f.flush()
        f.attrs["n_references"] = n + 1
        f.flush()

    def set_metadata(self, **values) -> None:
        """Store file attributes (strings or numbers), e.g. ``recipe=<yaml text>``."""
        f = self._writable()
        for key, value in values.items():
            f.attrs[key] = value
        f.flush()

    # ------------------------------------------------------------------ conversion
    def to_extxyz(self, path: str | os.PathLike, convention: str = "native") -> int:
        """Write every record to an extxyz file (via :mod:`emlpack.io.extxyz`); return count."""
        from emlpack.io.extxyz import write_structures

        structures = []
        for s in self:
            s.info = {k: v for k, v in s.info.items() if v != "" and not _is_nan(v)}
            structures.append(s)
        write_structures(path, structures, convention=convention,
                         core_centres=convention == "reference")
        return len(structures)

    @classmethod
    def from_extxyz(cls, xyz_path: str | os.PathLike, store_path: str | os.PathLike,
                    index: str = ":", kind: str = "", level: str = "") -> DatasetStore:
        """Append the frames of an extxyz file to a store (keys ``<file name>:<frame>``)."""
        from emlpack.io.extxyz import read_structures

        xyz_path = Path(xyz_path)
        structures = read_structures(xyz_path, index)
        store = cls(store_path, "a")
        for i, s in enumerate(structures):
            s.info = {
                "key": str(s.info.get("key", f"{xyz_path.name}:{i}")),
                "molecule_id": str(s.info.get("molecule_id", "")),
                "kind": str(s.info.get("kind", kind)),
                "level": str(s.info.get("level", level)),
                "wall_time": float(s.info.get("wall_time", np.nan)),
            }
        store.append(structures)
        return store


# ---------------------------------------------------------------------------------- helpers
def _create_layout(f: h5py.File, chunk_scale: float = 1.0, precision: str = "float64",
                   compress: bool = False) -> None:
    """Empty groups and datasets; ``chunk_scale`` < 1 makes small files (e.g. shards) compact;
    ``precision`` is the per-particle columns' float type, ``compress`` adds gzip + shuffle."""
    f.attrs["format"] = FORMAT
    f.attrs["format_version"] = FORMAT_VERSION
    f.attrs["precision"] = precision
    filters = {"compression": "gzip", "compression_opts": 6, "shuffle": True} if compress else {}
    for key, unit in UNITS.items():
        f.attrs[f"unit_{key}"] = unit
    for name in ("n_records", "n_cores", "n_pairs", "n_failures", "n_references"):
        f.attrs[name] = 0

    def make(group: h5py.Group, name: str, shape: tuple[int, ...], dtype: DTypeLike,
             chunk: int = 1024):
        chunk = max(4, int(chunk * chunk_scale))
        group.create_dataset(name, shape=(0, *shape), maxshape=(None, *shape), dtype=dtype,
                             chunks=(chunk, *shape), **filters)

    per_particle = np.dtype(precision)
    cores, pairs = f.create_group("cores"), f.create_group("pairs")
    make(cores, "numbers", (), np.int16, 4096)
    make(cores, "positions", (3,), per_particle, 4096)
    make(cores, "forces", (3,), per_particle, 4096)
    make(pairs, "positions", (3,), per_particle, 4096)
    make(pairs, "forces", (3,), per_particle, 4096)
    rec = f.create_group("records")
    for name, shape in (*_REC_FLOAT.items(), *_REC_OPTIONAL.items()):
        make(rec, name, shape, np.float64)
    for name, dtype in _REC_INT.items():
        make(rec, name, (), dtype)
    for name in _REC_STR:
        make(rec, name, (), f"S{_STR_LEN[name]}")
    fail = f.create_group("failures")
    for name in _FAIL_STR:
        make(fail, name, (), f"S{_STR_LEN[name]}", 256)
    ref = f.create_group("references")
    make(ref, "energy", (), np.float64, 64)
    for name in _REF_STR:
        make(ref, name, (), f"S{_STR_LEN[name]}", 64)


def _present(group: h5py.Group, optional: dict) -> tuple[str, ...]:
    """The optional columns ``optional`` that ``group`` has."""
    return tuple(name for name in optional if name in group)


def _add_optional_column(records: h5py.Group, name: str, n_rows: int) -> None:
    """Create the optional record column ``name`` in a store written before it existed, NaN
    for its ``n_rows`` committed records (chunked and filtered like the ``stress`` column)."""
    if name in records:
        return
    like = records["stress"]
    ds = records.create_dataset(
        name, shape=(n_rows, *_REC_OPTIONAL[name]), maxshape=(None, *_REC_OPTIONAL[name]),
        dtype=np.float64, chunks=(like.chunks[0], *_REC_OPTIONAL[name]),
        compression=like.compression, compression_opts=like.compression_opts,
        shuffle=like.shuffle, fillvalue=np.nan)
    records.file.attrs[f"unit_{name}"] = UNITS[name]
    del ds


def _write_rows(group: h5py.Group, columns: dict, start: int) -> None:
    for name, values in columns.items():
        ds = group[name]
        if ds.dtype.kind == "S":
            values = [_encode(v, ds.dtype.itemsize, name) for v in values]
        values = np.asarray(values, dtype=ds.dtype)
        if len(values) == 0:
            continue
        ds.resize(start + len(values), axis=0)
        ds[start:start + len(values)] = values


def _encode(value: str, size: int, name: str) -> bytes:
    data = str(value).encode()
    if len(data) <= size:
        return data
    if name == "key":
        raise StoreError(f"record key longer than {size} bytes: {value!r}")
    return data[: size - 3].decode(errors="ignore").encode() + b"..."


def _text(value: bytes | str) -> str:
    return value.decode() if isinstance(value, bytes) else str(value)


def _is_nan(value: object) -> bool:
    return isinstance(value, float) and not np.isfinite(value)
