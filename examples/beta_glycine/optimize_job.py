"""The DFT optimisation of beta-glycine as a long job whose steps are committed as they go.

``run_study.py optimize`` stores every BFGS step in ``WORKDIR/labels.h5`` (a working store, not
committed). This job runs that stage with the finished steps turned into immutable shards of
``datasets/beta-glycine/shards/NNNN.h5`` every ``--shard-minutes`` (and at the end, also on
SIGTERM), committed at once with ``--commit``. On a fresh machine it first copies the shards'
records into the working store, so the optimisation replays them (no calculation) and goes on
from the last committed step::

    python examples/beta_glycine/optimize_job.py --commit [key=value ...]

``key=value`` arguments override ``config.yaml`` as for ``run_study.py``; the defaults here
are the long job's: optimisation enabled, one single-process CP2K (the other core labels the
molecular campaign), ``fmax`` 0.02 eV/Å.
"""

from __future__ import annotations

import argparse
import socket
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import run_study  # noqa: E402

from emlpack.commits import git_commit  # noqa: E402
from emlpack.data.shards import SHARD_DIR, finished_keys, shard_paths  # noqa: E402
from emlpack.data.store import DatasetStore  # noqa: E402
from emlpack.interrupts import terminate_as_interrupt  # noqa: E402
from emlpack.qm.campaign import export_shard  # noqa: E402

DATASET = Path("datasets/beta-glycine")
DEFAULTS = ["optimization.enabled=true", "optimization.cp2k.n_processes=1",
            "optimization.cp2k.mpirun=null", "optimization.fmax=0.02",
            "optimization.max_steps=200"]


def restore(folder: Path, store_path: Path) -> int:
    """Append the shards' records that ``store_path`` lacks (a fresh machine); returns how
    many."""
    store_path.parent.mkdir(parents=True, exist_ok=True)
    n = 0
    with DatasetStore(store_path, "a") as work:
        have = set(work.keys())
        for path in shard_paths(folder):
            with DatasetStore(path, "r") as shard:
                new = [s for s in shard if s.info.get("key") not in have]
            if new:
                work.append(new)
                n += len(new)
    return n


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("overrides", nargs="*", help="key=value overrides of config.yaml")
    p.add_argument("--config", default=str(HERE / "config.yaml"))
    p.add_argument("--shard-minutes", type=float, default=25.0)
    p.add_argument("--commit", action="store_true", help="commit every new shard")
    args = p.parse_args(argv)
    cfg = run_study.load_config(args.config, [*DEFAULTS, *args.overrides])
    study = run_study.Study(cfg, log=lambda m: print(time.strftime("%H:%M:%S"), m, flush=True))
    n = restore(DATASET, study.store_path)
    study.log(f"optimize_job: {n} steps restored from {DATASET / SHARD_DIR}"
              f" ({len(finished_keys(DATASET))} keys in shards)")
    state = {"last": time.monotonic(), "since": time.time()}

    def flush(store: DatasetStore) -> None:
        now = time.time()
        shard = export_shard(DATASET, store, {"host": socket.gethostname(), "workers": 1,
                                              "threads": 1, "started": state["since"],
                                              "ended": now, "wall_s": now - state["since"],
                                              "level": study.level()})
        state["last"], state["since"] = time.monotonic(), now
        if shard is not None:
            study.log(f"optimize_job: wrote {shard}")
            if args.commit:
                git_commit([DATASET / SHARD_DIR], f"beta-glycine DFT optimisation: shard"
                                                  f" {shard.stem}")

    def on_stored(store: DatasetStore) -> None:
        if time.monotonic() - state["last"] > args.shard_minutes * 60:
            flush(store)

    study.on_stored = on_stored
    with terminate_as_interrupt():
        try:
            run_study.stage_optimize(study)
        finally:
            with DatasetStore(study.store_path, "a") as store:
                flush(store)


if __name__ == "__main__":
    main()
