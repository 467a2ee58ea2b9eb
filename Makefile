# Everything runs inside a local virtual environment (.venv) created on first use; nothing
# depends on what is installed elsewhere on the machine.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
# Kernels compiled by tests, demos and benchmarks are cached here unless FASTSDF_CACHE_DIR is set.
export FASTSDF_CACHE_DIR ?= $(CURDIR)/.cache/kernels
export MPLBACKEND ?= Agg

.PHONY: venv demo docs test bench bench-quick clean

$(VENV)/.base: setup.cfg pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e .
	touch $@

$(VENV)/.test: $(VENV)/.base
	$(PY) -m pip install --quiet -e '.[test]'
	touch $@

$(VENV)/.video: $(VENV)/.base
	$(PY) -m pip install --quiet -e '.[video]'
	touch $@

$(VENV)/.docs: $(VENV)/.base
	$(PY) -m pip install --quiet -e '.[docs]'
	touch $@

$(VENV)/.bench: $(VENV)/.base
	$(PY) -m pip install --quiet -e '.[bench]'
	touch $@

venv: $(VENV)/.base

demo: $(VENV)/.video
	$(VENV)/bin/fastsdf demo

# The API reference, generated from the docstrings.
docs: $(VENV)/.docs
	$(PY) -m pdoc --docformat restructuredtext -o docs/api fastsdf

test: $(VENV)/.test
	$(PY) -m pytest -q

bench: $(VENV)/.bench
	$(PY) -m bench

bench-quick: $(VENV)/.bench
	$(PY) -m bench --quick

clean:
	rm -rf $(VENV) .cache build *.egg-info
