# Quick start: `make run` (set up + main job), `make test` (set up + tests).
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: run test setup clean

setup: $(STAMP)

$(STAMP): pyproject.toml requirements.lock
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet -c requirements.lock -e ".[test,bench]"
	touch $(STAMP)

# The main job: a Monte Carlo sweep of the shipped default scenario, then its plots.
run: $(STAMP)
	$(VENV)/bin/rbdyn sweep torque_free_flip --n 20000 --out results/sweep/torque_free_flip.zarr
	$(VENV)/bin/rbdyn plot results/sweep/torque_free_flip.zarr

# Two workers: the suite is bound by XLA compilation, which is single-threaded.
test: $(STAMP)
	$(PY) -m pytest -q -n 2

clean:
	rm -rf $(VENV)
