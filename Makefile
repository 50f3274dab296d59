# weldrecon: `make demo` sets everything up and runs the main job on the built-in demo sample;
# `make test` runs the tests. Both install what is missing first (system packages, .venv).
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: setup demo test bench service-up service-down service-status clean-demo

$(STAMP): pyproject.toml deploy/install-system-deps.sh
	bash deploy/install-system-deps.sh
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[test]'
	touch $(STAMP)

setup: $(STAMP)

demo: setup
	$(BIN)/weldrecon demo --out out/demo

test: setup
	$(BIN)/pytest -q

bench: setup
	$(BIN)/python bench/bench_simulator.py

# a scheduled service on this machine (Prefect server on 127.0.0.1, process pool, worker): see docs/operations.md
service-up: setup
	deploy/service.sh up

service-down:
	deploy/service.sh down

service-status:
	deploy/service.sh status
