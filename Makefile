# escape: set-up, tests, demo and benchmarks.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: install test demo bench clean

install: $(STAMP)

$(STAMP): pyproject.toml
	bash scripts/install_system_deps.sh
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	# torch is pinned: 2.13.0 is the CPU build; anything else pulls CUDA wheels.
	$(BIN)/pip install --quiet torch==2.13.0
	$(BIN)/pip install --quiet -e '.[test,train,h5]'
	touch $(STAMP)

test: install
	$(BIN)/python -m pytest -q

demo: install
	bash examples/demo.sh

bench: install
	$(BIN)/python bench/bench_reconstruction.py
	$(BIN)/python bench/bench_complete.py

clean:
	rm -rf $(VENV) build src/*.egg-info .pytest_cache
