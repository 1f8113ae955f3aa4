# fpp-graph: `make demo` and `make test` set up everything they need on a fresh machine.
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.fpp-graph-installed
DEMO_STAMP := $(VENV)/.fpp-graph-demo-installed

.PHONY: setup demo test lint bench report clean

$(STAMP): pyproject.toml scripts/bootstrap.sh
	bash scripts/bootstrap.sh dev,eval,dask
	touch $@

# The demo needs the eval extra only (evo scores it); a venv already set up for the tests has it.
$(DEMO_STAMP): pyproject.toml scripts/bootstrap.sh
	if [ $(STAMP) -nt pyproject.toml ] && [ $(STAMP) -nt scripts/bootstrap.sh ]; then :; else bash scripts/bootstrap.sh eval; fi
	touch $@

setup: $(STAMP)

demo: $(DEMO_STAMP)
	$(VENV)/bin/fpp-slam demo

test: $(STAMP)
	$(PY) -m pytest -q

lint: $(STAMP)
	$(VENV)/bin/ruff check fpp_graph frontend tests scripts

bench: $(STAMP)
	$(PY) scripts/bench_cli_startup.py

# every benchmark script run, docs/benchmarks.md and README.md's figures table written from their output
# (tens of minutes; `make report ARGS="--only demo"` for one section, `--list` for the names)
report: $(STAMP)
	$(PY) -m scripts.write_benchmarks $(ARGS)

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache .mypy_cache
