"""Learning curve of the study's models: test errors against the number of training
configurations and against the number of optimizer steps.

The question it answers: do our models differ from the paper's because of the data volume or
because of the training budget?

    python examples/eqm7/learning_curve.py [--data datasets/mini-eqm7] [--shards 28 46 66]
        [--steps 7400 22200] [--workdir runs/eqm7-lc] [--out examples/eqm7/learning_curve]

**The grid.** For every prefix of the data set's shards (``--shards``, counts in labeling
order, so that a prefix holds whole molecules) and every step budget (``--steps``), one
augmented model per seed (``--seeds``, default 0) trains with the study's ``train.yaml``.

**The schedule.** Its epochs and learning-rate decay are scaled so that every run takes about
the same optimizer steps on the same schedule: ``max_epochs = round(steps / steps_per_epoch)``,
and the rate halves every ``--decay-steps`` steps. With ``train.yaml``'s batch of 16 and 444
training configurations this is the shipped ensemble's schedule: 100 epochs of 28 steps, and
~7400 steps in its 40 minutes.

**Evaluation.** Every model is evaluated by the study's ``evaluate`` stage:
- on the test split of the largest prefix (one test set for all);
- on the authors' six molecules.

The printed table gives static and dynamic errors, the pair-field slope and the steps actually
taken (from ``log.csv``).

**Resuming.** Every step resumes: the prefixes are folders of symbolic links under
``WORKDIR/data``, and the study's stages skip finished models and evaluations. With
``--snapshots DIR`` (a folder in the repository) the trainings commit their state there every
30 minutes, and the same command on a fresh clone goes on from it.
"""

from __future__ import annotations

import argparse
import csv
import datetime as dt
import json
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import run_study  # noqa: E402

#: what a prefix folder links to besides its shards
LINKED = ("molecules.csv", "campaign.yaml", "references", "prepared")


def prefix_folder(data: Path, n_shards: int, root: Path) -> Path:
    """``root/shards-NN``: the first ``n_shards`` shards of ``data`` as a data-set folder."""
    from emlpack.data.shards import shard_paths

    shards = shard_paths(data)
    if len(shards) < n_shards:
        raise SystemExit(f"{data}: {len(shards)} shards, fewer than the {n_shards} asked for")
    out = root / f"shards-{n_shards:02d}"
    (out / "shards").mkdir(parents=True, exist_ok=True)
    for name in LINKED:
        link = out / name
        if (data / name).exists() and not link.is_symlink():
            link.symlink_to((data / name).resolve())
    for path in shards[:n_shards]:
        link = out / "shards" / path.name
        if not link.is_symlink():
            link.symlink_to(path.resolve())
    return out


def _steps_taken(run: Path) -> tuple[int, int, int]:
    """(steps, epochs, best epoch) from a model's ``log.csv``."""
    rows = list(csv.DictReader((run / "log.csv").open()))
    best = min(rows, key=lambda r: float(r["val_loss"]))
    return int(rows[-1]["step"]), int(rows[-1]["epoch"]), int(best["epoch"])


def point(args, data: Path, n_shards: int, steps: int, test_data: Path) -> list[dict]:
    """Train (if needed) and evaluate one model per seed; their rows of the table."""
    from emlpack.data.shards import read_shards

    prefix = prefix_folder(data, n_shards, args.workdir / "data")
    shards = read_shards(prefix)
    split = shards.split_indices()
    train_molecules = {shards.structures[i].info["molecule_id"] for i in split["train"]}
    workdir = args.workdir / f"shards-{n_shards:02d}-steps-{steps}"
    seeds = ",".join(str(k) for k in args.seeds)
    common = [f"workdir={workdir}", "groups=[aug]", f"seeds=[{seeds}]", *args.set]
    if args.snapshots is not None:
        common.append(f"training.snapshots={args.snapshots / workdir.name}")
    common += [f"training.steps={steps}", f"training.decay_steps={args.decay_steps}"]

    def log(message: str) -> None:
        print(f"[{dt.datetime.now(dt.timezone.utc):%H:%M:%S}] {message}", flush=True)

    run_study.run(["train"], run_study.load_config(args.config, [f"data={prefix}", *common]),
                  log=log)
    run_study.run(["evaluate"], run_study.load_config(args.config,
                                                      [f"data={test_data}", *common]), log=log)
    return [_row(workdir, seed, n_shards, steps, train_molecules, len(split["train"]))
            for seed in args.seeds]


def _row(workdir: Path, seed: int, n_shards: int, steps: int, train_molecules: set,
         n_train: int) -> dict:
    taken, epochs, best_epoch = _steps_taken(workdir / "models" / "aug" / f"seed{seed}")
    row = {"shards": n_shards, "seed": seed, "train_molecules": len(train_molecules),
           "train_configurations": int(n_train), "steps_asked": steps,
           "steps": taken, "epochs": epochs, "best_epoch": best_epoch, "sets": {}}
    for set_dir in sorted((workdir / "eval").glob("*")):
        ev = json.loads((set_dir / f"aug-s{seed}.json").read_text())
        st, dy = ev["static"], ev.get("dynamic") or {}
        row["sets"][set_dir.name] = {
            "n_structures": ev["n_structures"],
            "energy_meV_per_atom": 1000 * st["energy"]["mae"],
            "forces_meV_per_A": 1000 * st["forces"]["mae"],
            "pair_forces_meV_per_A": 1000 * st["pair_forces"]["mae"],
            "pair_field_slope": st.get("pair_field_slope"),
            "dynamic_forces_meV_per_A": 1000 * dy["forces"]["mae"] if dy else None,
            "dipole_D": dy["dipole"]["mae"] if dy else None,
            "error_rate": dy.get("error_rate"),
        }
    return row


def markdown(rows: list[dict]) -> str:
    sets = sorted({s for r in rows for s in r["sets"]}, key=lambda s: s != "test")
    head = ["shards", "seed", "train molecules", "train configurations", "steps (best epoch)"]
    for s in sets:
        head += [f"{s}: core forces MAE [meV/Å]", f"{s}: pair forces MAE [meV/Å]",
                 f"{s}: energy MAE [meV/atom]", f"{s}: slope"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        cells = [str(r["shards"]), str(r.get("seed", 0)), str(r["train_molecules"]),
                 str(r["train_configurations"]),
                 f"{r['steps']} ({r['best_epoch']} of {r['epochs']})"]
        for s in sets:
            v = r["sets"].get(s)
            cells += (["–"] * 4 if v is None else
                      [f"{v['forces_meV_per_A']:.1f}", f"{v['pair_forces_meV_per_A']:.1f}",
                       f"{v['energy_meV_per_atom']:.1f}",
                       "–" if v["pair_field_slope"] is None else f"{v['pair_field_slope']:.2f}"])
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--data", type=Path, default=Path("datasets/mini-eqm7"))
    p.add_argument("--shards", type=int, nargs="+", default=[28, 46, 66])
    p.add_argument("--steps", type=int, nargs="+", default=[7400])
    p.add_argument("--decay-steps", type=float, default=2800.0,
                   help="optimizer steps per halving of the learning rate")
    p.add_argument("--workdir", type=Path, default=Path("runs/eqm7-lc"))
    p.add_argument("--snapshots", type=Path, default=None,
                   help="commit every model's training state to SNAPSHOTS/shards-NN-steps-S"
                        " (a folder in the repository) so that a run goes on across sessions")
    p.add_argument("--seeds", type=int, nargs="+", default=[0],
                   help="one model per seed at every point (rows per seed)")
    p.add_argument("--config", type=Path, default=HERE / "config.yaml", help="the study's")
    p.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE",
                   help="more overrides of the study's config (e.g. train.model.n_features=32)")
    p.add_argument("--out", type=Path, default=None,
                   help="write OUT.md and OUT.json (default: print only)")
    args = p.parse_args(argv)
    test_data = prefix_folder(args.data, max(args.shards), args.workdir / "data")
    rows = [row for s in sorted(args.steps) for n in sorted(args.shards)
            for row in point(args, args.data, n, s, test_data)]
    text = markdown(rows)
    print(text)
    if args.out is not None:
        for suffix, content in ((".md", text), (".json", json.dumps({"rows": rows}, indent=1))):
            path = args.out.with_suffix(suffix)
            tmp = path.with_suffix(suffix + ".tmp")
            tmp.write_text(content)
            tmp.replace(path)


if __name__ == "__main__":
    main()
