# fdi_ros: the README's two commands are `make demo` and `make test`.
# Both set up everything they need on a fresh machine (scripts/setup.sh, idempotent).
SHELL := /bin/bash
VENV  := $(CURDIR)/.venv
# Loopback-only DDS and a per-run domain id, for every run.
export ROS_AUTOMATIC_DISCOVERY_RANGE := LOCALHOST
export ROS_DOMAIN_ID ?= $(shell echo $$(( ($$$$ % 100) + 100 )))
export PYTHONUNBUFFERED := 1

.PHONY: setup demo test test-fast bench clean
setup:
	@bash scripts/setup.sh

demo: setup
	$(VENV)/bin/fdi-ros demo --out out/demo

test: setup
	bash scripts/test.sh

test-fast: setup
	$(VENV)/bin/python -m pytest tests -m "not graph and not slow"

bench: setup
	$(VENV)/bin/fdi-ros bench all --json

clean:
	rm -rf build out .pytest_cache
