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
	@touch $(STAMP)

setup: $(STAMP)

demo: $(STAMP)
	$(PY) -m rigidbench demo

test: $(STAMP)
	$(PY) -m pytest -q $(PYTEST_ARGS)

benchmarks: $(STAMP)
	$(PY) benchmarks/simulate.py

clean-venv:
	rm -rf $(VENV)
