# The project's commands. From a fresh clone, `make test` and `make demo` set up what
# they need: a .venv at the repo root from requirements.txt, then the colcon build.
SHELL := /bin/bash
.SHELLFLAGS := -e -o pipefail -c
PYTHON ?= python3
VENV := .venv
VENV_STAMP := $(VENV)/.installed
BUILD_STAMP := ros2_ws/install/.built
SOURCES := $(shell find src -type f -not -path '*/__pycache__/*' -not -name '*.pyc')
# Node processes in tests and the demo talk only on this machine.
export ROS_AUTOMATIC_DISCOVERY_RANGE ?= LOCALHOST
SCENARIO ?= default
PYTEST_ARGS ?=

.PHONY: setup build lint params test test-unit demo bench clean distclean

setup: $(VENV_STAMP)

$(VENV_STAMP): requirements.txt
	@echo "== setting up $(VENV) from requirements.txt"
	test -x $(VENV)/bin/python || $(PYTHON) -m venv $(VENV)
	$(VENV)/bin/pip install --quiet --disable-pip-version-check -r requirements.txt
	touch $@

build: $(BUILD_STAMP)

$(BUILD_STAMP): $(VENV_STAMP) $(SOURCES)
	@echo "== building ros2_ws"
	source $(VENV)/bin/activate && cd ros2_ws && \
	  if ! colcon build --event-handlers console_direct- > build.log 2>&1; then \
	    cat build.log; echo "colcon build failed (ros2_ws/build.log)"; exit 1; fi
	tail -n 2 ros2_ws/build.log
	touch $@

# ruff's rules and format (ruff.toml), mypy (mypy.ini: vgm_common and every core module
# fully typed) and the generated parameter lists up to date; `make test` runs it first. `ruff format src tests bench scripts`
# formats what it reports.
lint: $(VENV_STAMP)
	$(VENV)/bin/ruff check --output-format concise src tests bench scripts
	$(VENV)/bin/ruff format --check src tests bench scripts
	$(VENV)/bin/mypy
	$(VENV)/bin/python scripts/generate_params.py --check

# params files and README parameter tables, written from the nodes' declarations
params: $(VENV_STAMP)
	$(VENV)/bin/python scripts/generate_params.py

test: lint build
	source ros2_ws/install/setup.bash && \
	  $(VENV)/bin/python -m pytest tests $(PYTEST_ARGS)

# the quick loop while editing a core: no node processes (about a minute)
test-unit: lint build
	source ros2_ws/install/setup.bash && \
	  $(VENV)/bin/python -m pytest tests -m unit $(PYTEST_ARGS)

demo: build
	source ros2_ws/install/setup.bash && \
	  $(VENV)/bin/python scripts/demo.py --scenario $(SCENARIO)

bench: build
	source ros2_ws/install/setup.bash && \
	  $(VENV)/bin/python bench/run_all.py

clean:
	rm -rf ros2_ws/build ros2_ws/install ros2_ws/log
	find src tests bench scripts -name __pycache__ -type d -prune -exec rm -rf {} +

distclean: clean
	rm -rf $(VENV)
