# flexmbs: the README's two commands are `make demo` and `make test`.
VENV ?= .venv
PY := $(VENV)/bin/python
PYTEST_ARGS ?=

.PHONY: setup demo test docs bench clean

setup:
	@bash tools/setup.sh

demo: setup
	$(PY) -m flexmbs demo

# pytest exits with 5 when it collected no test: that fails here too.
test: setup
	$(PY) -m pytest -q $(PYTEST_ARGS)

# the documentation (docs/*.md) and the API reference from the docstrings, strict (a warning
# fails it): build/docs/index.html
docs: setup
	$(PY) -m mkdocs build --strict --quiet

# benchmarks (not tests): Exudyn is the peer of the work-precision study (the `bench` extra)
bench: setup
	$(PY) -m pip install -q exudyn || echo "exudyn could not be installed: work-precision runs flexmbs alone"
	$(PY) benchmarks/run.py $(BENCH_ARGS)

clean:
	rm -rf build $(VENV) .pytest_cache
