# jaxcal: `make demo` runs the main job, `make test` runs the test suite.
# Both create .venv when missing and install the project into it. The
# rendering targets install Debian's GL packages when missing (needs root;
# see README for users who are not root).

PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: demo test lint format bench clean

$(STAMP): pyproject.toml
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e ".[test]"
	@touch $(STAMP)

demo: $(STAMP)
	$(PY) -m jaxcal demo

test: $(STAMP)
	$(PY) -m pytest -q

lint: $(STAMP)
	$(VENV)/bin/ruff format --check jaxcal tests benchmarks
	$(VENV)/bin/ruff check jaxcal tests benchmarks

format: $(STAMP)
	$(VENV)/bin/ruff format jaxcal tests benchmarks
	$(VENV)/bin/ruff check --fix jaxcal tests benchmarks

bench: $(STAMP)
	$(PY) benchmarks/arcfit.py --json results/arcfit.json
	$(PY) benchmarks/montecarlo.py --trials 1000 --json results/montecarlo.json

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache results
