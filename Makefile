# fdi_ros: the README's two commands are `make demo` and `make test`.
# Both set up everything they need on a fresh machine (scripts/setup.sh, idempotent).
SHELL := /bin/bash
VENV  := $(CURDIR)/.venv
# Loopback-only DDS and a per-run domain id, for every run.
export ROS_AUTOMATIC_DISCOVERY_RANGE := LOCALHOST
export ROS_DOMAIN_ID ?= $(shell echo $$(( ($$$$ % 100) + 100 )))
export PYTHONUNBUFFERED := 1

.PHONY: setup banks demo test test-fast bench clean
setup:
	@bash scripts/setup.sh

demo: setup
	$(VENV)/bin/fdi-ros demo --out out/demo

# The models the tests' graphs use, identified by the product's own `fdi-ros build-bank` when
# missing: the diesel and turbofan banks side by side (each also spreads its own independent
# fits over the cores), so the one-off identification overlaps instead of queueing.
banks: setup
	@$(VENV)/bin/fdi-ros build-bank config/diesel.yaml --no-progress & d=$$!; \
	 $(VENV)/bin/fdi-ros build-bank config/turbofan.yaml --no-progress & t=$$!; \
	 wait $$d; a=$$?; wait $$t; b=$$?; [ $$a -eq 0 ] && [ $$b -eq 0 ]

test: banks
	$(VENV)/bin/python -m pytest tests

test-fast: setup
	$(VENV)/bin/python -m pytest tests -m "not graph and not slow"

bench: setup
	$(VENV)/bin/fdi-ros bench all --json

clean:
	rm -rf build out .pytest_cache
