# Two-command quick start: `make demo` and `make test` each create/refresh .venv and run.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
PIP    := $(PY) -m pip
STAMP  := $(VENV)/.installed

.PHONY: install test test-all demo bench train lint docs clean view-check

$(PY):
	$(PYTHON) -m venv $(VENV)
	$(PIP) install -q --upgrade pip

# Reinstall when the project's metadata or pins change.
$(STAMP): $(PY) pyproject.toml constraints.txt
	$(PIP) install -q -c constraints.txt torch==2.13.0
	$(PIP) install -q -c constraints.txt -e ".[dev,cli,plot,rl,tune,docs,viz]"
	$(PY) -m diffkin.kernels  # the fused C kernel, built once here (without a compiler: torch only)
	touch $(STAMP)

install: $(STAMP)

test: $(STAMP)
	$(PY) -m ruff check .
	$(PY) -m pytest

# Everything, the extended reference sweeps and long end-to-end runs included.
test-all: $(STAMP)
	$(PY) -m ruff check .
	$(PY) -m pytest -m "extended or not extended"

demo: $(STAMP)
	$(VENV)/bin/diffkin demo

bench: $(STAMP)
	$(PIP) install -q -c constraints.txt -e ".[dev,rl,bench]"
	$(PY) -m benchmarks.run all

train: $(STAMP)
	$(PY) -m diffkin.training.train --config configs/sac.yaml --env diffkin/Reach-v0 --variant cartesian

# The documentation site into site/ (MkDocs-Material + mkdocstrings; warnings fail the build).
docs: $(STAMP)
	NO_MKDOCS_2_WARNING=1 $(PY) -m mkdocs build --strict -d site

# `diffkin view --robot panda` in headless Chromium (the system's: apt-get install chromium; no
# `playwright install`): saves docs/img/viewer.png and checks it shows the robot.
view-check: $(STAMP)
	$(PIP) install -q -c constraints.txt -e ".[viz]" playwright
	$(PY) scripts/view_check.py

lint: $(STAMP)
	$(PY) -m ruff check .

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache site
