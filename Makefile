# Set-up and entry points. `make demo` and `make test` create .venv when missing.
# torch==2.13.0 (the CPU wheel) is installed FIRST, so nothing pulls a CUDA build.
VENV ?= .venv
PY := $(VENV)/bin/python
PIP := $(PY) -m pip

.PHONY: install install-cp2k demo test test-slow lint bench-deps bench clean

$(VENV)/.installed: pyproject.toml Makefile
	test -x $(PY) || python3 -m venv $(VENV)
	$(PIP) install -q --upgrade pip
	$(PIP) install -q torch==2.13.0
	$(PIP) install -q -e '.[qm,dev,periodic]'
	touch $@

install: $(VENV)/.installed

# CP2K (periodic labeler, emlpack.qm.cp2k): Debian/Ubuntu packages, only when missing.
install-cp2k:
	@command -v cp2k.psmp >/dev/null && command -v mpirun >/dev/null \
		&& test -f /usr/share/cp2k/BASIS_MOLOPT || { \
		SUDO=$$(test "$$(id -u)" -eq 0 || echo sudo); \
		$$SUDO apt-get update -q && \
		DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -q cp2k cp2k-data openmpi-bin; }

demo: install
	$(VENV)/bin/emlp demo --output demo_output

test: install install-cp2k
	$(PY) -m pytest -q

test-slow: install
	$(PY) -m pytest -q -m slow

lint: install
	$(VENV)/bin/ruff check src tests benchmarks

# SchNetPack is a benchmark baseline only. It pins sympy<=1.12, which would make pip
# replace torch 2.13 by an old CUDA build, so it is installed without its dependencies.
$(VENV)/.bench: $(VENV)/.installed
	$(PIP) install -q --no-deps schnetpack==2.1.1
	$(PIP) install -q hydra-core hydra-colorlog matscipy pytorch-lightning torchmetrics torch-ema \
		rich dirsync fasteners
	$(PY) -c 'import torch; v = torch.__version__; assert v.startswith("2.13.0"), v'
	touch $@

bench-deps: $(VENV)/.bench

bench: bench-deps
	$(PY) benchmarks/throughput.py --json benchmarks/results/throughput.json
	$(PY) benchmarks/relax.py --json benchmarks/results/relax.json

clean:
	rm -rf $(VENV) demo_output
