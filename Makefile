# psl: `make demo` and `make test` set up whatever is missing first (scripts/setup is
# idempotent and takes seconds when nothing changed).
SHELL := /bin/bash
ENV := source scripts/env.sh

.PHONY: setup demo test test-robot bench clean

setup:
	@bash scripts/setup

demo: setup
	@$(ENV) && psl demo

# two workers (pytest-xdist), a file at a time each, each on its own ROS domain (conftest.py);
# the order of the files and of the tests in them is shuffled (pytest-randomly)
test: setup
	@$(ENV) && python -m pytest -n 2 --dist loadfile

# psl against a robot process it does not simulate, on the wall clock (needs idle cores)
test-robot: setup
	@$(ENV) && python -m pytest -p no:randomly -m robot_on_the_wall_clock test/test_external_robot.py

bench: setup
	@$(ENV) && psl bench graph

clean:
	rm -rf build install log .venv demo
