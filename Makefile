# Set-up is automatic: every target below first runs scripts/setup.sh, which
# creates .venv (unless a virtual environment is active), installs the CPU
# wheel of torch when torch is missing, then the project with its train, onnx, fmu, casadi, fleet and dev extras.
# A second run reuses the environment and starts quickly.
SHELL := /bin/bash
PYTHON := $(shell bash scripts/setup.sh --print-python)

.PHONY: setup test test-all reproduce lint bench clean

setup:
	@bash scripts/setup.sh

test: setup
	@$(PYTHON) -m pytest -m "not slow" ; rc=$$?; if [ $$rc -eq 5 ]; then echo "no tests collected"; exit 0; fi; exit $$rc

test-all: setup
	@$(PYTHON) -m pytest ; rc=$$?; if [ $$rc -eq 5 ]; then exit 0; fi; exit $$rc

reproduce: setup
	@$(PYTHON) -m torchhys.reproduce

lint: setup
	@$(PYTHON) -m ruff check .

bench: setup
	@$(PYTHON) benchmarks/backlash.py

clean:
	rm -rf runs .pytest_cache build *.egg-info
