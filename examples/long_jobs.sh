#!/usr/bin/env bash
# The long jobs of the second wave (issues 50, 51, 52). Start them at the beginning of every
# session, from the project root; each goes on exactly where its committed work stopped.
#
#   bash examples/long_jobs.sh           start the jobs that are due and not running, and a
#                                        watcher that moves on as jobs end
#   bash examples/long_jobs.sh status    what runs, counts, rates
#   bash examples/long_jobs.sh stop      stop them; each saves and commits its finished work
#   bash examples/long_jobs.sh pause     SIGSTOP the running jobs and their children (a timing
#                                        or an equal-CPU comparison takes the cores), and
#   bash examples/long_jobs.sh resume    SIGCONT them (renice does not hold them back: the
#                                        kernel's autogroups give every session's group an
#                                        equal share whatever its tasks' nice values)
#
# The jobs, in the brief's order (two cores):
#   level-choice  the cheap level's measurements (examples/qm7_cheap/level_choice.py; one
#                 small JSON per measurement, committed every 25 min); ends by itself
#   bg-optimize   the beta-glycine DFT optimisation (CP2K, one process; every step a record,
#                 turned into shards of datasets/beta-glycine every 25 min and committed)
#   bg-settings   the CP2K settings check at the DFT optimum (examples/beta_glycine/
#                 settings_check.py: 400/500/600 Ry, relative cutoff 50/60, one sample; ~1 CPU h;
#                 each candidate committed to examples/beta_glycine/settings_check/), after
#                 bg-optimize on its core
#   bg-reference  the 19 finite-difference CP2K calculations at the DFT optimum (campaign_job.py
#                 label --reference-only: ~19 x 6 CPU min, shards committed every 25 min), then
#                 the DFT tensors (run_study.py reference) -> examples/beta_glycine/
#                 dft_reference.json, committed; after bg-settings on its core
#   val-refs      the DFT polarizabilities of mini-eQM7's validation molecules
#                 (examples/eqm7/validation_references.py; files committed every 25 min), on
#                 the core beside bg-optimize
#   raman-dft     the DFT Raman reference of aziridine (examples/raman/aziridine_dft.py, ~216
#                 SCFs, ~15-40 min), after val-refs on the same core; committed when it ends
#   bakeoff       issue 51's bake-off: each candidate recipe of examples/eqm7/bakeoff.yaml
#                 trained for its CPU budget (2 CPU h) and judged on the validation molecules
#                 (examples/eqm7/bakeoff.py run, then table; runs/bakeoff/NAME, resumable: a
#                 training goes on from its last.pt with the budget it has left), after
#                 raman-dft on the same core; bakeoff.md/json committed as each candidate ends;
#                 its schnet-pretrained (issue 50's pilot, pilot.md in examples/qm7_cheap)
#                 waits for 5000 cheap-level configurations without holding the chain up
#                 (bakeoff.py done counts it as pending only once they are there)
#   alpha-labels  paper-level polarizability labels of 300 mini-eQM7 training configurations
#                 (examples/eqm7/polarizability_labels.py, ~17 CPU h; issue 51's stiffness
#                 lever; one file a configuration, committed every 25 min), after bakeoff
#   pretrain      the QM7-wide cheap-level campaign (emlp campaign run on the folder named in
#                 examples/qm7_cheap/DATASET once the level is chosen; shards committed every
#                 25 min) on the cores the others leave: one labeling process, two when no
#                 other job runs
# Each job runs on its own copy of src/ and examples/ (/tmp/emlp-JOB), so editing the code does
# not change a running job. Logs go to runs/*.log; PIDs to runs/long_jobs/JOB.pid.
set -euo pipefail
cd "${EMLP_ROOT:-$(dirname "$0")/..}"
PY=.venv/bin/python
if [ ! -x "$PY" ]; then
  echo "long_jobs.sh: no $PY here: run 'make install' (and 'make install-cp2k') first" >&2
  exit 2
fi
PIDS=runs/long_jobs
mkdir -p "$PIDS"
PRETRAIN_FILE=examples/qm7_cheap/DATASET  # one line: the pretraining set's folder

running() {  # running JOB: its recorded process is alive
  local f="$PIDS/$1.pid"
  [ -f "$f" ] && kill -0 "$(cat "$f")" 2>/dev/null
}

code_copy() {  # code_copy JOB: a private copy of src/ and examples/ for the job
  rm -rf "/tmp/emlp-$1" && mkdir -p "/tmp/emlp-$1" && cp -r src examples "/tmp/emlp-$1/"
}

stop_job() {
  if running "$1"; then
    # raman-dft and bakeoff are a bash -c around their script: stop the script itself (the
    # recipe keeps its SCF files, a training its last finished epoch)
    case "$1" in raman-dft|bakeoff|bg-reference) pkill -TERM -P "$(cat "$PIDS/$1.pid")" 2>/dev/null ;; esac
    kill "$(cat "$PIDS/$1.pid")" && echo "$1: stopping (it saves and commits its finished work)"
  fi
}

level_choice_done() {
  "$PY" -c "
import sys; sys.path.insert(0, 'examples/qm7_cheap')
import level_choice as L
sys.exit(0 if L.complete() else 1)" 2>/dev/null
}

bg_optimize_done() {  # the optimisation converged (optimization.json says so)
  [ -f runs/bg_sc212/optimization.json ] && "$PY" -c "
import json, sys
sys.exit(0 if json.load(open('runs/bg_sc212/optimization.json'))['converged'] else 1)"
}

start_level_choice() {
  running level-choice && return 0
  level_choice_done && return 0
  code_copy level
  PYTHONPATH=/tmp/emlp-level/src OMP_NUM_THREADS=1 nohup "$PY" \
    /tmp/emlp-level/examples/qm7_cheap/level_choice.py --commit >> runs/level-choice.log 2>&1 &
  echo $! > "$PIDS/level-choice.pid"
  echo "level-choice: PID $!, log runs/level-choice.log"
}

start_bg_optimize() {
  running bg-optimize && return 0
  bg_optimize_done && return 0
  # on hold while examples/beta_glycine/HOLD exists (it says why)
  [ -f examples/beta_glycine/HOLD ] && return 0
  command -v cp2k.psmp >/dev/null || { echo "bg-optimize: no CP2K (make install-cp2k)"; return 0; }
  code_copy bgopt
  PYTHONPATH=/tmp/emlp-bgopt/src OMP_NUM_THREADS=1 nohup "$PY" \
    /tmp/emlp-bgopt/examples/beta_glycine/campaign_job.py optimize --commit \
    --config examples/beta_glycine/config.yaml >> runs/bg-optimize.log 2>&1 &
  echo $! > "$PIDS/bg-optimize.pid"
  echo "bg-optimize: PID $!, log runs/bg-optimize.log"
}

BG_SETTINGS_JSON=examples/beta_glycine/settings_check_optimum.json

start_bg_settings() {
  running bg-settings && return 0
  [ -f "$BG_SETTINGS_JSON" ] && return 0
  bg_optimize_done || return 0
  command -v cp2k.psmp >/dev/null || { echo "bg-settings: no CP2K (make install-cp2k)"; return 0; }
  code_copy bgset
  PYTHONPATH=/tmp/emlp-bgset/src OMP_NUM_THREADS=1 nohup "$PY" \
    /tmp/emlp-bgset/examples/beta_glycine/settings_check.py --config \
    examples/beta_glycine/config.yaml --only config rel-60 cutoff-500 cutoff-600 \
    cutoff-600-rel-60 --reference cutoff-600-rel-60 --results \
    examples/beta_glycine/settings_check --out "$BG_SETTINGS_JSON" --commit \
    >> runs/bg-settings.log 2>&1 &
  echo $! > "$PIDS/bg-settings.pid"
  echo "bg-settings: PID $!, log runs/bg-settings.log"
}

BG_REFERENCE_JSON=examples/beta_glycine/dft_reference.json

start_bg_reference() {
  running bg-reference && return 0
  [ -f "$BG_REFERENCE_JSON" ] && return 0
  [ -f "$BG_SETTINGS_JSON" ] && bg_optimize_done || return 0
  command -v cp2k.psmp >/dev/null || { echo "bg-reference: no CP2K (make install-cp2k)"; return 0; }
  code_copy bgref
  OMP_NUM_THREADS=1 nohup bash -c "PYTHONPATH=/tmp/emlp-bgref/src $PY \
    /tmp/emlp-bgref/examples/beta_glycine/campaign_job.py label --reference-only --commit --shard-min-records 2 \
    --config examples/beta_glycine/config.yaml && PYTHONPATH=/tmp/emlp-bgref/src $PY \
    /tmp/emlp-bgref/examples/beta_glycine/run_study.py reference --config \
    examples/beta_glycine/config.yaml && cp runs/bg_sc212/dft.json $BG_REFERENCE_JSON.tmp && \
    mv $BG_REFERENCE_JSON.tmp $BG_REFERENCE_JSON && PYTHONPATH=src $PY -c \"from \
    emlpack.commits import git_commit; git_commit(['$BG_REFERENCE_JSON'], 'beta-glycine: DFT \
    tensors at the DFT optimum (finite differences, CP2K 400 Ry)')\"" >> runs/bg-reference.log 2>&1 &
  echo $! > "$PIDS/bg-reference.pid"
  echo "bg-reference: PID $!, log runs/bg-reference.log"
}

val_refs_done() {
  [ "$(ls datasets/mini-eqm7/references/pbe0_aug-cc-pvtz/validation/*.json 2>/dev/null | wc -l)" -ge 15 ]
}

start_val_refs() {
  running val-refs && return 0
  val_refs_done && return 0
  code_copy valrefs
  PYTHONPATH=/tmp/emlp-valrefs/src OMP_NUM_THREADS=1 nohup "$PY" \
    /tmp/emlp-valrefs/examples/eqm7/validation_references.py --commit >> runs/val-refs.log 2>&1 &
  echo $! > "$PIDS/val-refs.pid"
  echo "val-refs: PID $!, log runs/val-refs.log"
}

RAMAN_JSON=examples/raman/aziridine_pbe0_aug-cc-pvdz.json

start_raman_dft() {
  running raman-dft && return 0
  [ -f "$RAMAN_JSON" ] && return 0
  code_copy raman
  # the recipe's files are committed when it ends (a rerun computes only the missing SCFs)
  OMP_NUM_THREADS=1 nohup bash -c "PYTHONPATH=/tmp/emlp-raman/src $PY \
    /tmp/emlp-raman/examples/raman/aziridine_dft.py --threads 1 --out examples/raman/aziridine_dft \
    --json $RAMAN_JSON; PYTHONPATH=src $PY -c \"from emlpack.commits import git_commit; \
    git_commit(['examples/raman'], 'aziridine DFT Raman reference (PBE0/aug-cc-pVDZ)')\"" \
    >> runs/raman-dft.log 2>&1 &
  echo $! > "$PIDS/raman-dft.pid"
  echo "raman-dft: PID $!, log runs/raman-dft.log"
}

bakeoff_done() {  # every candidate of bakeoff.yaml has every stage's outputs
  PYTHONPATH=src "$PY" examples/eqm7/bakeoff.py done >/dev/null 2>&1
}

start_bakeoff() {
  running bakeoff && return 0
  bakeoff_done && return 0
  code_copy bakeoff
  # run commits bakeoff.md/json as each candidate ends; table writes and commits the last one
  OMP_NUM_THREADS=1 nohup bash -c "PYTHONPATH=/tmp/emlp-bakeoff/src $PY \
    /tmp/emlp-bakeoff/examples/eqm7/bakeoff.py run --commit && PYTHONPATH=/tmp/emlp-bakeoff/src \
    $PY /tmp/emlp-bakeoff/examples/eqm7/bakeoff.py table --commit" >> runs/bakeoff.log 2>&1 &
  echo $! > "$PIDS/bakeoff.pid"
  echo "bakeoff: PID $!, log runs/bakeoff.log"
}

ALPHA_DIR=datasets/mini-eqm7/polarizability

alpha_labels_done() {
  [ "$(ls "$ALPHA_DIR"/*.json 2>/dev/null | wc -l)" -ge 300 ]
}

start_alpha_labels() {
  running alpha-labels && return 0
  alpha_labels_done && return 0
  code_copy alpha
  PYTHONPATH=/tmp/emlp-alpha/src OMP_NUM_THREADS=1 nohup "$PY" \
    /tmp/emlp-alpha/examples/eqm7/polarizability_labels.py --count 300 --commit \
    >> runs/alpha-labels.log 2>&1 &
  echo $! > "$PIDS/alpha-labels.pid"
  echo "alpha-labels: PID $!, log runs/alpha-labels.log"
}

others() {  # how many of the other jobs run (each takes one core)
  local n=0 job
  for job in level-choice bg-optimize bg-settings bg-reference val-refs raman-dft bakeoff alpha-labels; do running "$job" && n=$((n + 1)); done
  echo "$n"
}

start_pretrain() {  # start_pretrain WORKERS
  running pretrain && return 0
  [ -f "$PRETRAIN_FILE" ] || { echo "pretrain: no level chosen yet ($PRETRAIN_FILE)"; return 0; }
  local data
  data=$(cat "$PRETRAIN_FILE")
  code_copy pretrain
  PYTHONPATH=/tmp/emlp-pretrain/src OMP_WAIT_POLICY=PASSIVE nohup "$PY" -m emlpack.cli \
    campaign run "$data" --workers "$1" --threads 1 --shard-minutes 25 --commit --quiet \
    >> runs/pretrain.log 2>&1 &
  echo $! > "$PIDS/pretrain.pid"
  echo "$1" > "$PIDS/pretrain.workers"
  echo "pretrain ($data, $1 workers): PID $!, log runs/pretrain.log"
}

start_all() {
  start_bg_optimize
  running bg-optimize || start_bg_settings
  running bg-optimize || running bg-settings || start_bg_reference
  start_level_choice
  # the brief's second stage (the equivariant family and the faster trainer exist): the chain
  # val-refs -> raman-dft -> bakeoff -> alpha-labels takes one core beside bg-optimize; the
  # pilot labels take the core that is left (none while both run)
  if ! running level-choice; then
    start_val_refs
    running val-refs || start_raman_dft
    running val-refs || running raman-dft || running alpha-labels || start_bakeoff
    running val-refs || running raman-dft || running bakeoff || start_alpha_labels
  fi
  local free=$((2 - $(others)))
  if running pretrain && [ "$free" -lt 1 ]; then stop_job pretrain; fi
  [ "$free" -ge 1 ] && start_pretrain "$free"
  return 0
}

watch_jobs() {  # every 5 minutes: start what is due (one more labeling process when a core frees)
  while sleep 300; do
    if running pretrain && [ "$(others)" -ge 2 ]; then  # the other jobs take both cores
      stop_job pretrain
      while running pretrain; do sleep 10; done
    fi
    if running pretrain && [ "$(cat "$PIDS/pretrain.workers" 2>/dev/null)" = 1 ] \
        && [ "$(others)" = 0 ] && val_refs_done && [ -f "$RAMAN_JSON" ] && bakeoff_done \
        && alpha_labels_done; then
      stop_job pretrain
      while running pretrain; do sleep 10; done
    fi
    start_all >> runs/long_jobs.log 2>&1 || true
  done
}

tree() {  # tree PID: the process and all its descendants
  local child
  echo "$1"
  for child in $(pgrep -P "$1" 2>/dev/null); do tree "$child"; done
}

signal_jobs() {  # signal_jobs SIGNAL: the running jobs (not the watcher) and their children
  local job pids=""
  for job in level-choice bg-optimize bg-settings bg-reference val-refs raman-dft bakeoff alpha-labels pretrain; do
    running "$job" && pids="$pids $(tree "$(cat "$PIDS/$job.pid")" | tr "\n" " ")"
  done
  # shellcheck disable=SC2086
  [ -n "$pids" ] && kill "-$1" $pids && echo "SIG$1:$pids"
  return 0
}

status() {
  local job
  for job in level-choice bg-optimize bg-settings bg-reference val-refs raman-dft bakeoff alpha-labels pretrain watcher; do
    if running "$job"; then echo "$job: running (PID $(cat "$PIDS/$job.pid"))"; else echo "$job: not running"; fi
  done
  echo "--- level choice"
  ls examples/qm7_cheap/level_choice/*/*.json 2>/dev/null | wc -l | sed 's/^/measurement files: /'
  level_choice_done && echo "complete" || echo "not complete"
  echo "--- beta-glycine DFT optimisation$([ -f examples/beta_glycine/HOLD ] && echo ' (on hold: examples/beta_glycine/HOLD)')"
  grep "optimize step" runs/bg-optimize.log 2>/dev/null | tail -2 || true
  ls datasets/beta-glycine-sc212/shards/*.h5 2>/dev/null | wc -l | sed 's/^/shards (2x1x2 supercell): /'
  echo "--- DFT tensors at the optimum: $(grep -c 'label: ref-opt.* done' runs/bg-reference.log 2>/dev/null || echo 0) of 19 calculations this session$([ -f "$BG_REFERENCE_JSON" ] && echo ', dft_reference.json written')"
  echo "--- CP2K settings at the optimum: $(ls examples/beta_glycine/settings_check/*.json 2>/dev/null | wc -l) of 5 candidates$([ -f "$BG_SETTINGS_JSON" ] && echo ', table written')"
  echo "--- validation references: $(ls datasets/mini-eqm7/references/pbe0_aug-cc-pvtz/validation/*.json 2>/dev/null | wc -l) of 15"
  echo "--- bake-off (examples/eqm7/bakeoff.yaml)"
  PYTHONPATH=src "$PY" examples/eqm7/bakeoff.py done 2>&1 || true
  echo "--- polarizability labels: $(ls "$ALPHA_DIR"/*.json 2>/dev/null | wc -l) of 300"
  if [ -f "$PRETRAIN_FILE" ]; then
    echo "--- pretraining campaign $(cat "$PRETRAIN_FILE")"
    PYTHONPATH=src "$PY" -c "
from emlpack.qm.campaign import campaign_statistics, campaign_target
d = '$(cat "$PRETRAIN_FILE")'
s = campaign_statistics(d); t = campaign_target(d)[1]
print(f\"{s['n_configurations']} configurations of {s['molecules_labeled']} molecules in {s['n_shards']} shards; {s['configurations_per_hour'] or 0:.0f} per hour; target {t['configurations']}/{t['molecules']} reached: {t['reached']}\")"
  fi
}

case "${1:-start}" in
  start)
    start_all
    if ! running watcher; then
      cp "$0" "$PIDS/watcher.sh"
      EMLP_ROOT=$PWD nohup bash "$PIDS/watcher.sh" watch >> runs/long_jobs.log 2>&1 &
      echo $! > "$PIDS/watcher.pid"
      echo "watcher: PID $!, log runs/long_jobs.log"
    fi
    ;;
  watch) watch_jobs ;;
  stop)
    signal_jobs CONT >/dev/null  # a paused job must run to see its SIGTERM
    stop_job watcher
    for job in level-choice bg-optimize bg-settings bg-reference val-refs raman-dft bakeoff alpha-labels pretrain; do stop_job "$job"; done
    ;;
  status) status ;;
  pause) signal_jobs STOP ;;
  resume) signal_jobs CONT ;;
  *) echo "usage: $0 [start|status|stop|pause|resume]" >&2; exit 2 ;;
esac
