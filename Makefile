# polarshape — set-up, main job, tests.  `make run` and `make test` each create or reuse .venv and
# install everything needed (Debian packages via apt when root; otherwise they say what is missing).
SHELL := /bin/bash
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
PIP := $(PY) -m pip
STAMP := $(VENV)/.polarshape-installed
OUT ?= results/default

.PHONY: run test test-fast bench setup clean-venv

$(PY):
	$(PYTHON) -m venv $(VENV)

# torch first, and only the wheel pinned here (a CPU build is on disk on our machines), so that pip
# never resolves a multi-GB CUDA build; then polarshape with its extras.
$(STAMP): pyproject.toml scripts/install-system-deps.sh | $(PY)
	bash scripts/install-system-deps.sh
	$(PY) -c "import torch" 2>/dev/null || $(PIP) install "torch==2.13.0"
	$(PIP) install -e ".[dev]"
	$(PIP) install -e ".[aravis]" || echo "make: WARNING: the 'aravis' extra (PyGObject) did not install: the Aravis camera backend is unavailable (see scripts/install-system-deps.sh)"
	$(PIP) install -e ".[cluster]" || echo "make: WARNING: the 'cluster' extra (Ray) did not install: polarshape batch --engine ray is unavailable (--engine local works)"
	touch $(STAMP)

setup: $(STAMP)

run: $(STAMP)
	$(VENV)/bin/polarshape run configs/default.yaml --out $(OUT) --overwrite

test: $(STAMP)
	$(PY) -m pytest tests -q

test-fast: $(STAMP)
	$(PY) -m pytest tests -q -m "not slow"

bench: $(STAMP)
	$(PY) benchmarks/brdf_eval.py

clean-venv:
	rm -rf $(VENV)
