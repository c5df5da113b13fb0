#!/usr/bin/env bash
# The study's long jobs (issues 12 and 15). Start them at the beginning of every session, from
# the project root. Each job goes on exactly where its committed work stopped.
#
#   bash examples/eqm7/long_jobs.sh           start the jobs of the current phase that are not running
#   bash examples/eqm7/long_jobs.sh status    what runs, the campaign's target, the final models' steps
#   bash examples/eqm7/long_jobs.sh stop      stop them; each saves and commits its finished work
#
# Phase 1 lasts until the campaign reaches the target of datasets/mini-eqm7/campaign.yaml. It
# runs three jobs:
#   - the campaign (2 labeling processes; shards committed every 20 minutes);
#   - the DFT references of the test molecules (references.sh; finished files committed);
#   - at nice 10, the non-augmented model of the learning curve's 10x point (shards 0000-0078).
# Phase 2 starts once the target is reached. It runs the final study's 8 models (run_study.py
# train, config.yaml's schedule) in two training processes, seeds 0, 2 and seeds 1, 3, with the
# augmented models first, beside the references at nice 10. Snapshots are committed every 30
# minutes to examples/eqm7/snapshots/final.
# Phase 2b starts when all 8 models have finished: run_study.py evaluate polarizability md
# table (results in runs/eqm7/results, not committed: a session reviews them) in one process,
# beside the references.
# Phase 3 starts when that has ended (also when it failed: the watcher logs it, `status` shows
# the exit status, and the next start reruns phase 2b from its saved outputs). The references
# still to compute are split between two processes, one per core, balanced by their force calls
# still to do and the size of each call (reference_split.py); the 10x non-augmented model
# (stopped in phase 2) goes on at nice 10.
# Phase 4 starts when every harmonic reference is finished: run_study.py ir table (Figure 4,
# the frequency MAE; results in runs/eqm7/results). A session then reviews the results and runs
# `table export status=final` itself.
# The outputs of phases 2b and 4 (per-model JSON, each MD run's analysis.json) are committed
# every 20 minutes to examples/eqm7/snapshots/final-outputs and restored from there before
# those phases start (study_outputs.py), so that on a fresh machine they go on where they were.
# A watcher moves from one phase to the next as the jobs end, without waiting for a session.
#
# Each job runs on its own copy of src/ (/tmp/emlp-JOB), so editing the code does not change a
# running job. Logs go to runs/*.log; PIDs to runs/long_jobs/JOB.pid.
set -euo pipefail
# EMLP_ROOT: the project root, for the watcher (it runs from a copy of this script, so that
# editing the script does not change a running watcher)
cd "${EMLP_ROOT:-$(dirname "$0")/../..}"
PY=.venv/bin/python
if [ ! -x "$PY" ]; then
  echo "long_jobs.sh: no $PY here: run 'make install' first (a fresh machine)" >&2
  exit 2
fi
DATA=datasets/mini-eqm7
PIDS=runs/long_jobs
FINAL_SNAPSHOTS=examples/eqm7/snapshots/final
OUTPUTS=examples/eqm7/snapshots/final-outputs  # the study stages' small outputs (study_outputs.py)
WORK=runs/eqm7  # config.yaml's workdir: the final models and their evaluations
LC=runs/eqm7-lc
mkdir -p "$PIDS"

running() {  # running JOB: its recorded process is alive
  local f="$PIDS/$1.pid"
  [ -f "$f" ] && kill -0 "$(cat "$f")" 2>/dev/null
}

code_copy() {  # code_copy JOB: a private copy of src/ for the job
  rm -rf "/tmp/emlp-$1" && mkdir -p "/tmp/emlp-$1" && cp -r src "/tmp/emlp-$1/"
}

target_reached() {
  PYTHONPATH=src "$PY" -c "
import sys
from emlpack.qm.campaign import campaign_target
sys.exit(0 if campaign_target('$DATA')[1]['reached'] else 1)"
}

start_campaign() {
  running campaign && return 0
  code_copy campaign
  PYTHONPATH=/tmp/emlp-campaign/src OMP_WAIT_POLICY=PASSIVE nohup .venv/bin/emlp campaign run \
    "$DATA" --workers 2 --threads 1 --shard-minutes 20 --commit --quiet >> runs/campaign.log 2>&1 &
  echo $! > "$PIDS/campaign.pid"
  echo "campaign: PID $!, log runs/campaign.log"
}

start_references() {  # start_references JOB [NAME ...]: the DFT stage (all test molecules, or NAMEs)
  local job=$1
  shift
  running "$job" && return 0
  running references || running references-a || running references-b || code_copy refs
  PYTHONPATH=/tmp/emlp-refs/src OMP_NUM_THREADS=1 bash examples/eqm7/references.sh "$@" \
    > "runs/$job.out" 2>&1
  sed -n 's/^references: watcher PID \([0-9]*\)$/\1/p' "runs/$job.out" > "$PIDS/$job.pid"
  echo "$job: watcher PID $(cat "$PIDS/$job.pid"), log runs/eqm7-references.log"
}

remaining_references() {  # the test molecules whose harmonic reference is still to compute
  PYTHONPATH=src "$PY" -c "
import csv, json
from pathlib import Path
refs = Path('$DATA/references/pbe0_aug-cc-pvtz')
def done(name):
    static = refs / f'{name}.json'
    if (refs / f'{name}.ir.json').exists():
        return True
    return static.exists() and 'frequencies_cm-1' in json.loads(static.read_text())
rows = csv.DictReader(open('$DATA/molecules.csv'))
print(' '.join(r['name'] for r in rows if r['split'] == 'test' and not done(r['name'])))"
}

split_references() {  # phase 3: the remaining references in two processes, balanced by cost
  # (reference_split.py: calls left x basis functions^2.5, the most even split)
  local names a b
  names=$(remaining_references)
  [ -n "$names" ] || return 0
  # shellcheck disable=SC2086  # names: one word each
  { read -r a; read -r b; } < <("$PY" examples/eqm7/reference_split.py \
    "$DATA/references/pbe0_aug-cc-pvtz" $names)
  stop_job references
  sleep 30  # its watcher stops the stage and commits what is finished
  # shellcheck disable=SC2086
  start_references references-a $a
  [ -z "$b" ] || start_references references-b $b
}

start_noaug_10x() {  # the learning curve's 10x non-augmented model (augmented vs not at equal data)
  running noaug-10x && return 0
  local d=$LC/data/shards-79
  if [ ! -d "$d/shards" ]; then  # the 10x point's data: links to the first 79 shards
    mkdir -p "$d/shards"
    for f in campaign.yaml molecules.csv prepared references; do ln -sfn "$PWD/$DATA/$f" "$d/$f"; done
    for i in $(seq -f %04g 0 78); do ln -sfn "$PWD/$DATA/shards/$i.h5" "$d/shards/$i.h5"; done
  fi
  code_copy noaug
  PYTHONPATH=/tmp/emlp-noaug/src OMP_NUM_THREADS=1 nohup nice -n 10 "$PY" examples/eqm7/run_study.py \
    train data=$d workdir=$LC/shards-79-steps-74000 "groups=[noaug]" "seeds=[0]" \
    training.steps=74000 training.decay_steps=9400 \
    training.snapshots=examples/eqm7/snapshots/shards-79-steps-74000 >> runs/noaug-s0.log 2>&1 &
  echo $! > "$PIDS/noaug-10x.pid"
  echo "noaug 10x: PID $! (nice 10), log runs/noaug-s0.log"
}

start_final() {  # the final study's models, two processes
  code_copy final
  local k seeds
  for k in 0 1; do
    running "final-$k" && continue
    seeds=$([ "$k" = 0 ] && echo "0,2" || echo "1,3")
    PYTHONPATH=/tmp/emlp-final/src OMP_NUM_THREADS=1 nohup "$PY" examples/eqm7/run_study.py train \
      "groups=[aug,noaug]" "seeds=[$seeds]" training.snapshots=$FINAL_SNAPSHOTS \
      >> "runs/final-$k.log" 2>&1 &
    echo $! > "$PIDS/final-$k.pid"
    echo "final models, seeds $seeds: PID $!, log runs/final-$k.log"
  done
  # the trainings first: the references take what they leave until phase 2b (the same CPU in
  # all, so the final models, and all of the study but the IR, come hours earlier)
  renice_job references 10
}

renice_job() {  # renice_job JOB N: every thread of the job's processes (its children too)
  local queue p t
  running "$1" || return 0
  queue=("$(cat "$PIDS/$1.pid")")
  while [ ${#queue[@]} -gt 0 ]; do
    p=${queue[0]}
    queue=("${queue[@]:1}")
    for t in /proc/"$p"/task/*; do  # Linux: a nice value belongs to a thread
      renice -n "$2" -p "${t##*/}" > /dev/null 2>&1 || true
    done
    # shellcheck disable=SC2207  # PIDs: one word each
    queue+=($(pgrep -P "$p" || true))
  done
}

final_trained() {  # every final model has finished (run_study.py train writes done.json)
  local g k
  for g in aug noaug; do
    for k in 0 1 2 3; do
      [ -f "$WORK/models/$g/seed$k/done.json" ] || return 1
    done
  done
}

start_study() {  # start_study JOB STAGE ...: run_study.py stages on the final models (results in
  # $WORK/results); their outputs restored from $OUTPUTS first and committed there every 20
  # minutes and at the end (study_outputs.py). The PID is the watcher's: killing it stops the
  # stages and saves what they finished.
  local job=$1
  shift
  running "$job" && return 0
  rm -f "$PIDS/$job.rc"
  code_copy "$job"
  PYTHONPATH=/tmp/emlp-$job/src "$PY" examples/eqm7/study_outputs.py restore "$OUTPUTS" "$WORK"
  (
    PYTHONPATH=/tmp/emlp-$job/src OMP_NUM_THREADS=1 "$PY" examples/eqm7/run_study.py "$@" \
      results_dir=$WORK/results &
    stage=$!
    save() {
      PYTHONPATH=/tmp/emlp-$job/src "$PY" examples/eqm7/study_outputs.py save "$WORK" "$OUTPUTS" \
        --commit || echo "saving the outputs failed (retrying later)"
    }
    trap 'kill "$stage" 2>/dev/null; wait "$stage" 2>/dev/null || true; save; exit 0' TERM
    while kill -0 "$stage" 2>/dev/null; do
      for _ in $(seq 120); do
        kill -0 "$stage" 2>/dev/null || break
        sleep 10
      done
      save
    done
    rc=0
    wait "$stage" || rc=$?
    echo "$rc" > "$PIDS/$job.rc"  # the stages' exit status, for the watcher and status
    echo "[$(date +%T)] $job: the stages ended with exit status $rc"
  ) >> "runs/$job.log" 2>&1 &
  echo $! > "$PIDS/$job.pid"
  echo "$job ($*): PID $!, log runs/$job.log, results in $WORK/results"
}

stop_job() {
  if running "$1"; then
    kill "$(cat "$PIDS/$1.pid")" && echo "$1: stopping (it saves and commits its finished work)"
  fi
}

watch() {  # phase 1 -> 2 -> 2b -> 3 -> 4 as the jobs end
  while running campaign; do sleep 60; done
  target_reached || return 0  # the campaign stopped short of its target: a session looks
  if running noaug-10x; then
    stop_job noaug-10x
    sleep 60  # let it snapshot and commit
  fi
  start_final
  while running final-0 || running final-1; do sleep 60; done
  renice_job references 0
  final_trained || return 0  # a training stopped short: a session looks
  start_study study-eval evaluate polarizability md table  # phase 2b: no Hessian needed
  while running study-eval; do sleep 60; done
  if [ "$(cat "$PIDS/study-eval.rc" 2>/dev/null)" != 0 ]; then  # phase 3 goes on all the same:
    # the next start reruns phase 2b from its saved outputs; status shows the failure
    echo "[$(date +%T)] phase 2b failed (exit status $(cat "$PIDS/study-eval.rc" 2>/dev/null \
      || echo unknown)): see runs/study-eval.log; phase 3 starts, the next start reruns 2b"
  fi
  split_references
  start_noaug_10x  # the rest of its steps at nice 10, from what the references leave
  while running references-a || running references-b; do sleep 60; done
  [ -z "$(remaining_references)" ] || return 0  # a reference failed or stopped: a session looks
  start_study study-ir ir table  # phase 4
}

start_watcher() {
  running watcher && return 0
  cp "$0" /tmp/emlp-long_jobs.sh
  EMLP_ROOT=$PWD nohup bash /tmp/emlp-long_jobs.sh _watch >> runs/long_jobs.log 2>&1 &
  echo $! > "$PIDS/watcher.pid"
  echo "watcher: PID $! (moves to the next phase as the jobs end)"
}

main() {
case "${1:-start}" in
  start)  # the watcher starts phase 2 (and 3) at once when their time has come
    running references-a || running references-b || start_references references
    if ! target_reached; then
      start_campaign
      start_noaug_10x
    fi
    start_watcher
    ;;
  _watch)
    watch
    ;;
  stop)
    for job in watcher campaign references references-a references-b noaug-10x final-0 final-1 study-eval study-ir; do
      stop_job "$job"
    done
    ;;
  status)
    for job in campaign references references-a references-b noaug-10x final-0 final-1 study-eval study-ir watcher; do
      if running "$job"; then
        echo "$job: running (PID $(cat "$PIDS/$job.pid"))"
      elif [ -f "$PIDS/$job.rc" ]; then  # the study stages' jobs: how they ended
        echo "$job: ended with exit status $(cat "$PIDS/$job.rc")$([ "$(cat "$PIDS/$job.rc")" = 0 ] \
          || echo " (FAILED: see runs/$job.log)")"
      else
        echo "$job: -"
      fi
    done
    PYTHONPATH=src "$PY" -c "
from emlpack.qm.campaign import campaign_target
t = campaign_target('$DATA')[1]
print(f\"target: {t['configurations']} configurations of {t['molecules']} molecules;\"
      f\" labeled {t['labeled']} configurations of {t['labeled_molecules']} molecules;\"
      f\" {'reached' if t['reached'] else 'not reached'}\")"
    started=$(for job in references references-a references-b; do
      if running "$job"; then stat -c %Y "$PIDS/$job.pid"; fi; done | sort -n | head -1)
    PYTHONPATH=src "$PY" -c "
import json, sys, time
from pathlib import Path
refs = Path('$DATA/references/pbe0_aug-cc-pvtz')
started = float('${started:-0}')  # when the running reference processes started (0: none)
left = sys.argv[1:]
calls, todo, recent = [], 0, 0
for name in left:
    n = len(json.loads((refs / f'{name}.json').read_text())['numbers']) \\
        if (refs / f'{name}.json').exists() else None
    files = list((refs / name / 'vib-internal').glob('*[+-].npz'))  # config: internal
    calls.append(f'{name} {len(files)}/{2 * (3 * n - 6)}' if n else f'{name} (static)')
    todo += 2 * (3 * n - 6) - len(files) if n else 0
if started:  # every displacement since then, also those of references finished since
    recent = sum(f.stat().st_mtime > started for f in refs.glob('*/vib-internal/*[+-].npz'))
print(f'references: {len(left)} harmonic references left' + (': ' + ', '.join(calls) if calls else ''))
hours = (time.time() - started) / 3600 if started else 0
if todo and recent and hours > 0.25:  # the pace of the running processes, all together
    print(f'references: {todo} force calls left; {recent} done in the {hours:.1f} h since the'
          f' processes started, ~{todo * hours / recent:.1f} h left at that pace')
    for name in left:  # each molecule under way at its own pace (the cost per call differs)
        files = list((refs / name / 'vib-internal').glob('*[+-].npz'))
        new = [f.stat().st_mtime for f in files if f.stat().st_mtime > started]
        n = len(json.loads((refs / f'{name}.json').read_text())['numbers'])
        if len(new) >= 2:
            pace = (len(new) - 1) * 3600 / (max(new) - min(new))
            print(f'  {name}: {pace:.0f} force calls per hour, ~'
                  f'{(2 * (3 * n - 6) - len(files)) / pace:.1f} h to go')
" $(remaining_references)
    for d in "$FINAL_SNAPSHOTS"/*/seed*; do
      if [ -d "$d" ]; then echo "$d: $(ls "$d" | tail -1)"; fi
    done
    # the final models here: steps (of config.yaml's), the pace of the last 10 epochs, hours left
    PYTHONPATH=src "$PY" - "$WORK/models" examples/eqm7/config.yaml <<'PYEOF'
import csv, sys
from pathlib import Path

import yaml

steps = yaml.safe_load(Path(sys.argv[2]).read_text())["training"]["steps"]
for log in sorted(Path(sys.argv[1]).glob("*/seed*/log.csv")):
    rows = list(csv.DictReader(log.open()))
    if not rows:
        continue
    run, step = log.parent, int(rows[-1]["step"])
    if (run / "done.json").exists():
        print(f"{run}: done, {step} steps")
        continue
    before = int(rows[-11]["step"]) if len(rows) > 10 else 0  # the step before the last 10
    per_step = sum(float(r["epoch_time"]) for r in rows[-10:]) / max(step - before, 1)
    print(f"{run}: step {step} of {steps}, {per_step:.3f} s/step lately,"
          f" ~{(steps - step) * per_step / 3600:.1f} h left at that pace")
PYEOF
    ;;
  *)
    echo "usage: $0 [start|status|stop]" >&2
    exit 2
    ;;
esac
}

main "$@"; exit $?  # one line: bash has read the whole script before it runs
