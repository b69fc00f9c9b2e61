# escape: set-up, tests, demo and benchmarks.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
# Development installs every extra (one per job: see pyproject.toml).
EXTRAS ?= test,train,synth,h5,ray
# torch is pinned to 2.13.0; on indexes where that is a CUDA build, take the CPU build:
#   make install TORCH_INDEX="--index-url https://download.pytorch.org/whl/cpu"
TORCH_INDEX ?=
comma := ,

.PHONY: install test demo bench check-install clean

install: $(STAMP)

$(STAMP): pyproject.toml setup.py src/escape_cli/core/_kernels.c
	bash scripts/install_system_deps.sh $(subst $(comma), ,$(EXTRAS))
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet torch==2.13.0 $(TORCH_INDEX)
	$(BIN)/pip install --quiet -e '.[$(EXTRAS)]'
	touch $(STAMP)

test: install
	$(BIN)/python -m pytest -q

demo: install
	bash examples/demo.sh

bench: install
	$(BIN)/python bench/bench_reconstruction.py
	$(BIN)/python bench/bench_complete.py

# The wheel, installed without extras into a fresh virtual environment, completes a scan.
check-install:
	bash scripts/check_runtime_install.sh

clean:
	rm -rf $(VENV) build dist src/*.egg-info .pytest_cache
