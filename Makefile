# psl: `make demo` and `make test` set up whatever is missing first (scripts/setup is
# idempotent and takes seconds when nothing changed).
SHELL := /bin/bash
ENV := source scripts/env.sh

.PHONY: setup demo test bench clean

setup:
	@bash scripts/setup

demo: setup
	@$(ENV) && psl demo

test: setup
	@$(ENV) && python -m pytest

bench: setup
	@$(ENV) && psl bench graph

clean:
	rm -rf build install log .venv demo
