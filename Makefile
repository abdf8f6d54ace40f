# The README's two commands are `make demo` and `make test`; both set everything up first.
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
# torch is pinned here, not in pyproject: this exact release is the local CPU build, while a
# looser requirement would pull a multi-GB CUDA build. pyproject keeps a loose range for users.
TORCH := torch==2.13.0
PIP := $(BIN)/python -m pip --disable-pip-version-check -q

.PHONY: install demo test bench lint clean

install: $(STAMP)

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)

$(STAMP): pyproject.toml | $(BIN)/python
	$(PIP) install $(TORCH)
	$(PIP) install -e '.[dev]'
	@touch $(STAMP)

# The main job: the distributed system (router, world, cloud, 4 agent processes) in real time,
# the jammer swapped live through the control topic midway, then a summary and figures.
demo: install
	$(BIN)/jamnav up --uavs 4 --realtime --rate 20 --duration 60 --swap-jammer-at 30 \
		--swap-to 25,-10,1 --run-dir results/demo/up

test: install
	$(BIN)/python -m pytest

# Benchmarks measure one core, as their targets are stated.
bench: install
	OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 $(BIN)/python -m benchmarks --json benchmarks/latest.json

lint: install
	$(BIN)/ruff check .

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache
