# jaxcal: `make demo` runs the main job, `make test` runs the test suite.
# Both create .venv when missing and install the project into it. The
# rendering targets install Debian's GL packages when missing (needs root;
# see README for users who are not root).

PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: demo test lint format bench clean gl notebooks

# Headless OpenGL for MuJoCo (EGL + Mesa; OSMesa as the fallback).
GL_PACKAGES := libegl1 libgl1-mesa-dri
gl:
	@if ldconfig -p | grep -q 'libEGL.so.1' && ls /usr/lib/*/dri/swrast_dri.so >/dev/null 2>&1; then :; \
	elif ldconfig -p | grep -q 'libOSMesa.so'; then :; \
	elif [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
		echo "installing $(GL_PACKAGES) (headless OpenGL for MuJoCo rendering)"; \
		apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $(GL_PACKAGES) >/dev/null; \
	else \
		echo "MuJoCo rendering needs a headless OpenGL library: sudo apt-get install $(GL_PACKAGES) (or libosmesa6)"; \
		exit 1; \
	fi

$(STAMP): pyproject.toml constraints.txt
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -c constraints.txt -e ".[test]"
	@touch $(STAMP)

demo: $(STAMP) gl
	$(PY) -m jaxcal demo

# Two worker processes (one per core on CI's two): compilation is mostly
# single-threaded. Each test file stays whole on one worker (--dist loadfile), so
# module fixtures that render or calibrate are built once and a file's tests
# share their compiled programs in memory; the files are small against the
# total (the largest about a seventh), so the two workers still balance.
# (--dist loadgroup would be finer, but pytest-xdist 3.8 tags its groups through
# `item._nodeid`, which pytest 9 no longer reads: the groups silently split.)
# --no-loadscope-reorder keeps the files in tests/conftest.py's order, slowest
# first (pytest-xdist otherwise queues them by their number of tests).
# One BLAS thread per worker: two workers on two cores already fill the machine, and
# OpenBLAS's spinning threads only steal from the other worker.
test: $(STAMP) gl
	OPENBLAS_NUM_THREADS=1 $(PY) -m pytest -q --durations=15 -n auto --maxprocesses 2 --dist loadfile --no-loadscope-reorder

# The notebooks are run at full size and stored with their outputs (plots included), so a reader
# sees the results first; tests/test_notebooks.py fails when a notebook's code changed since.
notebooks: $(STAMP) gl
	$(PY) notebooks/refresh.py

lint: $(STAMP)
	$(VENV)/bin/ruff format --check jaxcal tests benchmarks
	$(VENV)/bin/ruff check jaxcal tests benchmarks

format: $(STAMP)
	$(VENV)/bin/ruff format jaxcal tests benchmarks
	$(VENV)/bin/ruff check --fix jaxcal tests benchmarks

bench: $(STAMP)
	$(PY) benchmarks/arcfit.py --json results/arcfit.json
	$(PY) benchmarks/montecarlo.py --trials 1000 --json results/montecarlo.json
	$(PY) benchmarks/render.py --json results/render.json

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache results
