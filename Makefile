# Everything runs inside a local virtual environment (.venv) created on first use; nothing
# depends on what is installed elsewhere on the machine.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
# Kernels compiled by the demo, the tests, the benchmarks and the user's own scripts share one
# cache (fastsdf's default, ~/.cache/fastsdf, or $FASTSDF_CACHE_DIR): its files are named by the
# hash of their source, so a kernel compiled once serves every later run.
export MPLBACKEND ?= Agg

.PHONY: venv demo docs lint test bench bench-quick clean

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

# The demo needs the video extra; the README's blocks need nothing more (a block that imports
# another extra's module names it: tests/test_readme.py checks that). It ends by compiling the
# kernels of the README's grain and image blocks, so that pasting them later loads them.
demo: $(VENV)/.video
	$(VENV)/bin/fastsdf demo

# The documentation site (docs/, Sphinx + MyST + myst-nb + sphinx-gallery; docs/conf.py says
# why): the guide, the notebook executed, the gallery executed from examples/ at small sizes and
# the API reference of the public surface. Warnings are errors.
docs: $(VENV)/.docs
	$(PY) -m sphinx -b html -W --keep-going -q docs docs/_build/html
	@echo "documentation: docs/_build/html/index.html"

# The habits the tests do not check: ruff's lint rules (pyproject [tool.ruff]), mypy over the
# package (pyproject [tool.mypy]) and the layer contract (pyproject [tool.importlinter]).
lint: $(VENV)/.test
	$(VENV)/bin/ruff check fastsdf tests bench examples
	$(VENV)/bin/ruff format --check fastsdf tests bench examples
	$(VENV)/bin/mypy fastsdf
	$(VENV)/bin/lint-imports

# One pytest worker per core (pytest-xdist): most of the suite's time is numba compiling the
# scenes of the tests, one core per compile. Tests are grouped by file, so a file's scenes are
# compiled by one worker; workers share the kernel cache (safe under concurrent processes).
# The lint runs first: it takes seconds, the suite minutes.
test: lint
	$(PY) -m pytest -q -n auto --dist loadfile

bench: $(VENV)/.bench
	$(PY) -m bench

bench-quick: $(VENV)/.bench
	$(PY) -m bench --quick

clean:
	rm -rf $(VENV) .cache build *.egg-info
