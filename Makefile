# flowloop developer entry points. Each creates .venv on first use.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python

# Workers for `make test`: most tests wait on hosts and the clock, not the CPU
# (README, "Where the time goes"); JOBS=0 runs them in one process.
JOBS ?= 4

.PHONY: demo test test-quick bench lint clean

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --disable-pip-version-check -e '.[dev]'
	touch $@

demo: $(VENV)/.installed
	$(PY) -m devtools.demo

test: $(VENV)/.installed
	$(PY) -m ruff check .
	$(PY) -m pytest -n $(JOBS)

# The developer's loop: unit and c tiers, and the klippy tests of what changed
# since BASE (default HEAD: the work not yet committed), on Klipper only.
test-quick: $(VENV)/.installed
	$(PY) -m ruff check .
	$(PY) -m devtools.quick $(if $(BASE),--base $(BASE))

bench: $(VENV)/.installed  # FLOWLOOP_BENCH_GCODE=DIR: whole slicer files for the G-code benches
	FLOWLOOP_BENCH_SIZE=full $(PY) -m pytest tests/bench -m bench -s -p no:cacheprovider

lint: $(VENV)/.installed
	$(PY) -m ruff check .

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache
