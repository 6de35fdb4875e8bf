# psl: `make demo` and `make test` set up whatever is missing first (scripts/setup is
# idempotent and takes seconds when nothing changed).
SHELL := /bin/bash
ENV := source scripts/env.sh
ROBOT_TESTS := python -m pytest -p no:randomly -m robot_on_the_wall_clock test

.PHONY: setup demo test test-robot bench clean

setup:
	@bash scripts/setup

demo: setup
	@$(ENV) && psl demo

# two workers (pytest-xdist), a file at a time each, each on its own ROS domain (conftest.py);
# the order of the files and of the tests in them is shuffled (pytest-randomly); then psl
# against robot processes it does not simulate, on the wall clock, alone: a Python robot at
# 500 Hz beside a busy core answers late (pytest.ini)
test: setup
	@$(ENV) && python -m pytest -n 2 --dist loadfile && $(ROBOT_TESTS)

# only the tests against a robot process on the wall clock
test-robot: setup
	@$(ENV) && $(ROBOT_TESTS)

bench: setup
	@$(ENV) && psl bench graph

clean:
	rm -rf build install log .venv demo
