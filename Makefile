# One-command set-up on a fresh Debian machine: `make demo` and `make test` install
# everything they need (Python venv, pinned torch CPU wheel, anny model data).
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
export PROX_THREADS ?= 1

.PHONY: setup demo test bench clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet torch==2.13.0
	$(BIN)/pip install --quiet -e '.[dev]'
	touch $(STAMP)

setup: $(STAMP)
	$(BIN)/prox setup

demo: setup
	$(BIN)/prox demo --out demo_output

test: setup
	$(BIN)/python -m pytest -q tests

# The full benchmark (about 25 minutes on 2 cores; not part of the tests).
bench: setup
	$(BIN)/python -m benchmarks --seed 1 --frames 6 --out bench_output

clean:
	rm -rf $(VENV) demo_output bench_output .pytest_cache
