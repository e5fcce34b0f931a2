# The two set-up commands: `make demo` and `make test`. Both are idempotent: they create .venv if it is
# missing, install the pinned CPU torch and the project (skipped when pyproject.toml has not changed), then run.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed-$(shell cat pyproject.toml | sha1sum | cut -c1-12)

# Torch's and numba's OpenMP pools fight under load unless waiting threads sleep (docs/DECISIONS.md, "Numbers
# behind code comments", thread pools).
export OMP_WAIT_POLICY := PASSIVE
export PIP_DISABLE_PIP_VERSION_CHECK := 1

.PHONY: install demo test lint bench clean

$(BIN)/python:
	$(PY) -m venv $(VENV)

$(STAMP): pyproject.toml | $(BIN)/python
	$(BIN)/pip install -q "torch==2.13.0"
	$(BIN)/pip install -q -e ".[dev,service,report]"
	rm -f $(VENV)/.installed-*
	touch $(STAMP)

install: $(STAMP)

demo: install
	$(BIN)/dualphys demo --out demo-out

test: install
	$(BIN)/ruff check pipeline service worker cli tests bench
	$(BIN)/python -m pytest -q -n 2

lint: install
	$(BIN)/ruff check pipeline service worker cli tests bench

bench: install
	$(BIN)/python bench/raster.py

clean:
	rm -rf $(VENV) demo-out .pytest_cache .ruff_cache
