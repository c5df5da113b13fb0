"""The beta-glycine campaign's long jobs, committing their finished work as they go (issue 52).

``run_study.py optimize`` and ``label`` store every CP2K calculation in working stores under
``WORKDIR`` (not committed). Here they run with the finished records turned into immutable
shards of the data set ``datasets/beta-glycine/shards/NNNN.h5`` every ``--shard-minutes`` once
there are ``--shard-min-records`` new ones (and at the end, also on SIGTERM, whatever is left),
committed at once with ``--commit``; several processes may
export side by side (a lock orders them). Every stage of run_study.py reads the shards beside
the working stores (``dataset`` of config.yaml), so a fresh machine labels only what no shard
holds, and the optimisation replays its committed steps (copied into its working store first:
no calculation) and goes on from the last one::

    python examples/beta_glycine/campaign_job.py optimize --commit
    python examples/beta_glycine/campaign_job.py label --shard 0/2 --commit   # and 1/2
    python examples/beta_glycine/campaign_job.py label --reference-only --commit  # FD only
    python examples/beta_glycine/campaign_job.py card      # datasets/beta-glycine/README.md

``key=value`` arguments override ``config.yaml`` as for ``run_study.py``. The optimisation's
defaults here: enabled, one single-process CP2K, ``fmax`` 0.02 eV/Å, at most 200 steps.
Shards keep float64 (an optimisation replays its steps bit for bit), gzip-compressed, in the
packed layout of :func:`emlpack.data.store.write_packed`.
"""

from __future__ import annotations

import argparse
import collections
import os
import socket
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import run_study  # noqa: E402

from emlpack._files import try_lock, write_text_atomic  # noqa: E402
from emlpack.commits import git_commit  # noqa: E402
from emlpack.data.shards import SHARD_DIR, shard_paths, shards_size_text  # noqa: E402
from emlpack.data.store import DatasetStore  # noqa: E402
from emlpack.interrupts import terminate_as_interrupt  # noqa: E402
from emlpack.qm.campaign import SHARD_MIN_RECORDS, export_shard, unexported  # noqa: E402

OPTIMIZE = ["optimization.enabled=true", "optimization.cp2k.n_processes=1",
            "optimization.cp2k.mpirun=null", "optimization.fmax=0.02",
            "optimization.max_steps=200"]
STORAGE = {"precision": "float64", "compress": True}


def restore(folder: Path, store_path: Path, prefix: str) -> int:
    """Append the shards' records under ``prefix/`` that ``store_path`` lacks (the
    optimisation replays from its own store); returns how many."""
    store_path.parent.mkdir(parents=True, exist_ok=True)
    n = 0
    with DatasetStore(store_path, "a") as work:
        have = set(work.keys())
        for path in shard_paths(folder):
            with DatasetStore(path, "r") as shard:
                new = [s for s in shard if s.info.get("key") not in have
                       and str(s.info.get("key")).startswith(f"{prefix}/")]
            if new:
                work.append(new)
                n += len(new)
    return n


class Exporter:
    """Turns a working store's new records into a committed shard every ``minutes``, once
    there are ``min_records`` of them (records and failures)."""

    def __init__(self, study: run_study.Study, minutes: float, commit: bool, what: str,
                 min_records: int = SHARD_MIN_RECORDS) -> None:
        self.study, self.minutes, self.commit, self.what = study, minutes, commit, what
        self.min_records = min_records
        self.folder = study.dataset
        self.last, self.since = time.monotonic(), time.time()

    def flush(self, store: DatasetStore) -> None:
        """Export now (under a lock: other processes export to the same folder)."""
        lock_path = self.folder / SHARD_DIR / ".export.lock"
        lock_path.parent.mkdir(parents=True, exist_ok=True)
        while (lock := try_lock(lock_path)) is None:
            time.sleep(1.0)
        try:
            now = time.time()
            shard = export_shard(self.folder, store, {
                "host": socket.gethostname(), "workers": 1, "threads": 1, "job": self.what,
                "started": self.since, "ended": now, "wall_s": now - self.since,
                "level": self.study.level()}, STORAGE)
            self.last, self.since = time.monotonic(), now
            if shard is not None:
                self.study.log(f"campaign_job: wrote {shard}")
                write_card(self.study)
                if self.commit:
                    git_commit([self.folder / SHARD_DIR, self.folder / "README.md"],
                               f"beta-glycine {self.what}: shard {shard.stem}")
        finally:
            os.close(lock)

    def on_stored(self, store: DatasetStore) -> None:
        if (time.monotonic() - self.last > self.minutes * 60
                and sum(map(len, unexported(self.folder, store))) >= self.min_records):
            self.flush(store)


def write_card(study: run_study.Study) -> Path:
    """``datasets/beta-glycine/README.md`` from the shards: counts by kind, level, seconds per
    calculation, failures, size."""
    folder = study.dataset
    kinds: collections.Counter = collections.Counter()
    walls: dict[str, list[float]] = collections.defaultdict(list)
    failures, n = [], 0
    for path in shard_paths(folder):
        with DatasetStore(path, "r") as store:
            failures += store.failures()
            for s in store:
                key = str(s.info.get("key"))
                group = key.split("/")[0] if key.startswith(("opt/", "ref")) else (
                    "stress set" if s.stress is not None else "field set")
                kinds[group] += 1
                walls[group].append(float(s.info.get("wall_time", np.nan)))
                n += 1
    lines = [
        "# beta-glycine: CP2K labels of the crystal campaign (issue 52)", "",
        "Generated by `examples/beta_glycine/campaign_job.py card`; do not edit by hand. Read"
        " with `emlpack.data.store.DatasetStore` per shard, or through"
        " `examples/beta_glycine/run_study.py` (config.yaml's `dataset`).", "",
        f"- level: {study.level()} (Γ point of the 20-atom cell, or of the supercell the level"
        " names, labels per cell; identical for every record; examples/beta_glycine/LEVEL.md);",
        "- records: 'opt/NNN' the DFT cell optimisation's steps (stress set, zero field),"
        " 'ref-opt/...' the finite-difference calculations at the DFT optimum, the rest the"
        " sampling rounds of config.yaml (field set: a random field ≤ 0.01 au, no stress;"
        " stress set: a random strain ≤ 2 %, zero field, stress labels);",
        f"- {n} configurations in {len(shard_paths(folder))} shards"
        f" ({shards_size_text(folder)});",
        f"- failures: {len(failures)}" + ("" if not failures else " (" + "; ".join(
            sorted({f['reason'][:80] for f in failures})) + ")") + ".", "",
        "| records | configurations | median s per calculation |", "|---|---|---|"]
    for group, count in sorted(kinds.items()):
        w = [x for x in walls[group] if np.isfinite(x)]
        lines.append(f"| {group} | {count} | {f'{np.median(w):.0f}' if w else '-'} |")
    path = folder / "README.md"
    write_text_atomic(path, "\n".join(lines) + "\n")
    return path


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("action", choices=("optimize", "label", "card"))
    p.add_argument("overrides", nargs="*", help="key=value overrides of config.yaml")
    p.add_argument("--config", default=str(HERE / "config.yaml"))
    p.add_argument("--shard", default="0/1", help="label: this process's share, i/n")
    p.add_argument("--shard-minutes", type=float, default=25.0)
    p.add_argument("--shard-min-records", type=int, default=SHARD_MIN_RECORDS,
                   help="fewest new records per shard before the end")
    p.add_argument("--commit", action="store_true", help="commit every new shard")
    p.add_argument("--reference-only", action="store_true",
                   help="label: only the finite-difference reference calculations (19)")
    args = p.parse_args(argv)
    extra = OPTIMIZE if args.action == "optimize" else []
    cfg = run_study.load_config(args.config, [*extra, *args.overrides])
    study = run_study.Study(cfg, log=lambda m: print(time.strftime("%H:%M:%S"), m, flush=True))
    if study.dataset is None:
        raise SystemExit("campaign_job.py: config.yaml names no dataset")
    if args.action == "card":
        print(write_card(study))
        return
    index, n_shards = (int(x) for x in args.shard.split("/"))
    exporter = Exporter(study, args.shard_minutes, args.commit, args.action,
                        args.shard_min_records)
    study.on_stored = exporter.on_stored
    if args.action == "optimize":
        n = restore(study.dataset, study.store_path, "opt")
        study.log(f"campaign_job: {n} optimisation steps restored from the shards")
        work = study.store_path
    else:
        work = study.shard_store(index)
    try:
        with terminate_as_interrupt():
            try:
                if args.action == "optimize":
                    run_study.stage_optimize(study)
                else:
                    run_study.stage_label(study, shard=(index, n_shards),
                                          reference_only=args.reference_only)
            finally:
                with DatasetStore(work, "a") as store:
                    exporter.flush(store)
    except KeyboardInterrupt:  # SIGTERM or Ctrl-C: the finished records are in a shard
        raise SystemExit(f"campaign_job.py {args.action}: interrupted; its finished work is"
                         " saved (re-run the same command to go on)") from None


if __name__ == "__main__":
    main()
