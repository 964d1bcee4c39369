# edgemodbus developer tasks.  `make demo` and `make test` set up everything they need
# on a Debian bookworm machine: the Debian packages (apt-get, with sudo when not root)
# and a .venv holding the package (editable) with its test and bench extras.

PY      ?= python3
VENV    := .venv
BIN     := $(VENV)/bin
DEB     := libmodbus-dev pkg-config socat
SUDO    := $(shell [ "$$(id -u)" = 0 ] || echo sudo)
CSRC    := $(wildcard csrc/*.c csrc/*.h csrc/cdefs/*.h)
PYTEST  := $(BIN)/python -m pytest
QUICK   ?= 0

.PHONY: all deps build demo test lint typecheck unit integration test-asan bench bench-quick fuzz soak clean

all: test

deps:
	@missing=""; for p in $(DEB); do dpkg -s $$p >/dev/null 2>&1 || missing="$$missing $$p"; done; \
	if [ -n "$$missing" ]; then \
	  echo "installing Debian packages:$$missing"; \
	  $(SUDO) apt-get update -qq && \
	  DEBIAN_FRONTEND=noninteractive $(SUDO) apt-get install -y -qq $$missing >/dev/null; \
	fi

$(BIN)/python:
	$(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip 'setuptools>=77' 'cffi>=2' wheel

.stamp-install: pyproject.toml setup.py build_ffi.py $(CSRC) | deps $(BIN)/python
	$(BIN)/python -m pip install -q --no-build-isolation -e '.[test,bench]'
	@touch $@

build: .stamp-install

demo: build
	$(BIN)/edgemodbus demo

lint: build
	$(BIN)/ruff check src tests bench
	$(BIN)/mypy

test: build lint
	$(PYTEST) tests

unit: build
	$(PYTEST) tests/unit

integration: build
	$(PYTEST) tests/integration

# The C codec built with AddressSanitizer + UBSan (into build-asan/), driven by the codec
# tests; --capture=sys lets a sanitizer report (written to fd 2) reach the terminal.
test-asan: build
	$(BIN)/python tools/asan_build.py && \
	  ASAN_OPTIONS=detect_leaks=0 LD_PRELOAD="$$(gcc -print-file-name=libasan.so)" \
	  EDGEMODBUS_NATIVE=asan $(PYTEST) -q -p no:cacheprovider --capture=sys tests/unit/test_codec*.py

bench: build
	$(PYTEST) bench --benchmark-only --benchmark-columns=min,mean,median,rounds

bench-quick: build
	EDGEMODBUS_BENCH_QUICK=1 $(PYTEST) bench --benchmark-only -q \
	  --benchmark-min-rounds=3 --benchmark-max-time=0.2 --benchmark-columns=min,mean,rounds

clean:
	rm -rf build build-asan dist *.egg-info src/*.egg-info .stamp-* src/edgemodbus/_native*
