"""Shard size on disk: committed shards against the same records re-exported in the packed layout.

For each data-set folder, the records, failures, references and metadata of its committed shards
(appendable layout, ``format_version`` 1) are written again with
:func:`emlpack.data.store.write_packed` into a temporary folder, one packed shard per committed
shard and, to show what fewer and larger shards give, in groups of ``--group`` consecutive
shards. It prints bytes per configuration (file size / records) and the HDF5 overhead (file size
minus the storage of its datasets), and checks that every record reads back the same.
``--precision``/``--compress`` default to what each folder's shards hold.

Usage::

    OMP_NUM_THREADS=1 PYTHONPATH=src python benchmarks/shard_size.py \\
        datasets/qm7-pbe0-def2svpd datasets/beta-glycine datasets/mini-eqm7 --group 4
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import h5py
import numpy as np

from emlpack.data.shards import shard_paths
from emlpack.data.store import DatasetStore, write_packed

RECORD_FIELDS = ("numbers", "positions", "forces", "pairs", "pair_forces", "energy", "field",
                 "cell", "stress", "charge", "pbc", "polarizability")


def data_bytes(path: Path) -> int:
    """Bytes the datasets of the HDF5 file ``path`` occupy (the rest is HDF5 overhead)."""
    total = 0

    def visit(_name: str, obj: object) -> None:
        nonlocal total
        if isinstance(obj, h5py.Dataset):
            total += obj.id.get_storage_size()

    with h5py.File(path, "r") as f:
        f.visititems(visit)
    return total


def repack(shards: list[Path], out: Path, precision: str | None,
           compress: bool | None) -> tuple[int, int]:
    """Write the records of ``shards`` as one packed shard ``out``; return (records, bytes)
    after checking that every record reads back the same (float32 columns: exactly the
    float32 values)."""
    records, structures, failures, references, metadata = [], [], [], {}, {}
    for path in shards:
        with DatasetStore(path) as store:
            records += [store.record(i) for i in range(len(store))]
            structures += list(store)
            failures += store.failures()
            references.update(store.references())
            layout = store.storage
            metadata = {k: v for k, v in store.metadata.items()
                        if k.startswith("run_") or k == "recipe"}
    write_packed(out, structures, failures, references, metadata,
                 precision=precision or layout["precision"],
                 compress=layout["compress"] if compress is None else compress)
    with DatasetStore(out) as packed:
        assert len(packed) == len(records) and packed.failures() == failures
        for i, ref in enumerate(records):
            got = packed.record(i)
            for name, value in ref.items():
                if isinstance(value, str) or name in ("pbc",):
                    assert got[name] == value, (out, i, name)
                else:
                    assert np.array_equal(got[name], value, equal_nan=True), (out, i, name)
    return len(records), out.stat().st_size


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("folders", nargs="+", type=Path)
    p.add_argument("--group", type=int, default=4, help="also pack this many shards as one")
    p.add_argument("--precision", choices=("float64", "float32"))
    p.add_argument("--compress", type=int, choices=(0, 1))
    args = p.parse_args()
    compress = None if args.compress is None else bool(args.compress)
    with tempfile.TemporaryDirectory() as tmp:
        for folder in args.folders:
            paths = shard_paths(folder)
            n = sum(len(DatasetStore(q)) for q in paths)
            size = sum(q.stat().st_size for q in paths)
            overhead = size - sum(data_bytes(q) for q in paths)
            print(f"{folder}: {len(paths)} shards, {n} configurations")
            print(f"  committed (format 1): {size / n / 1e3:.2f} kB per configuration,"
                  f" HDF5 overhead {overhead / len(paths) / 1e3:.1f} kB per shard")
            for group in sorted({1, args.group}):
                chunks = [paths[k:k + group] for k in range(0, len(paths), group)]
                n_total = b_total = over = 0
                for k, chunk in enumerate(chunks):
                    out = Path(tmp) / f"{folder.name}-{group}-{k:04d}.h5"
                    m, b = repack(chunk, out, args.precision, compress)
                    n_total, b_total = n_total + m, b_total + b
                    over += b - data_bytes(out)
                print(f"  packed (format 2), {group} shard(s) per file: {len(chunks)} files,"
                      f" {b_total / n_total / 1e3:.2f} kB per configuration,"
                      f" HDF5 overhead {over / len(chunks) / 1e3:.1f} kB per file"
                      f" ({n_total / len(chunks):.1f} records per file)")


if __name__ == "__main__":
    main()
