# sync4d: two commands on a fresh machine.
#   make train [ARGS="sim=mpm_warp recon.bones=13"]   set up .venv and run the default scene
#   make test                                          set up .venv, lint and run the fast test lane
#   make test-slow                                     the slow lane (end-to-end runs; CI runs both)
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
export WARP_CACHE_PATH := $(CURDIR)/.warp_cache

.PHONY: venv train test test-slow bench clean browser models

venv: $(STAMP)

# MediaPipe's legacy BlazePose models (Apache-2.0), taken from the mediapipe 0.10.14 wheel (later releases
# download their models instead); recon=body_video and the video front end (person segmentation) run them under
# ai-edge-litert. No network at run time.
MODEL_DIR := models/mediapipe
POSE_MODELS := $(MODEL_DIR)/pose_landmark_full.tflite  # the detector and the licence come with it
models: $(POSE_MODELS)

$(POSE_MODELS):
	mkdir -p $(MODEL_DIR)/wheel
	$(PYTHON) -m pip download --quiet --no-deps --only-binary=:all: --python-version 3.11 \
		--platform manylinux2014_x86_64 mediapipe==0.10.14 -d $(MODEL_DIR)/wheel
	$(PYTHON) -c "import glob, sys, zipfile; z = zipfile.ZipFile(glob.glob('$(MODEL_DIR)/wheel/mediapipe-0.10.14-*.whl')[0]); \
	[open('$(MODEL_DIR)/' + dst, 'wb').write(z.read(src)) for src, dst in [ \
	('mediapipe/modules/pose_detection/pose_detection.tflite', 'pose_detection.tflite'), \
	('mediapipe/modules/pose_landmark/pose_landmark_full.tflite', 'pose_landmark_full.tflite'), \
	('mediapipe/modules/selfie_segmentation/selfie_segmentation.tflite', 'selfie_segmentation.tflite'), \
	('mediapipe-0.10.14.dist-info/LICENSE', 'LICENSE.mediapipe')]]"
	rm -rf $(MODEL_DIR)/wheel

# torch first, pinned to the CPU wheel this machine provides; a bare `torch` would pull a CUDA build.
$(STAMP): requirements.txt constraints.txt $(POSE_MODELS)
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet torch==2.13.0
	$(PY) -m pip install --quiet -c constraints.txt -r requirements.txt
	$(PY) -m pip install --quiet --no-deps -e .
	touch $(STAMP)

train: $(STAMP)
	$(PY) train.py $(ARGS)

# The fast lane (about 4 minutes idle here): lint, type check, then every test not marked slow.
test: $(STAMP)
	$(PY) -m ruff check sync4d sync4d_tools tests benchmarks plugins train.py
	$(PY) -m mypy
	$(PY) -m pytest -q -m "not slow" $(PYTEST_ARGS)

# The slow lane: end-to-end runs and long fits (CI runs it after the fast lane).
test-slow: $(STAMP)
	$(PY) -m pytest -q -m slow $(PYTEST_ARGS)

# The browser and glTF tests' tools: Debian's chromium (as root, through apt) and, from npm, playwright-core
# (drives that chromium; it downloads no browser), the Khronos glTF validator and three.js (tests/js/).
browser:
	command -v chromium >/dev/null || { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium; }
	cd tests/js && npm ci --no-audit --no-fund --silent

bench: $(STAMP)
	$(PY) benchmarks/mpm.py --json benchmarks/results/mpm.json
	$(PY) benchmarks/render.py --json benchmarks/results/render.json

clean:
	rm -rf $(VENV) .warp_cache
