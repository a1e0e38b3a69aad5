# RigidBench: two commands for a newcomer.
#   make demo   sets up .venv if missing, then runs the whole loop on the embedded default
#   make test   sets up .venv if missing, then runs the test suite
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
PIP := $(VENV)/bin/pip
# Pin torch so pip takes the CPU wheel where one is provided locally and never
# silently upgrades to a multi-GB CUDA build; override with `make TORCH_SPEC=...`.
TORCH_SPEC ?= torch==2.13.0
STAMP := $(VENV)/.rigidbench-installed
PYTEST_ARGS ?=

.PHONY: demo test setup clean-venv benchmarks

$(STAMP): pyproject.toml Makefile
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PIP) install --quiet --upgrade pip
	$(PIP) install --quiet "$(TORCH_SPEC)"
	$(PIP) install --quiet -e ".[all]"
	# LPIPS's linear-layer weights ship in the lpips package; install it without its torchvision
	# dependency (the CPU torch wheel has no matching torchvision build here, and we don't need it).
	$(PIP) install --quiet --no-deps "lpips==0.1.4"
	# Headless Chromium (Debian's package) for the report's browser test; skipped with its reason when
	# it cannot be installed (not root, no apt).
	@command -v chromium >/dev/null 2>&1 || { [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1 && \
		apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null; } || \
		echo "chromium not installed: the report's browser test will be skipped"
	@touch $(STAMP)

setup: $(STAMP)

demo: $(STAMP)
	$(PY) -m rigidbench demo

test: $(STAMP)
	$(PY) -m pytest -q $(PYTEST_ARGS)

# Stage timings as JSON. The render and perception benchmarks take minutes on a CPU:
#   $(PY) benchmarks/render.py    $(PY) benchmarks/perception.py --frames 8 --size 320x176
benchmarks: $(STAMP)
	$(PY) benchmarks/simulate.py
	$(PY) benchmarks/metrics.py
	$(PY) benchmarks/stats.py

clean-venv:
	rm -rf $(VENV)
