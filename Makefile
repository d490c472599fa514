# Two commands on a fresh machine without ROS:
#   make demo   set up .venv and run the main job (a closed-loop run of the paper's stage)
#   make test   set up .venv if missing and run lint, type checks and the whole test suite

PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: venv demo test lint typecheck pytest bench soak clean

venv: $(STAMP)

$(STAMP): requirements.txt requirements-dev.txt setup.py package.xml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip setuptools wheel
	$(BIN)/python -m pip install --quiet -r requirements-dev.txt
	$(BIN)/python -m pip install --quiet --no-deps --no-build-isolation -e .
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/simulate --experiment table3

lint: $(STAMP)
	$(BIN)/ruff check piezo_stage_ros test launch setup.py

typecheck: $(STAMP)
	$(BIN)/mypy piezo_stage_ros/core piezo_stage_ros/analysis

pytest: $(STAMP)
	$(BIN)/python -m pytest -q

test: lint typecheck pytest

bench: $(STAMP)
	$(BIN)/benchmark

soak: $(STAMP)
	$(BIN)/soak

clean:
	rm -rf $(VENV) build install log *.egg-info
