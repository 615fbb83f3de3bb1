# flexmbs: the README's two commands are `make demo` and `make test`.
VENV ?= .venv
PY := $(VENV)/bin/python
PYTEST_ARGS ?=

.PHONY: setup demo test bench clean

setup:
	@bash tools/setup.sh

demo: setup
	$(PY) -m flexmbs demo

# pytest exits with 5 when it collected no test: that fails here too.
test: setup
	$(PY) -m pytest -q $(PYTEST_ARGS)

# benchmarks (not tests): Exudyn is the peer of the work-precision study (the `bench` extra)
bench: setup
	$(PY) -m pip install -q exudyn || echo "exudyn could not be installed: work-precision runs flexmbs alone"
	$(PY) benchmarks/run.py $(BENCH_ARGS)

clean:
	rm -rf build $(VENV) .pytest_cache
