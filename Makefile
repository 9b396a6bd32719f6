# armourcam — the two commands of the README are the contract:
#   make demo   sets up .venv and runs the ROS graph on the bundled bags, report in out/
#   make test   sets up .venv and runs lint, types and the whole test suite
PY      ?= python3
VENV    := .venv
VPY     := $(VENV)/bin/python
STAMP   := $(VENV)/.installed

.PHONY: setup demo test lint typecheck pytest bench bags clean

setup: $(STAMP)

# Reinstall only when the project's declared dependencies or its compiled kernels change; the
# package itself is editable (the kernels are built in place, beside their modules).
$(STAMP): pyproject.toml setup.py $(wildcard src/fiducial_detector/_*_kernel.c)
	test -x $(VPY) || $(PY) -m venv $(VENV)
	$(VPY) -m pip install -q --upgrade pip
	$(VPY) -m pip install -q -e ".[dev]"
	touch $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/armourcam demo --out out

lint: $(STAMP)
	$(VENV)/bin/ruff check src tests benchmarks setup.py
	$(VENV)/bin/ruff format --check src tests benchmarks setup.py

typecheck: $(STAMP)
	$(VENV)/bin/mypy

pytest: $(STAMP)
	$(VPY) -m pytest -q

test: lint typecheck pytest

bench: $(STAMP)
	$(VPY) -m benchmarks.run_all

bags: $(STAMP)
	$(VENV)/bin/armourcam make-bags --out bags

clean:
	rm -rf $(VENV) out .pytest_cache .mypy_cache .ruff_cache build src/fiducial_detector/_*_kernel*.so
