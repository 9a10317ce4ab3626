PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
export XLA_FLAGS ?= --xla_cpu_multi_thread_eigen=true
# The suite is bound by XLA compilation, which runs on one core: two pytest workers (pytest-xdist), one
# test file each at a time so that module fixtures are built once, took the fast suite from 13 min 17 s
# to 8 min 14 s on a 2-core machine. The suite also asks XLA for its faster-compiling CPU emitters
# (tests/conftest.py): 9 min 10 s against 13.5 to 16 min on the same machine. The longest files go first
# (tests/conftest.py's LONGEST_FIRST, with --no-loadscope-reorder): pytest-xdist's own order, the files
# with the most tests first, leaves the single long tests of one-test files for the end
# (python experiments/suite_files.py REPORT.xml models both orders on a run's measured times). The
# compiled programs are kept in .pytest_cache between runs (tests/conftest.py): the next make test reads
# them (301 s against 432 s of tests in a clean clone); make clean or pytest --cache-clear starts from none.
WORKERS ?= 2

.PHONY: run lint test test-all bench clean

$(VENV)/.installed: pyproject.toml
	test -d $(VENV) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e ".[test]"
	touch $@

run: $(VENV)/.installed
	$(VENV)/bin/jaxfric run nine --variant mu017

# Lint (ruff: style, imports, pyupgrade, blind except) and type-check (mypy, the package) before the tests.
lint: $(VENV)/.installed
	$(VENV)/bin/ruff check jaxfric tests experiments notebooks/execute.py
	$(VENV)/bin/mypy

test: $(VENV)/.installed lint
	$(PY) -m pytest -q -m "not slow" -n $(WORKERS) --dist loadfile --no-loadscope-reorder --durations=15

test-all: $(VENV)/.installed lint
	$(PY) -m pytest -q -n $(WORKERS) --dist loadfile --no-loadscope-reorder

bench: $(VENV)/.installed
	$(PY) experiments/bench_core.py

clean:
	rm -rf $(VENV) runs .pytest_cache
