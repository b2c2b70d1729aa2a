# Quick start: `make run` (set up + main job), `make test` (set up + tests).
# `make docs` builds the documentation site into site/ (open site/index.html).
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: run test lint test-jax-next docs setup clean

setup: $(STAMP)

$(STAMP): pyproject.toml requirements.lock
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet -c requirements.lock -e ".[test,bench,docs,dask]"
	touch $(STAMP)

# The main job: a Monte Carlo sweep of the shipped default scenario (replacing the last
# one), then its plots.
run: $(STAMP)
	$(VENV)/bin/rbdyn sweep torque_free_flip --n 20000 --out results/sweep/torque_free_flip.zarr --overwrite
	$(VENV)/bin/rbdyn plot results/sweep/torque_free_flip.zarr

# Two workers: the suite is bound by XLA compilation, which is single-threaded.
test: $(STAMP)
	$(PY) -m pytest -q -n 2 --dist loadgroup

# The code as ruff checks and formats it (pyproject's [tool.ruff]); CI runs it before the tests.
lint: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

# The suite's core again under the next JAX (0.11, on Python >= 3.12): a second venv,
# .venv-jax-next (.ci/jax-next).
test-jax-next:
	.ci/jax-next

# The documentation site, built offline into site/ (strict: a broken link fails the build).
docs: $(STAMP)
	NO_MKDOCS_2_WARNING=1 $(PY) -m mkdocs build --strict

clean:
	rm -rf $(VENV) .venv-jax-next site
