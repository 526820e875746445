# One-command set-up on a fresh Debian machine: `make demo` and `make test` install
# everything they need (Python venv, pinned torch CPU wheel, anny model data).
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
export PROX_THREADS ?= 1
# Debian packages: Redis for the job queue (tests start their own server), OSMesa for
# renders on the CPU; Chromium and tidy only for the report tests.
APT_PACKAGES := redis-server libosmesa6 chromium tidy
SUDO := $(if $(filter 0,$(shell id -u)),,sudo)

.PHONY: system setup demo serve test bench loadcheck clean

system:
	@missing=$$(for p in $(APT_PACKAGES); do dpkg-query -W -f='$${Status}\n' $$p 2>/dev/null \
	  | grep -q '^install ok installed' || echo $$p; done); \
	if [ -n "$$missing" ]; then $(SUDO) apt-get update -qq && \
	  DEBIAN_FRONTEND=noninteractive $(SUDO) apt-get install -y -qq --no-install-recommends \
	  $$missing; fi

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet torch==2.13.0
	$(BIN)/pip install --quiet -e '.[dev]'
	touch $(STAMP)

setup: system $(STAMP)
	$(BIN)/prox setup

# Fits the bundled synthetic sequence through a local service (Redis, API, 2 workers).
demo: setup
	$(BIN)/prox demo --out demo_output

# Redis, the API on :8000 and one worker, until Ctrl-C.
serve: setup
	$(BIN)/prox serve

test: setup
	$(BIN)/python -m pytest -q tests

# The full benchmark (8 configurations x 7 kinds x 6 frames, about an hour in one
# process; not part of the tests).
bench: setup
	$(BIN)/python -m benchmarks --seed 1 --frames 6 --out bench_output

# 50 small jobs on 2 workers, then a worker killed mid-job (a few minutes; not a test).
loadcheck: setup
	$(BIN)/python -m service.loadcheck --jobs 50 --workers 2 --out loadcheck_output

clean:
	rm -rf $(VENV) demo_output bench_output loadcheck_output .pytest_cache
