# Two commands on a fresh machine without ROS:
#   make demo   set up .venv and run the main job (the paper's Table III in the offline closed loop)
#   make test   set up the environments if missing and run lint, type checks and the whole suite,
#               on this Python with current numpy/scipy and on Python 3.12 with the versions ROS 2
#               Jazzy ships (numpy 1.26, scipy 1.11)

PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
# Python 3.12 for the Jazzy-version environment: python3.12 on PATH, else a pyenv install
JAZZY_PYTHON ?= $(shell for p in python3.12 $$(ls -d $${PYENV_ROOT:-$$HOME/.pyenv}/versions/3.12*/bin/python3.12 2>/dev/null); do $$p -c 'import sys; assert sys.version_info[:2] == (3, 12)' 2>/dev/null && { echo $$p; break; }; done)
JAZZY_VENV ?= .venv-jazzy
JAZZY_STAMP := $(JAZZY_VENV)/.installed

.PHONY: venv demo test check lint typecheck pytest test-jazzy bench soak tune clean

venv: $(STAMP)

$(STAMP): requirements.txt requirements-dev.txt setup.py package.xml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip setuptools wheel
	$(BIN)/python -m pip install --quiet -r requirements-dev.txt
	$(BIN)/python -m pip install --quiet --no-deps --no-build-isolation -e .
	touch $(STAMP)

$(JAZZY_STAMP): requirements-jazzy.txt setup.py package.xml
	@test -n "$(JAZZY_PYTHON)" || { echo 'make: no Python 3.12 found (set JAZZY_PYTHON=...)'; exit 1; }
	$(JAZZY_PYTHON) -m venv $(JAZZY_VENV)
	$(JAZZY_VENV)/bin/python -m pip install --quiet --upgrade pip setuptools wheel
	$(JAZZY_VENV)/bin/python -m pip install --quiet -r requirements-jazzy.txt
	$(JAZZY_VENV)/bin/python -m pip install --quiet --no-deps --no-build-isolation -e .
	touch $(JAZZY_STAMP)

demo: $(STAMP)
	$(BIN)/simulate --experiment table3

lint: $(STAMP)
	$(BIN)/ruff check piezo_stage_ros test launch setup.py

typecheck: $(STAMP)
	$(BIN)/mypy piezo_stage_ros launch/closed_loop.launch.py

pytest: $(STAMP)
	$(BIN)/python -m pytest -q

test-jazzy: $(JAZZY_STAMP)
	$(JAZZY_VENV)/bin/python -m pytest -q -p no:warnings

# the quick loop while developing: one environment
check: lint typecheck pytest

test: check test-jazzy

# one BLAS thread: idle BLAS threads spinning after a matrix call would count as CPU time
bench: $(STAMP)
	OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1 $(BIN)/benchmark --suite all

soak: $(STAMP)
	$(BIN)/soak

tune: $(STAMP)
	$(BIN)/tune

clean:
	rm -rf $(VENV) $(JAZZY_VENV) build install log *.egg-info
