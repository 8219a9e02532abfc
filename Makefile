# Two entry points (see README "Quick start"):
#   make demo   set up .venv and run the built-in synthetic sample end to end
#   make test   set up .venv, lint (ruff check) and run the test suite (slowest 25 timed)
#   make test-fast   the same without the end-to-end runs marked slow
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.recon-installed

.PHONY: setup demo test test-fast lint bench clean

setup: $(STAMP)

$(STAMP): pyproject.toml scripts/setup.sh
	bash scripts/setup.sh $(VENV)
	touch $(STAMP)

demo: setup
	$(VENV)/bin/recon demo

test: setup
	$(VENV)/bin/ruff check .
	$(PY) -m pytest -q --durations=25

# Everything but the end-to-end runs marked slow: a few minutes instead of the whole suite's.
test-fast: setup
	$(VENV)/bin/ruff check .
	$(PY) -m pytest -q -m "not slow"

lint: setup
	$(VENV)/bin/ruff check .

bench: setup
	$(PY) benchmarks/medea_synthetic.py

clean:
	rm -rf $(VENV) demo_out
