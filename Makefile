# Fresh-machine entry points: each target makes .venv and installs the package itself.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: paper test test-all bench clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test]'
	touch $(STAMP)

## Regenerate the paper's figures and tables into results/paper/ (reduced trials).
paper: $(STAMP)
	$(PY) -m experiments.paper

## The test suite CI runs (slow end-to-end tests excluded; see test-all).
test: $(STAMP)
	$(PY) -m pytest -m "not slow" -q

test-all: $(STAMP)
	$(PY) -m pytest -q

clean:
	rm -rf $(VENV) outputs multirun
