# Two commands for a fresh clone: `make demo` (the main job) and `make test`.
# Both create .venv on first use: the CPU torch wheel first (pinned to its +cpu build, so pip never pulls a CUDA
# build), then hapticlink with its training and development extras. pip finds that wheel where its configuration
# points (a local wheel folder on this project's machines); PyPI has no +cpu build, so where pip reaches PyPI name
# PyTorch's CPU index: `make TORCH_INDEX=https://download.pytorch.org/whl/cpu test`.
PYTHON ?= python3
TORCH_INDEX ?=
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: demo test bench

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet 'torch==2.13.0+cpu' $(if $(TORCH_INDEX),--index-url $(TORCH_INDEX)) \
	  || { echo "no CPU build of torch 2.13.0 found: run make TORCH_INDEX=https://download.pytorch.org/whl/cpu …" >&2; exit 1; }
	$(BIN)/pip install --quiet -e '.[train,dev]'
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/hapticlink demo

# The house's checks first (seconds), then the suite; the import contracts run inside it (tests/test_architecture.py).
# Two pytest-xdist workers, each taking whole files (a module's server, browser or topology is started once): many
# tests wait on real time (streams, restarts, a browser), and the other worker computes meanwhile. The files are
# handed out in collection order, the files with a `slow` test first (tests/conftest.py), so both end together.
test: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/mypy
	$(BIN)/python -m pytest -q -n 2 --dist loadfile --no-loadscope-reorder

bench: $(STAMP)
	$(BIN)/python -m benchmarks
