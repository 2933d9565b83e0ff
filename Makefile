# PB3A: `make demo` and `make test` each create .venv from setup.cfg when it is missing.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test lint bench clean

$(STAMP): setup.cfg setup.py pyproject.toml pb3a/transport/_ringcore.c rave/_raycore.c
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test,ui,traffic]'
	@command -v dot >/dev/null || { [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null \
	  && (apt-get update -qq && apt-get install -y -qq graphviz >/dev/null) \
	  || echo "note: graphviz's 'dot' is missing; 'pb3a graph' will write DOT only"; }
	@# The manager's browser tests drive Debian's chromium with the pinned Playwright
	@# (its own browser download is not reachable from every machine).
	@command -v chromium >/dev/null || { [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null \
	  && (apt-get update -qq && apt-get install -y -qq chromium >/dev/null) \
	  || echo "note: chromium is missing; the manager's browser tests will be skipped"; }
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/pb3a run examples/pipeline.toml --for 5

test: $(STAMP)
	$(BIN)/ruff check pb3a rave agents tests examples bench scenarios setup.py
	@# Most tests run on three workers, a test file to each (pytest-xdist): they mostly
	@# wait for processes, links and deadlines, so a third keeps two cores busy. Those
	@# marked serial load the CPUs or time whole applications, and run alone after them.
	@# The slowest are listed at the end of each, to keep the suite near its 10 minutes.
	$(BIN)/python -m pytest -q -n 3 --dist loadfile -m "not serial" --durations=15
	$(BIN)/python -m pytest -q -m serial --durations=5

bench: $(STAMP)
	mkdir -p bench/results
	for b in local_link latency startup migration rave_world; do \
	  $(BIN)/python bench/$$b.py > bench/results/$$b.json || exit 1; done
	@echo "results in bench/results/*.json"

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache
