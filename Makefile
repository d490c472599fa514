# Two commands on a fresh machine without ROS:
#   make demo   set up .venv and run the main job (the paper's Table III in the offline closed loop)
#   make test   set up the environments if missing and run lint, type checks and the whole suite,
#               on this Python with current numpy/scipy and on Python 3.12 with the versions ROS 2
#               Jazzy ships (numpy 1.26, scipy 1.11)

# Python 3.11 for .venv, the version requirements-lock.txt was resolved on: python3.11 on PATH,
# else python3 (the lock may then not install: `make lock PYTHON=...` resolves one for it)
PYTHON ?= $(shell command -v python3.11 >/dev/null 2>&1 && echo python3.11 || echo python3)
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
# Python 3.12 for the Jazzy-version environment: python3.12 on PATH, else a pyenv install
JAZZY_PYTHON ?= $(shell for p in python3.12 $$(ls -d $${PYENV_ROOT:-$$HOME/.pyenv}/versions/3.12*/bin/python3.12 2>/dev/null); do $$p -c 'import sys; assert sys.version_info[:2] == (3, 12)' 2>/dev/null && { echo $$p; break; }; done)
JAZZY_VENV ?= .venv-jazzy
JAZZY_STAMP := $(JAZZY_VENV)/.installed
# Every package of each environment, transitive ones, pip, setuptools and wheel included, pinned:
# `make lock` writes them, the venvs install exactly them (no resolver at install time).
LOCK := requirements-lock.txt
JAZZY_LOCK := requirements-jazzy-lock.txt

.PHONY: venv demo test check lint typecheck pytest test-jazzy test-random test-matrix lock bench soak
.PHONY: tune results clean

venv: $(STAMP)

# Install the lock as it is, with --no-deps: nothing is resolved on the new machine, and
# `pip check` fails if the lock misses a dependency. A changed lock rebuilds the venv from scratch,
# so a package dropped from the lock is gone too.
define install_lock
	$(1) -m venv --clear $(2)
	$(2)/bin/python -m pip install --quiet --no-deps -r $(3)
	$(2)/bin/python -m pip check
	$(2)/bin/python -m pip install --quiet --no-deps --no-build-isolation -e .
	touch $(2)/.installed
endef

$(STAMP): $(LOCK) requirements.txt requirements-dev.txt setup.py package.xml
	$(call install_lock,$(PYTHON),$(VENV),$(LOCK))

$(JAZZY_STAMP): $(JAZZY_LOCK) requirements.txt requirements-jazzy.txt setup.py package.xml
	@test -n "$(JAZZY_PYTHON)" || { echo 'make: no Python 3.12 found (set JAZZY_PYTHON=...)'; exit 1; }
	$(call install_lock,$(JAZZY_PYTHON),$(JAZZY_VENV),$(JAZZY_LOCK))

# Refresh the locks on purpose: resolve each requirements file afresh in a throw-away venv and
# pin what pip installed. Commit the result; test/test_requirements_lock.py (run by `make test`)
# fails when a requirement and its lock disagree.
define write_lock
	rm -rf .venv-lock
	$(1) -m venv .venv-lock
	.venv-lock/bin/python -m pip install --quiet --upgrade pip setuptools wheel
	.venv-lock/bin/python -m pip install --quiet -r $(2)
	{ echo '# Every package of the environment from $(2), pinned; written by `make lock`, do not edit.'; \
	  echo "# Resolved on Python $$(.venv-lock/bin/python -c 'import platform; print(platform.python_version(), platform.system(), platform.machine())')."; \
	  .venv-lock/bin/python -m pip freeze --all | LC_ALL=C sort -f; } > $(3)
	rm -rf .venv-lock
endef

lock:
	@test -n "$(JAZZY_PYTHON)" || { echo 'make: no Python 3.12 found (set JAZZY_PYTHON=...)'; exit 1; }
	$(call write_lock,$(PYTHON),requirements-dev.txt,$(LOCK))
	$(call write_lock,$(JAZZY_PYTHON),requirements-jazzy.txt,$(JAZZY_LOCK))

demo: $(STAMP)
	$(BIN)/simulate --experiment table3

lint: $(STAMP)
	$(BIN)/ruff check piezo_stage_ros test launch setup.py

typecheck: $(STAMP)
	$(BIN)/mypy piezo_stage_ros launch/closed_loop.launch.py launch/commission.launch.py

pytest: $(STAMP)
	$(BIN)/python -m pytest -q

test-jazzy: $(JAZZY_STAMP)
	$(JAZZY_VENV)/bin/python -m pytest -q -p no:warnings

# The whole suite in both environments under several OpenBLAS kernels, thread counts and numpy
# SIMD levels (docs/explanation/testing.md); not part of `make test`: ~30 runs of the suite.
test-matrix: $(STAMP) $(JAZZY_STAMP)
	@mkdir -p out/test-matrix
	bash test/matrix.sh | tee out/test-matrix/table.md

# The property tests with new random examples on each run (test/conftest.py: profile `random`);
# `make test` runs them derandomized (profile `ci`), so a landing passes or fails reproducibly.
# A counterexample found here goes into the test as an @example.
test-random: $(STAMP)
	HYPOTHESIS_PROFILE=random $(BIN)/python -m pytest -q test/test_commands_ahead.py \
		test/test_controllers.py test/test_feedforward.py test/test_safety.py

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

# rewrite the generated sections of docs/results.md with this machine's figures
results: $(STAMP)
	OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1 $(BIN)/python -m piezo_stage_ros.results

clean:
	rm -rf $(VENV) $(JAZZY_VENV) .venv-lock build install log *.egg-info
