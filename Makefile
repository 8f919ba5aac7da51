# Quick start: `make demo` (install + the main training run) and `make test` (install + lint + tests).
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
DEMO_CONFIG ?= configs/demo_small.yaml
DEMO_OUT ?= runs/demo

.PHONY: demo test lint install install-dev clean

$(VENV)/bin/python:
	$(PYTHON) -c 'import sys; assert sys.version_info >= (3, 11), "Python 3.11+ needed"'
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip

$(VENV)/.installed: $(VENV)/bin/python pyproject.toml
	$(PY) -m pip install -q -e .
	touch $@

$(VENV)/.installed-dev: $(VENV)/bin/python pyproject.toml
	$(PY) -m pip install -q -e '.[dev]'
	touch $@ $(VENV)/.installed

install: $(VENV)/.installed
install-dev: $(VENV)/.installed-dev

demo: $(VENV)/.installed
	@if [ -f $(DEMO_OUT)/config.yaml ]; then \
	  $(VENV)/bin/evojax-motion train $(DEMO_CONFIG) --out $(DEMO_OUT) --resume; \
	else \
	  $(VENV)/bin/evojax-motion train $(DEMO_CONFIG) --out $(DEMO_OUT); \
	fi

lint: $(VENV)/.installed-dev
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .
	$(VENV)/bin/mypy

# --dist loadscope: a module's tests share one worker, so its module-scoped fixtures (compiled
# steps, training runs) are built once, not once per worker; tests/conftest.py makes modules that
# build the same programs one unit and orders the units heaviest first (--no-loadscope-reorder:
# in that order, not by their numbers of tests). The suite compiles at XLA's optimisation level 0;
# the tests marked isa_sensitive or shipped_level run (again) at the default level with XLA:CPU's
# instruction set capped (AVX2 on AVX-512 CPUs, else SSE4.2; EVOJAX_TEST_ISAS=SSE4_2,AVX2 for both)
# in a pytest subprocess of tests/test_isa_variants.py; a failure there fails this target.
test: lint
	$(VENV)/bin/pytest -q -n 2 --dist loadscope --no-loadscope-reorder --durations=15

clean:
	rm -rf $(VENV) runs .pytest_cache
