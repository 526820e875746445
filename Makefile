# One-command set-up on a fresh Debian machine: `make demo` and `make test` install
# everything they need (Python venv, pinned torch CPU wheel, anny model data).
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
export PROX_THREADS ?= 1
# Debian packages: Redis for the job queue, OSMesa for renders on the CPU; Chromium and
# tidy only for the report tests (`make test`).
APT_RUNTIME := redis-server libosmesa6
APT_TEST    := chromium tidy
SUDO := $(if $(filter 0,$(shell id -u)),,sudo)
# PyTorch's CPU wheels (the default index has the CUDA build: gigabytes of nvidia
# packages); when that index cannot be reached in 10 s, the configured index is used.
TORCH_INDEX ?= https://download.pytorch.org/whl/cpu
# What apt-get prints goes to a log, shown only when it fails.
apt_install = missing=$$(for p in $(1); do dpkg-query -W -f='$${Status}\n' $$p 2>/dev/null \
	  | grep -q '^install ok installed' || echo $$p; done); \
	if [ -n "$$missing" ]; then echo "installing Debian packages:" $$missing; \
	  { $(SUDO) apt-get update -qq && DEBIAN_FRONTEND=noninteractive $(SUDO) apt-get install \
	  -y -qq --no-install-recommends $$missing; } >/tmp/prox-apt.log 2>&1 \
	  || { cat /tmp/prox-apt.log; exit 1; }; fi

.PHONY: system system-test setup viewer demo serve test bench loadcheck clean

system:
	@$(call apt_install,$(APT_RUNTIME))

system-test:
	@$(call apt_install,$(APT_TEST))

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet --timeout 10 --retries 0 --index-url $(TORCH_INDEX) \
	  torch==2.13.0 2>/dev/null || $(BIN)/pip install --quiet torch==2.13.0
	$(BIN)/pip install --quiet -e '.[dev]'
	$(BIN)/python -c "import torch; assert torch.version.cuda is None, 'a CUDA torch'"
	touch $(STAMP)

# The reports' 3D viewer: three.js and our viewer code bundled by esbuild into one classic
# script (pinned in viewer/package-lock.json; Debian's nodejs and npm when there is no npm).
VIEWER_JS := viewer/dist/viewer.js
$(VIEWER_JS): viewer/package.json viewer/package-lock.json viewer/src/viewer.js
	@command -v npm >/dev/null || { $(call apt_install,nodejs npm); }
	cd viewer && npm ci --ignore-scripts --no-audit --no-fund --loglevel=error \
	  && npm run build --silent

viewer: $(VIEWER_JS)

setup: system $(STAMP) $(VIEWER_JS)
	$(BIN)/prox setup

# Fits the bundled synthetic sequence through a local service (Redis, API, 2 workers).
demo: setup
	$(BIN)/prox demo --out demo_output

# Redis, the API on :8000 and one worker, until Ctrl-C.
serve: setup
	$(BIN)/prox serve

test: setup system-test
	$(BIN)/python -m pytest -q tests

# The full benchmark (9 configurations x 7 kinds x 6 frames, about an hour in one
# process; not part of the tests).
bench: setup
	$(BIN)/python -m benchmarks --seed 1 --frames 6 --out bench_output

# 50 small jobs on 2 workers, then a worker killed mid-job (a few minutes; not a test).
loadcheck: setup
	$(BIN)/python -m service.loadcheck --jobs 50 --workers 2 --out loadcheck_output

clean:
	rm -rf $(VENV) demo_output bench_output loadcheck_output .pytest_cache viewer/node_modules \
	  viewer/dist
