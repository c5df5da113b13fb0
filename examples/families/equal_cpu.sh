#!/usr/bin/env bash
# Issue 48's learning-curve point: SchNet and PaiNN trained for the same CPU time (one core,
# one thread each, side by side) on the mini-eQM7 training split, then evaluated on the
# validation molecules (core-force MAE, pair-force MAE, pair-field slope).
#
#   bash examples/families/equal_cpu.sh [MINUTES]     # default 60; resumable (re-run it)
#
# The two trainings run at once, one per core, each until it has used MINUTES of CPU time
# (training.max_cpu_minutes, counted over resumes); pause the long jobs meanwhile
# (`bash examples/long_jobs.sh pause`, then `resume`) so each training has its core. Outputs under
# runs/families/ (not committed); the summary is examples/families/equal_cpu.json.
# Learning-rate schedule: the study's train.yaml (lr 1e-3 halved every decay_epochs), with
# decay_epochs chosen per family so that the rate halves about three times in the budget
# (SchNet ~13.8 s an epoch compiled, PaiNN ~4.9x its step: docs/performance.md).
set -euo pipefail
cd "$(dirname "$0")/../.."
MINUTES=${1:-60}
PY=${PYTHON:-.venv/bin/python}
OUT=runs/families
mkdir -p "$OUT"
common=(data.path=datasets/mini-eqm7 augmentation.enabled=true training.seed=0
        training.max_time_minutes=null training.max_cpu_minutes="$MINUTES"
        training.max_epochs=100000 training.patience=null
        output.progress=false training.threads=1)
OMP_NUM_THREADS=1 .venv/bin/emlp train examples/eqm7/train.yaml "${common[@]}" \
    output.dir="$OUT/schnet" training.decay_epochs=$((MINUTES * 87 / 60)) \
    >"$OUT/schnet.log" 2>&1 &
s=$!
OMP_NUM_THREADS=1 .venv/bin/emlp train examples/eqm7/train.yaml "${common[@]}" \
    model.family=painn output.dir="$OUT/painn" training.decay_epochs=$((MINUTES * 18 / 60)) \
    >"$OUT/painn.log" 2>&1 &
p=$!
wait $s $p
for f in schnet painn; do
    OMP_NUM_THREADS=1 .venv/bin/emlp evaluate "$OUT/$f/best.pt" datasets/mini-eqm7 \
        --subset val -o "$OUT/$f/evaluation" --threads 1 --quiet >"$OUT/$f-evaluate.log" 2>&1 &
done
wait
$PY - "$OUT" "$MINUTES" <<'PY'
import csv, json, sys
from pathlib import Path
out, minutes = Path(sys.argv[1]), float(sys.argv[2])
rows = {}
for f in ("schnet", "painn"):
    e = json.loads((out / f / "evaluation" / "evaluation.json").read_text())[0]
    log = list(csv.DictReader((out / f / "log.csv").open()))
    best = min(log, key=lambda r: float(r["val_loss"]))
    st, dy = e["static"], e["dynamic"]
    rows[f] = {"config": (out / f / "config.yaml").read_text().split("model:")[1].split(
                   "augmentation:")[0].strip(),
               "minutes": minutes, "epochs": len(log), "steps": int(log[-1]["step"]),
               "best_epoch": int(best["epoch"]),
               "val_core_force_mae_meV_per_A": 1e3 * st["forces"]["mae"],
               "val_pair_force_mae_meV_per_A": 1e3 * st["pair_forces"]["mae"],
               "val_energy_mae_meV_per_atom": 1e3 * st["energy"]["mae"],
               "pair_field_slope": st["pair_field_slope"],
               "dynamic_core_force_mae_meV_per_A": 1e3 * dy["forces"]["mae"],
               "dynamic_error_rate": dy["error_rate"], "n_structures": e["n_structures"]}
Path("examples/families/equal_cpu.json").write_text(json.dumps(rows, indent=1) + "\n")
for f, r in rows.items():
    print(f, {k: (round(v, 3) if isinstance(v, float) else v) for k, v in r.items()
              if k != "config"})
PY
