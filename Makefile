# fpp-graph: `make demo` and `make test` set up everything they need on a fresh machine.
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.fpp-graph-installed

.PHONY: setup demo test lint bench clean

$(STAMP): pyproject.toml scripts/bootstrap.sh
	bash scripts/bootstrap.sh dev,eval,dask
	touch $@

setup: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/fpp-slam demo

test: $(STAMP)
	$(PY) -m pytest -q

lint: $(STAMP)
	$(VENV)/bin/ruff check fpp_graph frontend tests scripts

bench: $(STAMP)
	$(PY) scripts/bench_cli_startup.py

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache .mypy_cache
