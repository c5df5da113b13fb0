"""HDF5 dataset store: ragged eMLP records, readable by index, in one of two layouts.

Units everywhere: emlpack's public ones (Å, eV, eV/Å, V/Å, eV/Å^3, e, e·Å²/V).

**Appendable layout** (``format_version`` 1): the working stores of labeling runs, and the
shards written before the packed layout existed. One chunked, growable dataset per column::

    /cores/numbers (n_cores_total,) int16      /cores/positions, /cores/forces (.., 3)
    /pairs/positions (n_pairs_total, 3)        /pairs/forces (n_pairs_total, 3)
    /records/{core_start, n_cores, pair_start, n_pairs, energy, field(3), cell(3,3), pbc,
              charge, stress(3,3), molecule_id, kind, level, key, wall_time,
              polarizability(3,3)}
    /failures/{key, molecule_id, kind, reason}
    /references/{name, energy, level}          (e.g. the hydrides H2, CH4, NH3, H2O)

**Packed layout** (``format_version`` 2, :func:`write_packed`): a finished, immutable shard
written in one go. The same columns as fields of one compound (table) dataset per group,
``/cores``, ``/pairs``, ``/records``, ``/failures``, ``/references`` (the last two only when
they have rows), of fixed size, gzip + shuffle where that makes them smaller, with HDF5 1.10
object headers and no metadata block padding; the file attributes (precision, units, counts,
run information, recipe) are one UTF-8 JSON attribute ``metadata`` of fixed length (a
variable-length string would cost a 4 kB global heap). Every chunked column of the appendable
layout carries ~2.5 kB of chunk index and header whatever its length (~70 kB a file); the
packed layout carries ~2-3 kB a file in all. A packed file opens read-only; readers handle both
layouts alike, and read appendable files exactly as before.

Missing labels are NaN (``energy``, ``forces``, ``stress``, ``polarizability``). The
``polarizability`` column (e·Å²/V, clamped nuclei) is optional in the appendable layout: stores
written before it existed read as unlabelled, and the first record with one adds the column
(NaN for the records before it). Each record has a unique ``key``
(e.g. ``"qm7-0003/nms800/0017"``), which makes labeling resumable.

Crash safety (appendable layout): the number of committed rows of every group is an attribute
of the file (``n_records``, ``n_cores``, ``n_pairs``, ...). An append writes and flushes the
data beyond the committed end first and only then moves the counters (and flushes again). A
process killed in between leaves rows beyond the counters, which readers ignore and the next
writer overwrites: a record is either fully there or absent. (HDF5 has no journal; a kill during
the flush of HDF5's own metadata could still damage the file, which is why writers batch records
and flush rarely relative to the work between them.) A packed file is written under a temporary
name and renamed, so it is complete or absent.

The reader is torch-free; open one :class:`DatasetStore` per process (it reopens itself after a
fork, so it can be shared with data-loader workers).
"""

from __future__ import annotations

import json
import os
import zlib
from collections.abc import Iterable, Iterator, Mapping
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from emlpack._files import atomic_path, try_lock
from emlpack.errors import EmlpackError
from emlpack.structure import Structure

if TYPE_CHECKING:
    import h5py

FORMAT = "emlpack-store"
#: the appendable, chunked layout (working stores; shards written before the packed layout)
FORMAT_VERSION = 1
#: the packed, write-once layout of finished shards (:func:`write_packed`)
PACKED_VERSION = 2
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
#: rows per chunk of the appendable layout's columns, by group
_CHUNK_ROWS = {"cores": 4096, "pairs": 4096, "records": 1024, "failures": 256,
               "references": 64}
#: packed layout: at most this many bytes per chunk (below h5py's 1 MiB chunk cache, so that
#: reading record after record decompresses each chunk once)
_PACKED_CHUNK_BYTES = 256 * 1024
#: packed layout: what a filter pipeline and chunk index cost beyond a contiguous dataset
#: (bytes, measured); gzip is used only where it saves more
_FILTER_BYTES = 64
_GZIP = {"compression": "gzip", "compression_opts": 6, "shuffle": True}


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
        self._precision = _checked_precision(precision)
        self._compress = bool(compress)
        self._packed = False
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
        if self.mode == "a" and _format_version(self.path) == PACKED_VERSION:
            raise StoreError(f"{self.path}: a packed shard is written once and never appended"
                             " to (open it with mode 'r')")
        try:
            if self.mode == "a":
                self._lock_writer()
            # HDF5's own locking would stop readers from watching a store being written (and
            # mixes badly within one process); one writer at a time is ensured by _lock_writer
            self._file = h5py.File(self.path, "r" if self.mode == "r" else "r+", locking=False)
        except OSError as exc:
            raise StoreError(f"{self.path}: cannot open as an HDF5 dataset store: {exc}") from None
        self._pid = os.getpid()
        if _text(self._file.attrs.get("format", b"")) != FORMAT:
            raise StoreError(f"{self.path}: not an emlpack dataset store")
        version = int(self._file.attrs.get("format_version", -1))
        if version not in (FORMAT_VERSION, PACKED_VERSION):
            raise StoreError(f"{self.path}: store format version {version} is not supported")
        self._packed = version == PACKED_VERSION
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
    def _count(self, group: str) -> int:
        """Committed rows of ``group`` (``records``, ``cores``, ``pairs``, ``failures``,
        ``references``)."""
        f = self.file
        if self._packed:
            return int(f[group].shape[0]) if group in f else 0
        return int(f.attrs[f"n_{group}"])

    def _rows(self, group: str, names: Iterable[str], start: int = 0,
              stop: int | None = None) -> dict[str, np.ndarray]:
        """The columns ``names`` that ``group`` has, rows ``start:stop`` (default: to the
        committed end), from either layout."""
        f = self.file
        stop = self._count(group) if stop is None else stop
        if group not in f:
            return {}
        node = f[group]
        if self._packed:
            present = [n for n in names if n in node.dtype.names]
            if not present:
                return {}
            rows = node.fields(present)[start:stop] if stop > start else np.zeros(
                0, dtype=[(n, node.dtype[n]) for n in present])
            return {n: rows[n] for n in present}
        return {n: node[n][start:stop] for n in names if n in node}

    def __len__(self) -> int:
        return self._count("records")

    def __getitem__(self, index: int) -> Structure:
        return self.structure(index)

    def __iter__(self) -> Iterator[Structure]:
        """Every record in order; each column is read once for all of them (one record at a
        time took ~20 HDF5 reads each: 2.2 s CPU for 1030 records of mini-eqm7)."""
        n = len(self)
        if n == 0:
            return
        cols = self._rows("records", _RECORD_COLUMNS)
        cores = self._rows("cores", ("numbers", "positions", "forces"))
        pairs = self._rows("pairs", ("positions", "forces"))
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
        cols = self._rows("records", _RECORD_COLUMNS, index, index + 1)
        c0, nc = int(cols["core_start"][0]), int(cols["n_cores"][0])
        p0, npair = int(cols["pair_start"][0]), int(cols["n_pairs"][0])
        cols["core_start"], cols["pair_start"] = np.array([0]), np.array([0])
        cores = self._rows("cores", ("numbers", "positions", "forces"), c0, c0 + nc)
        pairs = self._rows("pairs", ("positions", "forces"), p0, p0 + npair)
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
        return [_text(k) for k in self._rows("records", (name,)).get(name, [])]

    def failures(self) -> list[dict]:
        """Recorded failures: dicts with key, molecule_id, kind and reason."""
        n = self._count("failures")
        cols = self._rows("failures", _FAIL_STR)
        return [{name: _text(cols[name][i]) for name in _FAIL_STR} for i in range(n)]

    def done_keys(self) -> set[str]:
        """Keys already finished: stored records and recorded failures."""
        return set(self.keys()) | {f["key"] for f in self.failures()}

    def references(self) -> dict[str, dict]:
        """Reference energies (eV) by name, e.g. the hydrides, with their level of theory."""
        n = self._count("references")
        g = self._rows("references", ("name", "energy", "level"))
        out = {}
        for i in range(n):
            out[_text(g["name"][i])] = {"energy": float(g["energy"][i]),
                                        "level": _text(g["level"][i])}
        return out

    @property
    def metadata(self) -> dict:
        """File attributes (format, units, and e.g. the labeling recipe as YAML text); of a
        packed file, those of its ``metadata`` JSON attribute beside ``format`` and
        ``format_version``."""
        out = {k: _text(v) if isinstance(v, bytes) else v for k, v in self.file.attrs.items()}
        if self._packed:
            out.update(json.loads(out.pop("metadata", "{}")))
        return out

    @property
    def storage(self) -> dict:
        """How the file holds its data: ``format_version`` (:data:`FORMAT_VERSION`
        appendable, :data:`PACKED_VERSION` packed), ``precision`` of the positions and forces,
        ``compress`` (gzip on any of them)."""
        f = self.file
        if self._packed:
            precision = f["cores"].dtype["positions"].base.name
            compress = any(f[g].compression is not None for g in f)
        else:
            precision = f["cores/positions"].dtype.name
            compress = f["cores/positions"].compression is not None
        return {"format_version": PACKED_VERSION if self._packed else FORMAT_VERSION,
                "precision": precision, "compress": compress}

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
        _check_keys(keys, self._key_cache, self.path)
        f = self._writable()
        n_rec, n_c, n_p = (int(f.attrs[a]) for a in ("n_records", "n_cores", "n_pairs"))
        cores, pairs, recs = _columns(structures, keys)
        core_len, pair_len = recs["n_cores"], recs["n_pairs"]
        recs["core_start"] = n_c + recs["core_start"]
        recs["pair_start"] = n_p + recs["pair_start"]
        if "polarizability" in f["records"] or any(s.polarizability is not None
                                                   for s in structures):
            _add_optional_column(f["records"], "polarizability", n_rec)
        else:
            del recs["polarizability"]
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


def write_packed(path: str | os.PathLike, structures: Iterable[Structure],
                 failures: Iterable[dict] = (), references: Mapping[str, dict] | None = None,
                 metadata: Mapping[str, str | int | float | bool] | None = None,
                 precision: str = "float64", compress: bool = True) -> Path:
    """Write a finished shard in the packed layout (:data:`PACKED_VERSION`) in one go.

    Args:
        path: the ``.h5`` file (written under a temporary name, then renamed onto it).
        structures: the records, as :meth:`DatasetStore.append` takes them (keys from
            ``info["key"]``, unique and non-empty).
        failures: dicts with key, molecule_id, kind and reason (:meth:`DatasetStore.failures`).
        references: name -> ``{"energy": eV, "level": str}`` (:meth:`DatasetStore.references`).
        metadata: further attributes (strings or numbers), e.g. ``recipe`` and ``run_*``.
        precision: ``"float64"`` or ``"float32"``, the positions' and forces' type (as for
            :class:`DatasetStore`); energies, fields, cells and stresses stay float64.
        compress: gzip + shuffle on each table where that makes it smaller.
    Returns ``path``; :class:`DatasetStore` reads it (read-only) like any store.
    """
    import h5py

    precision = _checked_precision(precision)
    path = Path(path)
    structures = list(structures)
    keys = [str(s.info.get("key", "")) for s in structures]
    _check_keys(keys, set(), path)
    cores, pairs, recs = _columns(structures, keys)
    failures = list(failures)
    refs = dict(references or {})
    columns = {
        "cores": cores, "pairs": pairs, "records": recs,
        "failures": {name: [str(d.get(name, "")) for d in failures] for name in _FAIL_STR},
        "references": {"name": list(refs), "energy": [float(r["energy"]) for r in refs.values()],
                       "level": [str(r["level"]) for r in refs.values()]},
    }
    tables = {group: _table(columns[group], fields)
              for group, fields in _schema(precision).items()}
    info: dict = {"precision": precision, **{f"unit_{k}": v for k, v in UNITS.items()},
                  **{f"n_{group}": len(table) for group, table in tables.items()}}
    for key, value in (metadata or {}).items():
        value = value.item() if isinstance(value, np.generic) else value
        if not isinstance(value, (str, int, float, bool)):
            raise StoreError(f"{path}: metadata {key!r} must be a string or a number, got"
                             f" {type(value).__name__}")
        info[key] = value
    with atomic_path(path) as tmp:
        # HDF5 1.10 object headers (readable by HDF5 >= 1.10) and no 2 kB metadata blocks
        with h5py.File(tmp, "w", libver=("v110", "v110"), meta_block_size=0) as f:
            f.attrs["format"] = np.bytes_(FORMAT.encode())
            f.attrs["format_version"] = PACKED_VERSION
            f.attrs["metadata"] = np.bytes_(json.dumps(info).encode())
            for group, table in tables.items():
                if len(table) or group in ("cores", "pairs", "records"):
                    _put_table(f, group, table, compress)
    return path


# ---------------------------------------------------------------------------------- helpers
#: every column of ``/records`` (the optional ones too)
_RECORD_COLUMNS = (*_REC_INT, *_REC_FLOAT, *_REC_OPTIONAL, *_REC_STR)


def _checked_precision(precision: str) -> str:
    """``precision`` when it is ``"float64"`` or ``"float32"``; ValueError otherwise."""
    if precision not in ("float64", "float32"):
        raise ValueError(f"precision must be 'float64' or 'float32', got {precision!r}")
    return precision


def _schema(precision: str) -> dict[str, list[tuple[str, np.dtype, tuple[int, ...]]]]:
    """The columns of each group, ``(name, dtype, shape of one row)``, for both layouts;
    ``precision`` is the per-particle columns' float type."""
    per_particle = np.dtype(precision)

    def text(name: str) -> tuple[str, np.dtype, tuple[int, ...]]:
        return name, np.dtype(f"S{_STR_LEN[name]}"), ()

    return {
        "cores": [("numbers", np.dtype(np.int16), ()), ("positions", per_particle, (3,)),
                  ("forces", per_particle, (3,))],
        "pairs": [("positions", per_particle, (3,)), ("forces", per_particle, (3,))],
        "records": [*((name, np.dtype(np.float64), shape)
                      for name, shape in {**_REC_FLOAT, **_REC_OPTIONAL}.items()),
                    *((name, np.dtype(dtype), ()) for name, dtype in _REC_INT.items()),
                    *(text(name) for name in _REC_STR)],
        "failures": [text(name) for name in _FAIL_STR],
        "references": [("energy", np.dtype(np.float64), ()),
                       *(text(name) for name in _REF_STR)],
    }


def _create_layout(f: h5py.File, chunk_scale: float = 1.0, precision: str = "float64",
                   compress: bool = False) -> None:
    """Empty groups and datasets of the appendable layout; ``chunk_scale`` < 1 makes small
    files compact; ``precision`` is the per-particle columns' float type, ``compress`` adds
    gzip + shuffle."""
    f.attrs["format"] = FORMAT
    f.attrs["format_version"] = FORMAT_VERSION
    f.attrs["precision"] = precision
    filters = _GZIP if compress else {}
    for key, unit in UNITS.items():
        f.attrs[f"unit_{key}"] = unit
    for name in ("n_records", "n_cores", "n_pairs", "n_failures", "n_references"):
        f.attrs[name] = 0
    for group_name, fields in _schema(precision).items():
        group = f.create_group(group_name)
        chunk = max(4, int(_CHUNK_ROWS[group_name] * chunk_scale))
        for name, dtype, shape in fields:
            group.create_dataset(name, shape=(0, *shape), maxshape=(None, *shape),
                                 dtype=dtype, chunks=(chunk, *shape), **filters)


def _check_keys(keys: list[str], stored: set[str], path: Path) -> None:
    """Raise :class:`StoreError` unless ``keys`` are non-empty, unique, and not in
    ``stored``."""
    existing = set(stored)
    for k in keys:
        if not k:
            raise StoreError(f"{path}: every record needs a non-empty key")
        if k in existing:
            raise StoreError(f"{path}: a record with key {k!r} is already stored")
        existing.add(k)


def _columns(structures: list[Structure], keys: list[str]) -> tuple[dict, dict, dict]:
    """The rows of ``structures`` as ``(cores, pairs, records)`` columns (``core_start`` and
    ``pair_start`` counted from 0; ``polarizability`` NaN where unlabelled)."""
    nan3 = np.full((3, 3), np.nan)

    def stack(values: list, shape: tuple[int, ...]) -> np.ndarray:
        return np.concatenate(values).reshape(-1, *shape) if values else np.zeros((0, *shape))

    def labels(attr: str, n_of: str) -> list:
        return [np.full((getattr(s, n_of), 3), np.nan) if getattr(s, attr) is None
                else getattr(s, attr) for s in structures]

    core_len = np.array([s.n_cores for s in structures], dtype=np.int64)
    pair_len = np.array([s.n_pairs for s in structures], dtype=np.int64)
    cores = {
        "numbers": stack([s.numbers for s in structures], ()).astype(np.int16),
        "positions": stack([s.positions for s in structures], (3,)),
        "forces": stack(labels("forces", "n_cores"), (3,)),
    }
    pairs = {
        "positions": stack([s.pairs for s in structures], (3,)),
        "forces": stack(labels("pair_forces", "n_pairs"), (3,)),
    }
    recs = {
        "core_start": np.cumsum(core_len) - core_len, "n_cores": core_len,
        "pair_start": np.cumsum(pair_len) - pair_len, "n_pairs": pair_len,
        "pbc": [s.pbc for s in structures],
        "energy": [np.nan if s.energy is None else s.energy for s in structures],
        "field": [s.field for s in structures],
        "cell": [s.cell for s in structures],
        "charge": [s.charge for s in structures],
        "stress": [nan3 if s.stress is None else s.stress for s in structures],
        "wall_time": [float(s.info.get("wall_time", np.nan)) for s in structures],
        "polarizability": [nan3 if s.polarizability is None else s.polarizability
                           for s in structures],
        "molecule_id": [str(s.info.get("molecule_id", "")) for s in structures],
        "kind": [str(s.info.get("kind", "")) for s in structures],
        "level": [str(s.info.get("level", "")) for s in structures],
        "key": keys,
    }
    return cores, pairs, recs


def _table(columns: dict, fields: list[tuple[str, np.dtype, tuple[int, ...]]]) -> np.ndarray:
    """``columns`` as one structured array with ``fields`` (a packed-layout table)."""
    n = len(columns[fields[0][0]])
    out = np.zeros(n, dtype=[(name, dtype, shape) for name, dtype, shape in fields])
    for name, dtype, shape in fields:
        out[name] = _as_column(columns[name], dtype, name).reshape(n, *shape)
    return out


def _put_table(f: h5py.File, name: str, table: np.ndarray, compress: bool) -> None:
    """Write ``table`` as the fixed-size dataset ``name``: contiguous, or in chunks of at most
    :data:`_PACKED_CHUNK_BYTES` with gzip + shuffle when ``compress`` and that pays."""
    filters: dict = {}
    if compress and _gzip_pays(table):
        rows = max(1, min(len(table), _PACKED_CHUNK_BYTES // table.dtype.itemsize))
        filters = {"chunks": (rows,), **_GZIP}
    f.create_dataset(name, data=table, **filters)


def _gzip_pays(table: np.ndarray) -> bool:
    """True when gzip + shuffle (estimated with zlib on the shuffled bytes) saves more than
    the :data:`_FILTER_BYTES` a filtered dataset costs."""
    raw = table.tobytes()
    if not raw:
        return False
    shuffled = np.frombuffer(raw, np.uint8).reshape(len(table), -1).T.tobytes()
    return len(zlib.compress(shuffled, _GZIP["compression_opts"])) + _FILTER_BYTES < len(raw)


def _format_version(path: Path) -> int:
    """The ``format_version`` attribute of the HDF5 file ``path`` (-1 when unreadable)."""
    import h5py

    try:
        with h5py.File(path, "r", locking=False) as f:
            return int(f.attrs.get("format_version", -1))
    except OSError:
        return -1


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
        values = _as_column(values, ds.dtype, name)
        if len(values) == 0:
            continue
        ds.resize(start + len(values), axis=0)
        ds[start:start + len(values)] = values


def _as_column(values: Iterable, dtype: np.dtype, name: str) -> np.ndarray:
    """``values`` as an array of ``dtype`` (text as UTF-8, cut to the column's length)."""
    if dtype.kind == "S":
        values = [_encode(v, dtype.itemsize, name) for v in values]
    return np.asarray(values, dtype=dtype)


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
