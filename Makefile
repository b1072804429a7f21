# sync4d: two commands on a fresh machine.
#   make train [ARGS="sim=mpm_warp recon.bones=13"]   set up .venv and run the default scene
#   make test                                          set up .venv and run the test suite
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
export WARP_CACHE_PATH := $(CURDIR)/.warp_cache

.PHONY: venv train test bench clean

venv: $(STAMP)

# torch first, pinned to the CPU wheel this machine provides; a bare `torch` would pull a CUDA build.
$(STAMP): requirements.txt
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet torch==2.13.0
	$(PY) -m pip install --quiet -r requirements.txt
	$(PY) -m pip install --quiet --no-deps -e .
	touch $(STAMP)

train: $(STAMP)
	$(PY) train.py $(ARGS)

test: $(STAMP)
	$(PY) -m pytest -q $(PYTEST_ARGS)

bench: $(STAMP)
	$(PY) benchmarks/mpm.py --json benchmarks/results/mpm.json
	$(PY) benchmarks/render.py --json benchmarks/results/render.json

clean:
	rm -rf $(VENV) .warp_cache
