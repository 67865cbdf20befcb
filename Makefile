# roco-env: `make demo` runs the main job, `make test` runs the suite.
# Both create .venv on first use and reuse it afterwards.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
PIP := $(PY) -m pip install --quiet --disable-pip-version-check
# This machine's CPU build of torch, found on disk; installing it first keeps
# pip from pulling a multi-GB CUDA build to satisfy the range in pyproject.toml.
TORCH_PIN ?= torch==2.13.0

.PHONY: demo test bench lint wheel-check clean

$(PY):
	$(PYTHON) -m venv $(VENV)

$(VENV)/.base-installed: pyproject.toml | $(PY)
	$(PIP) $(TORCH_PIN)
	$(PIP) -e .
	touch $@

$(VENV)/.dev-installed: $(VENV)/.base-installed
	$(PIP) -e '.[dev]'
	touch $@

# A fresh sweep each time: a resumed one would show results of older code.
demo: $(VENV)/.base-installed
	rm -rf runs/demo
	$(VENV)/bin/roco-env compare --demo

test: $(VENV)/.dev-installed
	$(PY) -m pytest

# The benchmarks compare against shapely loops, a dev extra.
bench: $(VENV)/.dev-installed
	$(PY) -m roco_env.benchmarks

lint: $(VENV)/.dev-installed
	$(VENV)/bin/ruff check roco_env tests examples baselines

# Build the wheel, install it into a fresh environment (the CPU torch first, as
# above) and step every shipped scenario from it, outside the checkout.
WHEEL_DIR ?= build/wheel-check
wheel-check: $(VENV)/.base-installed
	rm -rf $(WHEEL_DIR)
	$(PY) -m pip wheel --quiet --disable-pip-version-check --no-deps -w $(WHEEL_DIR)/dist .
	$(PYTHON) -m venv $(WHEEL_DIR)/venv
	$(WHEEL_DIR)/venv/bin/python -m pip install --quiet --disable-pip-version-check $(TORCH_PIN)
	$(WHEEL_DIR)/venv/bin/python -m pip install --quiet --disable-pip-version-check \
		$(WHEEL_DIR)/dist/roco_env-*.whl
	cd $(WHEEL_DIR) && venv/bin/python -I $(CURDIR)/.ci/wheel_smoke.py

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache
