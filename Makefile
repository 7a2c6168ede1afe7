# Entry points (see README): `make demo`, `make test` (the fast tier) and `make test-all`
# (everything, what CI runs). Each installs first.
VENV ?= .venv
PY := $(VENV)/bin/python

.PHONY: install demo test test-all lint bench

install: $(VENV)/.installed

$(VENV)/.installed: pyproject.toml scripts/install.sh
	bash scripts/install.sh $(VENV)

demo: install
	$(VENV)/bin/sine demo --out runs/demo

test: install
	$(PY) -m pytest -q -m "not slow" tests

test-all: install
	$(PY) -m pytest -q tests

lint: install
	$(VENV)/bin/ruff check . && $(VENV)/bin/ruff format --check .
