# Two commands do all the set-up on a fresh machine: `make demo` and `make test`.
# torch comes from the local CPU build pinned in constraints.txt (no CUDA downloads).
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
PIP_FLAGS ?= -q --disable-pip-version-check
STAMP := $(VENV)/.installed

.PHONY: venv demo test lint format bench clean

$(STAMP): pyproject.toml constraints.txt
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install $(PIP_FLAGS) -c constraints.txt -e ".[dev,sumo]"
	touch $(STAMP)

venv: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/trajeglish demo --out out/demo

lint: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

format: $(STAMP)
	$(VENV)/bin/ruff format .
	$(VENV)/bin/ruff check --fix .

test: lint
	$(PY) -m pytest -n 2 --durations=15 tests

bench: $(STAMP)
	$(VENV)/bin/trajeglish bench --out out/bench.json

clean:
	rm -rf $(VENV) out .pytest_cache .ruff_cache
