# Fresh-machine entry points: each target makes .venv and installs what it needs itself.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python

.PHONY: paper test test-all bench results clean

$(PY):
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip

# The paper's figures need the harness (Hydra, pandas, pyarrow, matplotlib, ...), an extra of the package.
$(VENV)/.paper: pyproject.toml | $(PY)
	$(PY) -m pip install --quiet -e '.[harness]'
	touch $@

# The tests also exercise the optional extras (harness, OR-Tools, dask, astroalign, GTSAM).
$(VENV)/.test: pyproject.toml | $(PY)
	$(PY) -m pip install --quiet -e '.[test]'
	touch $@

# Every driver's extras: the harness, OR-Tools (the bench's 10^5-landmark LP), astroalign, GTSAM (the SLAM maps of
# Victoria Park and MR.CLAM) and pycpd. CLIPPER and TEASER++ are built by tools/build_peers.sh; without them the
# peers' steps are skipped.
$(VENV)/.results: pyproject.toml | $(PY)
	$(PY) -m pip install --quiet -e '.[harness,large,baselines,slam,peers]'
	touch $@

## Regenerate the paper's Fig. 1-3 and tables into results/paper/ (10,000 trials per ROC curve).
paper: $(VENV)/.paper
	$(PY) -m experiments.paper

## The test suite CI runs: the whole default suite (slow end-to-end runs excluded; see test-all),
## on 2 processes (pytest-xdist; worksteal keeps both busy while the long end-to-end tests finish).
PYTEST := $(PY) -m pytest -q -n 2 --dist worksteal

test: $(VENV)/.test
	$(PYTEST) -m "not slow"

test-all: $(VENV)/.test
	$(PYTEST)

## Speed and scale benchmarks into results/bench.md (about 15 minutes).
bench: $(VENV)/.test
	$(PY) -m experiments.bench

## Regenerate every committed result, driver by driver, then the tables in docs/ (python -m experiments.all;
## the order and each step's time: docs/harness.md; this run's times: results/timing.md).
results: $(VENV)/.results
	$(PY) -m experiments.all

clean:
	rm -rf $(VENV) outputs multirun
