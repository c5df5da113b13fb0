#!/usr/bin/env bash
# The package as users install it: build the wheel from the tracked files, install it into a
# fresh virtual environment without extras (CPU torch 2.13.0 first, as the Makefile does) and
# run .ci/wheel_smoke.py there: every command of `emlp --help` works on a small input or exits 2
# with one line naming its extra. Cost: 5.5 min on 2 busy cores (venv and pip 0.4 min, CPU torch
# 1.2, wheel 0.1, its dependencies 1.1, smoke test 2.6).
#   WHEEL_CHECK_DIR=/tmp/x  keep the venv and the outputs there (default: a new temporary folder,
#                           removed after a passing run)
#   PYTHON=python3.11       the interpreter of the venv (default python3)
set -euo pipefail
ROOT="$(cd "$(dirname "$0")/.." && pwd)"
PYTHON="${PYTHON:-python3}"
WORK="${WHEEL_CHECK_DIR:-$(mktemp -d "${TMPDIR:-/tmp}/emlpack-wheel-check.XXXXXX")}"
mkdir -p "$WORK"
export OMP_NUM_THREADS="${OMP_NUM_THREADS:-1}"
export PIP_DISABLE_PIP_VERSION_CHECK=1
start=$SECONDS
step() { echo "wheel check: $1 ($((SECONDS - start)) s)"; }

step "source tree of the tracked files -> $WORK/src"
rm -rf "$WORK/src" "$WORK/dist" "$WORK/venv" "$WORK/smoke"
mkdir -p "$WORK/src"
# tracked files only (a stale build/ or an untracked file cannot reach the wheel)
git -C "$ROOT" ls-files -z | (cd "$ROOT" && tar --null -T - -cf -) | tar -xf - -C "$WORK/src"

step "fresh venv"
"$PYTHON" -m venv "$WORK/venv"
VPY="$WORK/venv/bin/python"
"$VPY" -m pip install -q --upgrade pip
step "torch==2.13.0 (CPU)"
"$VPY" -m pip install -q torch==2.13.0
step "build the wheel"
"$VPY" -m pip wheel -q --no-deps -w "$WORK/dist" "$WORK/src"
WHEEL="$(ls "$WORK"/dist/emlpack-*.whl)"
# the pretrained model files are package data
"$VPY" - "$WHEEL" <<'PY'
import sys, zipfile
names = zipfile.ZipFile(sys.argv[1]).namelist()
models = [n for n in names if n.startswith("emlpack/pretrained/") and n.endswith(".pt")]
cards = [n for n in names if n.startswith("emlpack/pretrained/") and n.endswith("card.md")]
assert models and cards, f"no pretrained model files in {sys.argv[1]}"
print(f"wheel check: {len(models)} pretrained model files and {len(cards)} card(s) in the wheel")
PY
step "install the wheel without extras"
"$VPY" -m pip install -q "$WHEEL"
"$VPY" -c 'import torch; v = torch.__version__; assert v.startswith("2.13.0"), v'
step "smoke test"
SHARED=()
if [ -d "$ROOT/../shared" ]; then SHARED=(--shared "$(cd "$ROOT/../shared" && pwd)"); fi
cd "$WORK"  # not the source tree: the installed package is what is imported
"$VPY" "$ROOT/.ci/wheel_smoke.py" "$WORK/smoke" "${SHARED[@]}"
step "passed"
if [ -z "${WHEEL_CHECK_DIR:-}" ]; then rm -rf "$WORK"; fi
