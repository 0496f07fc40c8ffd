# Two entry points for a fresh Debian/Ubuntu machine with Python 3.11:
#   make demo   installs what the demo needs and runs it
#   make test   installs the test dependencies and runs the whole suite
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin

.PHONY: demo test test-serving system-deps venv lint clean

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

test-serving:
	rm -rf $(SERVE_VENV)
	$(PYTHON) -m venv $(SERVE_VENV)
	$(SERVE_VENV)/bin/pip install -q --upgrade pip
	$(SERVE_VENV)/bin/pip install -q '.[serve]' pytest pytest-timeout pytest-xdist schemathesis
	$(SERVE_VENV)/bin/python -c "import importlib.util as u, sys; sys.exit(any(u.find_spec(m) for m in ('torch', 'mitsuba')))"
	$(SERVE_VENV)/bin/pytest -q -n 2 --timeout=300 tests/service

lint: venv
	$(BIN)/ruff check .

clean:
	rm -rf $(VENV) $(SERVE_VENV) .pytest_cache .ruff_cache
