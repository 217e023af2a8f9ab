# Everyday commands. `make test` and `make demo` set the environment up first (scripts/setup_env.sh
# is idempotent and returns quickly once .venv is complete).
VENV   ?= .venv
PY     := $(VENV)/bin/python
RUFF   := $(VENV)/bin/ruff
PYTEST_ARGS ?= -q

# DDS traffic stays on this machine. tests/conftest.py also sets this and picks a random
# ROS_DOMAIN_ID for every pytest run, so parallel runs do not see each other.
export ROS_AUTOMATIC_DISCOVERY_RANGE := LOCALHOST

.PHONY: setup test lint demo clean

setup:
	bash scripts/setup_env.sh

lint: setup
	$(RUFF) check .

test: setup lint
	$(PY) -m pytest $(PYTEST_ARGS)

demo: setup
	$(VENV)/bin/sfm-ttr demo --overwrite

clean:
	rm -rf build install log .pytest_cache .ruff_cache *.egg-info sfm_ttr_demo
