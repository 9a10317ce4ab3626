PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
# 2 cores in CI: XLA's CPU backend uses them itself; keep pytest single-process.
export XLA_FLAGS ?= --xla_cpu_multi_thread_eigen=true

.PHONY: run test test-all bench clean

$(VENV)/.installed: pyproject.toml
	test -d $(VENV) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e ".[test]"
	touch $@

run: $(VENV)/.installed
	$(VENV)/bin/jaxfric run nine --variant mu017

test: $(VENV)/.installed
	$(PY) -m pytest -q -m "not slow" --durations=15

test-all: $(VENV)/.installed
	$(PY) -m pytest -q

bench: $(VENV)/.installed
	$(PY) experiments/bench_core.py

clean:
	rm -rf $(VENV) runs .pytest_cache
