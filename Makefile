# Two commands set up a fresh machine: `make install`, then `make test`.
PYTHON ?= python
# A torch that fits this machine. Used only when no torch is installed yet, so a GPU user's
# CUDA build is never replaced; override e.g. `make install TORCH_SPEC="torch==2.5.1"`.
TORCH_SPEC ?= torch==2.13.0
PYTEST_ARGS ?=

.PHONY: install test lint format bench train clean

install:
	$(PYTHON) -c "import torch" 2>/dev/null || $(PYTHON) -m pip install "$(TORCH_SPEC)"
	$(PYTHON) -m pip install -e ".[dev]"

# The architecture contract (pyproject.toml [tool.importlinter]): a wrong-way import fails here,
# naming both modules.
LINT_IMPORTS = $(PYTHON) -c "from importlinter.cli import lint_imports_command; lint_imports_command()"

test:
	$(PYTHON) -m ruff check src tests bench
	$(LINT_IMPORTS)
	$(PYTHON) -m pytest -n 2 $(PYTEST_ARGS)

lint:
	$(PYTHON) -m ruff check src tests bench
	$(LINT_IMPORTS)
	$(PYTHON) -m ruff format --check src tests bench

format:
	$(PYTHON) -m ruff check --fix src tests bench
	$(PYTHON) -m ruff format src tests bench

train:
	$(PYTHON) -m mfg_lightning.train

bench:
	$(PYTHON) bench/run_all.py

clean:
	rm -rf build dist .pytest_cache .ruff_cache .import_linter_cache outputs multirun
