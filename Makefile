# Two commands set up a fresh machine: `make install`, then `make test`.
PYTHON ?= python
# A torch that fits this machine. Used only when no torch is installed yet, so a GPU user's
# CUDA build is never replaced; override e.g. `make install TORCH_SPEC="torch==2.5.1"`. Unquoted
# below: a requirement with pip options ("torch==2.5.1 --index-url <URL>") reaches pip as
# separate arguments.
TORCH_SPEC ?= torch==2.13.0
PYTEST_ARGS ?=
# GPU users (docs/gpu.md): `make install-gpu`, then `make gpu-check`. The torch installed unless
# a CUDA torch >= 2.4 is there already; `===` so that a local `+cpu` build never matches.
TORCH_GPU_SPEC ?= torch===2.13.0
# The project's extras install-gpu adds, comma-separated: `sweeps` for the SLURM, joblib and
# Optuna plugins of a cluster (docs/scaling.md)
GPU_EXTRAS ?=
# gpu-check's device and bench/gpu_check.py options (the test suite: cpu and --tiny --out DIR)
GPU_CHECK_ACCELERATOR ?= gpu
GPU_CHECK_ARGS ?=

.PHONY: install install-gpu gpu-check test test-fast lint format bench train clean

install:
	$(PYTHON) -c "import torch" 2>/dev/null || $(PYTHON) -m pip install $(TORCH_SPEC)
	$(PYTHON) bench/install_opencv.py
	$(PYTHON) -m pip install -e ".[dev]"

# Keeps a working CUDA torch >= 2.4, else installs TORCH_GPU_SPEC; the project without [dev];
# then says whether torch sees a GPU, and what to do if not (bench/install_gpu.py).
install-gpu:
	$(PYTHON) bench/install_gpu.py --torch-spec '$(TORCH_GPU_SPEC)' --extras '$(GPU_EXTRAS)'

# One command on a fresh CUDA machine: install what is missing, then the check (writes
# bench/results/gpu_check.md). GPU_CHECK_ACCELERATOR=cpu skips the install (the test suite).
gpu-check:
ifneq ($(GPU_CHECK_ACCELERATOR),cpu)
	$(MAKE) --no-print-directory install-gpu
endif
	$(PYTHON) bench/gpu_check.py --accelerator $(GPU_CHECK_ACCELERATOR) $(GPU_CHECK_ARGS)

# The architecture contract (pyproject.toml [tool.importlinter]): a wrong-way import fails here,
# naming both modules.
LINT_IMPORTS = $(PYTHON) -c "from importlinter.cli import lint_imports_command; lint_imports_command()"

test:
	$(PYTHON) -m ruff check src tests bench notebooks
	$(LINT_IMPORTS)
	$(PYTHON) -m pytest -n 2 $(PYTEST_ARGS)

# The edit-test loop: every test but the `slow` ones (real trainings, multiruns, the tiny study;
# the marker in pyproject.toml). CI runs `make test`, which includes them.
test-fast:
	$(PYTHON) -m pytest -n 2 -m "not slow" $(PYTEST_ARGS)

lint:
	$(PYTHON) -m ruff check src tests bench notebooks
	$(LINT_IMPORTS)
	$(PYTHON) -m ruff format --check src tests bench notebooks

format:
	$(PYTHON) -m ruff check --fix src tests bench notebooks
	$(PYTHON) -m ruff format src tests bench notebooks

train:
	$(PYTHON) -m mfg_lightning.train

bench:
	$(PYTHON) bench/run_all.py

clean:
	rm -rf build dist .pytest_cache .ruff_cache .import_linter_cache outputs multirun
