#!/usr/bin/env bash
# The study's models on a borrowed GPU machine, for as long as it is lent (issue 15).
#
#   bash examples/eqm7/gpu_models.sh train GROUP SEEDS SECONDS OUT
#       (on the GPU machine, from the project root) trains the models GROUP/seedK, K in the
#       comma-separated SEEDS, one process each, side by side on the GPU (training.device=auto:
#       the study's small models leave a GPU mostly idle, so processes share it well), with
#       config.yaml's schedule, each from its newest snapshot when there is one; after
#       SECONDS (or when one has ended) it stops them (SIGTERM: each keeps its last finished
#       epoch) and packs every run folder's last.pt, best.pt and log.csv into OUT/models.tar,
#       the training logs into OUT/train-K.log
#   bash examples/eqm7/gpu_models.sh import TAR
#       (here) turns the packed runs into the snapshots the study's CPU training resumes from
#       (examples/eqm7/snapshots/final/GROUP/seedK/step-N, committed): the CPU goes on where
#       the GPU stopped, with the same steps, schedule and data
set -euo pipefail
cd "$(dirname "$0")/../.."
SNAPSHOTS=examples/eqm7/snapshots/final

case "${1:-}" in
train)
  group=$2 seeds=$3 seconds=$4 out=$5
  work=/tmp/eqm7-gpu
  mkdir -p "$out" "$work"
  pids=()
  for k in ${seeds//,/ }; do
    # from the newest committed snapshot of the model, when there is one
    snap=$(ls -d "$SNAPSHOTS/$group/seed$k"/step-* 2>/dev/null | tail -1 || true)
    if [ -n "$snap" ] && [ ! -f "$work/models/$group/seed$k/last.pt" ]; then
      mkdir -p "$work/models/$group/seed$k" && cp "$snap"/* "$work/models/$group/seed$k/"
    fi
    PYTHONPATH="src:${PYTHONPATH:-}" PYTHONUNBUFFERED=1 "${PYTHON:-python3}" \
      examples/eqm7/run_study.py train \
      "groups=[$group]" "seeds=[$k]" "workdir=$work" > "$out/train-$k.log" 2>&1 &
    pids+=($!)
  done
  end=$((SECONDS + seconds))
  while [ $SECONDS -lt $end ] && kill -0 "${pids[@]}" 2>/dev/null; do sleep 5; done
  kill -TERM "${pids[@]}" 2>/dev/null || true
  wait || true
  (cd "$work/models" && tar cf "$out/models.tar" "$group"/seed*/{last.pt,best.pt,log.csv})
  ls -la "$out"
  ;;
import)
  tar=$(realpath "$2")
  tmp=$(mktemp -d)
  tar xf "$tar" -C "$tmp"
  for run in "$tmp"/*/seed*; do
    group=$(basename "$(dirname "$run")") seed=$(basename "$run")
    step=$(.venv/bin/python -c "
import sys
from emlpack.nn.checkpoint import read_checkpoint
print(read_checkpoint(sys.argv[1])['metadata']['training']['step'])" "$run/last.pt")
    dest=$SNAPSHOTS/$group/$seed
    older=$(ls -d "$dest"/step-* 2>/dev/null || true)
    if [ -n "$older" ] && [ "$(basename "$(echo "$older" | tail -1)")" \> "$(printf 'step-%09d' "$step")" ]; then
      echo "$dest has a newer snapshot than step $step: not replaced" >&2
      continue
    fi
    mkdir -p "$dest/.tmp" && cp "$run"/{last.pt,best.pt,log.csv} "$dest/.tmp/"
    mv "$dest/.tmp" "$dest/$(printf 'step-%09d' "$step")"
    for old in $older; do [ "$old" != "$dest/$(printf 'step-%09d' "$step")" ] && rm -rf "$old"; done
    echo "$dest: step $step"
  done
  rm -rf "$tmp"
  git add "$SNAPSHOTS" && git commit -q -m "training snapshots from the GPU machine: $(basename "$tar")" -- "$SNAPSHOTS"
  ;;
*)
  sed -n 2,15p "$0"
  exit 2
  ;;
esac
