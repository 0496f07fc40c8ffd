# Two entry points for a fresh Debian/Ubuntu machine with Python 3.11:
#   make demo   installs what the demo needs and runs it
#   make test   installs the test dependencies and runs the whole suite (what CI runs)
# and, for local work, make test-fast: the suite without the tests marked slow (> ~2.5 s each).
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin

.PHONY: demo test test-fast test-serving system-deps venv lint clean models fused-models

# Mitsuba's LLVM backend needs libllvm19 (LLVM 15/16 abort inside mi.render with "Cannot select: fminimum").
system-deps:
	@if ls /usr/lib/*/libLLVM*19* >/dev/null 2>&1; then :; \
	elif [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	  apt-get install -y -q libllvm19 >/dev/null || (apt-get update -q >/dev/null && apt-get install -y -q libllvm19 >/dev/null); \
	elif command -v sudo >/dev/null && command -v apt-get >/dev/null; then \
	  sudo apt-get install -y -q libllvm19 >/dev/null; \
	else \
	  echo "WARNING: libllvm19 is not installed and cannot be installed here; rendering (Mitsuba llvm_ad_rgb) will fail." >&2; \
	fi

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip

venv: $(BIN)/python

demo: venv
	$(BIN)/pip install -q -e '.[serve]'
	$(BIN)/python examples/demo.py

# The Dockerfile installs exactly '.[serve]': the service tests also run in a fresh venv holding only that (plus
# the test runner), so a serving host that lacks torch and mitsuba is what gets tested.
SERVE_VENV ?= .venv-serve

test: venv system-deps
	$(BIN)/pip install -q -e '.[test]'
	$(BIN)/ruff check .
	$(BIN)/pytest -q -n 2 --timeout=900
	$(MAKE) test-serving

# Markers (pyproject.toml): slow (> ~2.5 s of CPU per test, measured with --durations), render (runs Mitsuba),
# train (trains a torch model). CI runs everything; locally e.g. -m "not slow", -m "not render and not train".
test-fast: venv system-deps
	$(BIN)/pip install -q -e '.[test]'
	$(BIN)/pytest -q -n 2 --timeout=900 -m "not slow"

test-serving:
	rm -rf $(SERVE_VENV)
	$(PYTHON) -m venv $(SERVE_VENV)
	$(SERVE_VENV)/bin/pip install -q --upgrade pip
	$(SERVE_VENV)/bin/pip install -q '.[serve]' pytest pytest-timeout pytest-xdist schemathesis
	$(SERVE_VENV)/bin/python -c "import importlib.util as u, sys; sys.exit(any(u.find_spec(m) for m in ('torch', 'mitsuba')))"
	# the install claims the one name gradsep: no generic top-level package (model, service, ...) outside the checkout
	cd / && $(abspath $(SERVE_VENV))/bin/python -c "import importlib.util as u, sys; \
	  sys.exit(any(u.find_spec(m) for m in ('model', 'service', 'renderer', 'training', 'evaluation')))"
	$(SERVE_VENV)/bin/pytest -q -n 2 --timeout=300 tests/service

# The shipped models, by one command (docs/training.md, "The shipped models"): a 120-frame procedural dataset (two
# independent realizations per frame: Noise2Noise targets), then
# the two layer models side by side (one core and one torch thread each: two single-threaded runs make more
# steps per minute on 2 cores than one two-threaded run), then the color baseline and the four Fig. 7 ablation
# variants (one identical budget of MINUTES_ABLATION per variant; the separated ones split it over their two
# layers). Writes into MODELS_OUT; copy direct/indirect/color.onnx to models/ to serve them.
DATASET          ?= data/n2n16
MODELS_OUT       ?= runs/ship-models
MINUTES_LAYER    ?= 30
MINUTES_COLOR    ?= 10
MINUTES_ABLATION ?= 5
TRAIN0 = OMP_NUM_THREADS=1 taskset -c 0 $(BIN)/gradsep
TRAIN1 = OMP_NUM_THREADS=1 taskset -c 1 $(BIN)/gradsep

$(DATASET)/manifest.json:
	$(BIN)/gradsep dataset --count 120 --spp 16 --size 256x256 --first-seed 1000 --pairs -o $(DATASET)

models: venv system-deps $(DATASET)/manifest.json
	$(BIN)/pip install -q -e '.[test]'
	mkdir -p $(MODELS_OUT)/ablation/combined-noattn $(MODELS_OUT)/ablation/combined-attn \
	         $(MODELS_OUT)/ablation/separated-noattn $(MODELS_OUT)/ablation/separated-attn
	( $(TRAIN0) train --data $(DATASET) --layer direct --minutes $(MINUTES_LAYER) -o runs/ship-direct && \
	  $(TRAIN0) export runs/ship-direct -o $(MODELS_OUT)/direct.onnx && \
	  $(TRAIN0) train --data $(DATASET) --layer color --no-attention --minutes $(MINUTES_COLOR) -o runs/ship-color && \
	  $(TRAIN0) export runs/ship-color -o $(MODELS_OUT)/color.onnx && \
	  $(TRAIN0) train --data $(DATASET) --layer color --no-attention --minutes $(MINUTES_ABLATION) -o runs/abl-combined-noattn && \
	  $(TRAIN0) export runs/abl-combined-noattn -o $(MODELS_OUT)/ablation/combined-noattn/color.onnx && \
	  $(TRAIN0) train --data $(DATASET) --layer color --minutes $(MINUTES_ABLATION) -o runs/abl-combined-attn && \
	  $(TRAIN0) export runs/abl-combined-attn -o $(MODELS_OUT)/ablation/combined-attn/color.onnx ) & p0=$$!; \
	( $(TRAIN1) train --data $(DATASET) --layer indirect --minutes $(MINUTES_LAYER) -o runs/ship-indirect && \
	  $(TRAIN1) export runs/ship-indirect -o $(MODELS_OUT)/indirect.onnx && \
	  for v in separated-noattn separated-attn; do for layer in direct indirect; do \
	    flag=; [ $$v = separated-noattn ] && flag=--no-attention; \
	    $(TRAIN1) train --data $(DATASET) --layer $$layer $$flag --minutes $$($(PYTHON) -c 'print($(MINUTES_ABLATION) / 2)') \
	      -o runs/abl-$$v-$$layer && \
	    $(TRAIN1) export runs/abl-$$v-$$layer -o $(MODELS_OUT)/ablation/$$v/$$layer.onnx || exit 1; \
	  done; done ) & p1=$$!; \
	wait $$p0 && wait $$p1

# The fused method's blend model by one command (docs/training.md, "The fused blend model"): the same Noise2Noise dataset;
# every training frame's candidates computed once into runs/fused-cache (gradsep.model.fused.layer_candidates, as inference
# computes them); then the indirect layer's blend network trained for MINUTES_FUSED on one core and exported. The
# direct layer has no model: the method serves it with its refine candidate (model.fused.FIXED_LAYERS, chosen on the
# held-out study). Writes $(MODELS_OUT)/fused/indirect.onnx; copy it to models/fused/ to serve it. The run folder
# resumes: re-running with a larger MINUTES_FUSED continues it.
MINUTES_FUSED    ?= 15
FUSED_CANDIDATES ?= oidn,refine-fast
FUSED_PY = OMP_NUM_THREADS=1 taskset -c 0 $(BIN)/python -m gradsep.training.fused
fused-models: venv system-deps $(DATASET)/manifest.json
	$(BIN)/pip install -q -e '.[test]'
	mkdir -p $(MODELS_OUT)/fused
	$(BIN)/python -m gradsep.training.fused cache --data $(DATASET) -o runs/fused-cache
	$(FUSED_PY) train --cache runs/fused-cache --layer indirect --candidates $(FUSED_CANDIDATES) \
	    --minutes $(MINUTES_FUSED) -o runs/fused-blend-indirect
	$(FUSED_PY) export runs/fused-blend-indirect -o $(MODELS_OUT)/fused/indirect.onnx
	rm -f $(MODELS_OUT)/fused/direct.onnx

lint: venv
	$(BIN)/ruff check .

clean:
	rm -rf $(VENV) $(SERVE_VENV) .pytest_cache .ruff_cache
