# Two commands do everything: `make run` (the whole pipeline at scale=quick) and `make test`.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
EXPERIMENT ?= quick

.PHONY: setup run test lint bench preview mutation clean-venv

setup: $(VENV)/.installed

$(VENV)/.installed: requirements.lock requirements-dev.lock pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q -r requirements-dev.lock
	$(PY) -m pip install -q --no-deps -e .
	touch $@

run: setup
	$(PY) -m worldmodel.pipeline experiment=$(EXPERIMENT) scale=quick

# Two workers, one per core; a file's tests stay on one worker, so module-scoped fixtures (the smoke pipeline) are
# built once.
test: setup lint
	$(PY) -m pytest -q -n 2 --dist loadfile

lint: setup
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

bench: setup
	$(PY) -m benchmarks.run

# Mutation testing of the core numeric modules (tests/README.md): not part of CI, 5-7 minutes on 2 cores.
mutation: setup
	$(PY) -m pip install -q -r requirements-mutation.lock
	$(PY) tests/mutation.py

preview: setup
	$(PY) -m envs.preview --out runs/preview/episode.gif

clean-venv:
	rm -rf $(VENV)
