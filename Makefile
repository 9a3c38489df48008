# Every target bootstraps .venv with the machine's python3 when it is missing or older than
# pyproject.toml, so a fresh clone needs nothing but `make demo` or `make test`.
PYTHON ?= python3
# The estimators' matrices are tiny: a multi-threaded BLAS only spins against Python (measured 2.6×
# slower on 2 cores). A value already set in the environment wins.
export OPENBLAS_NUM_THREADS ?= 1
export OMP_NUM_THREADS ?= 1
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: demo test lint bench venv clean

venv: $(STAMP)

$(STAMP): pyproject.toml
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test,dev,cluster,learn,ros2,view]'
	@touch $(STAMP)

demo: $(STAMP)
	$(BIN)/semfleet demo

# Two phases: everything but the `serial` tests spread over the cores, then those alone
# (tests/conftest.py says which and why). Each phase fails the target on a failure or on no test.
PYTEST_JOBS ?= auto
test: $(STAMP)
	$(BIN)/python -m pytest -q -n $(PYTEST_JOBS) --dist worksteal -m "not serial"
	$(BIN)/python -m pytest -q -m serial

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/mypy estimator protocol sim agents deploy bench

bench: $(STAMP)
	$(BIN)/python -m bench

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache .mypy_cache .ruff_cache
