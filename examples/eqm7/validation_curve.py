"""The training schedule judged by validation error: how much each model's best validation
error still fell in the last stretch of its optimizer steps.

    python examples/eqm7/validation_curve.py [SNAPSHOTS] [--steps 7400 22200 ...] [--json OUT]

SNAPSHOTS (default ``examples/eqm7/snapshots/final``) holds ``GROUP/seedK/step-N/log.csv``
(the study's committed training snapshots); the latest step folder of each model is read. For
each model and each step budget, the best validation epoch among those ended within that many
optimizer steps (the model ``training`` would keep had it stopped there, the learning-rate
schedule being the full run's): its core-force MAE on the held-out validation molecules
(meV/Å) and its validation loss. Printed as a markdown table with each group's mean ± std;
``--json`` writes the numbers. Milliseconds of CPU.
"""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import run_study  # noqa: E402

DEFAULT_STEPS = (7400, 22200, 37000, 55500, 74036)


def best_within(log_csv: Path, budgets) -> list[dict]:
    """For each step budget, the best validation epoch of ``log_csv`` (``emlp train``'s log)
    among the epochs ended within it: ``{"steps", "epoch", "val_forces_meV_per_A",
    "val_loss"}``; None for a budget no epoch ended within."""
    rows = list(csv.DictReader(log_csv.open()))
    out = []
    for budget in budgets:
        done = [r for r in rows if int(r["step"]) <= budget]
        if not done:
            out.append(None)
            continue
        best = min(done, key=lambda r: float(r["val_loss"]))
        out.append({"steps": int(best["step"]), "epoch": int(best["epoch"]),
                    "val_forces_meV_per_A": 1000.0 * float(best["val_forces_mae"]),
                    "val_loss": float(best["val_loss"])})
    return out


def latest_logs(snapshots: Path) -> dict[str, Path]:
    """``{"GROUP-sK": log.csv of the model's latest snapshot}`` under ``snapshots``."""
    logs = {}
    for seed_dir in sorted(snapshots.glob("*/seed*")):
        steps = sorted(seed_dir.glob("step-*/log.csv"))
        if steps:
            logs[f"{seed_dir.parent.name}-s{seed_dir.name[4:]}"] = steps[-1]
    return logs


def curve(snapshots: Path, budgets) -> dict:
    """Every model's :func:`best_within`, and each group's mean ± std per budget."""
    models = {name: best_within(log, budgets) for name, log in latest_logs(snapshots).items()}
    groups: dict[str, dict] = {}
    for name, points in models.items():
        groups.setdefault(name.rsplit("-s", 1)[0], {})[name] = points
    summary = {
        group: [{key: run_study.mean_std([m[k][key] for m in members.values() if m[k]])
                 for key in ("val_forces_meV_per_A", "val_loss")} for k in range(len(budgets))]
        for group, members in groups.items()}
    return {"steps": list(budgets), "models": models, "groups": summary}


def markdown(result: dict) -> str:
    def cell(ms: dict, fmt: str) -> str:
        return "" if ms["mean"] is None else f"{ms['mean']:{fmt}} ± {ms['std']:{fmt}}"

    steps = result["steps"]
    lines = ["| model | " + " | ".join(f"≤ {s} steps" for s in steps) + " |",
             "|---|" + "---|" * len(steps)]
    for name, points in result["models"].items():
        lines.append(f"| {name} | " + " | ".join(
            "" if p is None else f"{p['val_forces_meV_per_A']:.1f} ({p['val_loss']:.3f})"
            for p in points) + " |")
    for group, points in result["groups"].items():
        lines.append(f"| {group}: mean ± std | " + " | ".join(
            f"{cell(p['val_forces_meV_per_A'], '.1f')} ({cell(p['val_loss'], '.3f')})"
            for p in points) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("snapshots", nargs="?", type=Path, default=HERE / "snapshots" / "final")
    ap.add_argument("--steps", nargs="+", type=int, default=list(DEFAULT_STEPS))
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    result = curve(args.snapshots, args.steps)
    if not result["models"]:
        raise SystemExit(f"{args.snapshots}: no GROUP/seedK/step-N/log.csv found")
    print("Best validation core-force MAE [meV/Å] (validation loss) within the first N steps:")
    print(markdown(result))
    if args.json:
        from emlpack._files import write_json_atomic

        write_json_atomic(args.json, result)


if __name__ == "__main__":
    main()
