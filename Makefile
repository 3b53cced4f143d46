# The three commands of README: set-up, tests, main job.
VENV ?= .venv
PY := $(VENV)/bin/python

.PHONY: setup test test-fast doctor demo extension clean

setup:
	./setup.sh

test:
	$(PY) -m pytest -q

test-fast:
	$(PY) -m pytest -q -m "not slow"

doctor:
	$(VENV)/bin/unipixie doctor

demo:
	$(VENV)/bin/unipixie demo

extension:
	$(VENV)/bin/unipixie build-extension

clean:
	rm -rf dist build .pytest_cache
