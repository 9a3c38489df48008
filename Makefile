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

.PHONY: demo test lint bench venv clean ros2-env

venv: $(STAMP)

$(STAMP): pyproject.toml
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test,dev,cluster,learn,ros2,view]'
	@touch $(STAMP)

demo: $(STAMP)
	$(BIN)/semfleet demo --force

# Two phases: everything but the `serial` tests spread over the cores, then those alone
# (tests/conftest.py says which and why). Each phase fails the target on a failure or on no test.
PYTEST_JOBS ?= auto
test: $(STAMP) ros2-env
	$(BIN)/python -m pytest -q -n $(PYTEST_JOBS) --dist worksteal -m "not serial"
	$(BIN)/python -m pytest -q -m serial

# ROS 2 itself (rclpy and the message packages, the PyPI `ros-*` wheels of ROS 2 Kilted) in a
# virtual environment of its own, for tests/agents/test_ros2_reference.py: the test reads
# semfleet's messages with it. Best effort: where the wheels cannot be installed those tests skip
# with a one-line reason.
ROS2_VENV  := .venv-ros2
ROS2_STAMP := $(ROS2_VENV)/.installed
ROS2_WHEELS := ros-rclpy ros-rmw-fastrtps-cpp ros-nav-msgs ros-geometry-msgs ros-visualization-msgs
ros2-env:
	@test -e $(ROS2_STAMP) || { $(PYTHON) -m venv $(ROS2_VENV) \
	  && $(ROS2_VENV)/bin/python -m pip install --quiet $(ROS2_WHEELS) \
	  && touch $(ROS2_STAMP); } \
	  || echo "ros2-env: the ROS 2 wheels did not install; the ROS 2 reference tests will skip"

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/mypy estimator protocol sim agents deploy bench

bench: $(STAMP)
	$(BIN)/python -m bench

clean:
	rm -rf $(VENV) $(ROS2_VENV) build *.egg-info .pytest_cache .mypy_cache .ruff_cache
