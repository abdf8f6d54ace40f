# The README's two commands are `make demo` and `make test`; both set everything up first.
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
# torch is pinned here, not in pyproject: this exact release is the local CPU build, while a
# looser requirement would pull a multi-GB CUDA build. pyproject keeps a loose range for users.
TORCH := torch==2.13.0
PIP := $(BIN)/python -m pip --disable-pip-version-check -q

.PHONY: install demo test soak bench lint clean

install: $(STAMP)
	@# The console's browser test drives Debian's chromium: installed here where we may (root).
	@[ -x /usr/bin/chromium ] || [ "$$(id -u)" != 0 ] || { apt-get update -qq >/dev/null && \
		DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null; } || \
		echo "could not install chromium: tests/test_console_browser.py will fail" >&2

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)

# The compiled core is built by the editable install, again whenever its source changes
# (shared.compiled_core refuses a core older than its source).
$(STAMP): pyproject.toml setup.py planning/_lookahead.pyx planning/_routes.pyx \
		planning/_regression.pyx planning/_evidence.pyx planning/_measuring.pyx planning/_dense.h \
		planning/_regression.h shared/_radio.pyx shared/_vector_math.h \
		| $(BIN)/python
	$(PIP) install $(TORCH)
	$(PIP) install -e '.[dev]'
	@touch $(STAMP)

# The main job: the distributed system (router, world, cloud, 4 agent processes) in real time,
# the jammer swapped live through the control topic midway, then a summary and figures. Each
# demo starts afresh: a run directory that exists would carry the cloud's memory over.
DEMO_DIR := results/demo/up
demo: install
	rm -rf $(DEMO_DIR)
	$(BIN)/jamnav up --uavs 4 --realtime --rate 20 --duration 60 --swap-jammer-at 30 \
		--swap-to 25,-10,1 --run-dir $(DEMO_DIR)

# Two workers (pytest-xdist): the systems of processes on one, the in-process tests on the
# other (tests/conftest.py makes the schedule).
test: install
	$(BIN)/python -m pytest -n 2 --dist loadscope

# Half an hour of faults: a process (world, cloud, an agent, the router) killed or frozen every
# 10-30 s, then the ledger of what came through (results/soak/ledger.json, report.json). Three
# UAVs at 2 steps/s take about 60,000 measurements: within the 100,000 the cloud's memory
# keeps, as the ledger looks for every one of them there.
SOAK_DIR := results/soak
soak: install
	rm -rf $(SOAK_DIR)
	$(BIN)/jamnav chaos --duration 1800 --uavs 3 --rate 2 --seed 1 --run-dir $(SOAK_DIR)

# Benchmarks measure one core, as their targets are stated.
bench: install
	OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 $(BIN)/python -m benchmarks --json benchmarks/latest.json

lint: install
	$(BIN)/ruff check .

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache
