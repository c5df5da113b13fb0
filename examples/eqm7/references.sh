#!/usr/bin/env bash
# DFT references of the study's test molecules in the background, committed as they finish.
#
#   bash examples/eqm7/references.sh [NAME ...] [KEY=VALUE ...]
#       (from the project root; default: every test molecule of the card and the second test
#       set's static ones, in `dft_plan`'s order; KEY=VALUE: run_study.py overrides, e.g. a
#       second process on the molecule another one is computing, from its last displacement back:
#       REFERENCES_LOG=runs/eqm7-references-reverse.log bash examples/eqm7/references.sh NAME \
#       dft.hessian_reverse=true)
#
# Runs `run_study.py dft` (resumable: BFGS step by step, ground state, each field, each Hessian
# displacement) and every COMMIT_MINUTES (default 20) commits the finished reference files only:
# .npz sub-results, NAME.json and NAME.ir.json, and the displacement files of NAME/vib/ that are
# complete JSON (a file being written is never committed). Restart it after a session ends:
# nothing finished is lost.
# Log: runs/eqm7-references.log. Stop: `kill WATCHER_PID` (the PID it prints): the watcher stops
# the dft stage, commits what is finished and exits (it also commits once more when the stage
# ends by itself).
set -euo pipefail
cd "$(dirname "$0")/../.."
PY=${PYTHON:-.venv/bin/python}
REFS=datasets/mini-eqm7/references
LOG=${REFERENCES_LOG:-runs/eqm7-references.log}  # a second run beside the first: its own log
mkdir -p runs
molecules=()
overrides=()
for arg in "$@"; do
  case "$arg" in
    *=*) overrides+=("$arg") ;;
    *) molecules+=("$arg") ;;
  esac
done
if [ ${#molecules[@]} -gt 0 ]; then overrides+=("molecules=[$(IFS=,; echo "${molecules[*]}")]"); fi

commit_finished() {
  "$PY" - "$REFS" <<'PYEOF'
import json, subprocess, sys
from pathlib import Path

from emlpack.commits import git_commit  # retries while another job's commit holds the lock

refs = Path(sys.argv[1])
done = []
for p in sorted(refs.rglob("*")):
    if not p.is_file() or p.name.startswith("."):
        continue
    if p.suffix == ".json":
        try:
            json.loads(p.read_text())
        except ValueError:
            continue  # being written
    elif p.suffix != ".npz":
        continue
    done.append(str(p))
new = subprocess.run(["git", "ls-files", "--others", "--exclude-standard", "--", *done],
                     capture_output=True, text=True, check=True).stdout.split()
if new and git_commit([Path(f) for f in new], f"mini-eqm7 DFT references: {len(new)} finished files"):
    print(f"committed {len(new)} files", flush=True)
PYEOF
}

(
  OMP_WAIT_POLICY=PASSIVE nohup "$PY" examples/eqm7/run_study.py dft dft.keep_heap=true "${overrides[@]}" >> "$LOG" 2>&1 &
  job=$!
  echo "dft stage: PID $job, log $LOG"
  # kill WATCHER_PID: stop the stage (its sub-steps are written atomically), commit, exit
  trap 'kill "$job" 2>/dev/null; wait "$job" 2>/dev/null || true; commit_finished >> "$LOG" 2>&1 || true; exit 0' TERM
  while kill -0 "$job" 2>/dev/null; do
    for _ in $(seq $((${COMMIT_MINUTES:-20} * 6))); do
      kill -0 "$job" 2>/dev/null || break
      sleep 10
    done
    commit_finished >> "$LOG" 2>&1 || echo "commit failed (retrying later)" >> "$LOG"
  done
  commit_finished >> "$LOG" 2>&1 || true
) &
echo "references: watcher PID $!"
