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

bench: setup
	$(PY) benchmarks/run.py

clean:
	rm -rf build $(VENV) .pytest_cache
