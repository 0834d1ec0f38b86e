# Set-up and checks. `make test` and `make demo` are self-sufficient on a fresh machine.
PY     ?= $(shell command -v python3.11 || command -v python3)
VENV   := .venv
BIN    := $(VENV)/bin
PYTEST_ARGS ?=
# the suite runs in parallel, one test file per worker at a time (module fixtures are built once);
# TEST_WORKERS=0 runs it in this process
TEST_WORKERS ?= 2
XDIST = $(if $(filter 0,$(TEST_WORKERS)),,-n $(TEST_WORKERS) --dist loadfile)

.PHONY: setup setup-test demo test test-full bench bench-plant bench-scale bench-alarms bench-workbench bench-detection docs clean gateway historian

setup: $(VENV)/.stamp-run

setup-test: $(VENV)/.stamp-test

$(BIN)/python:
	$(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip

# The development setup: the gateway's runtime plus the workbench (the demo's simulated drive is the
# rig simulator, which needs numba). A gateway PC takes `make gateway` instead.
$(VENV)/.stamp-run: $(BIN)/python requirements.lock requirements-workbench.lock pyproject.toml setup.py agent/_kernels.c
	$(BIN)/pip install -q -r requirements-workbench.lock
	$(BIN)/pip install -q --no-deps --no-build-isolation -e . >/dev/null
	touch $@

# A lean gateway install into GATEWAY_VENV (default /opt/pmsm-agent/.venv): the agent, its
# transports and the C kernels; no workbench, no simulator (docs/benchmarks.md has its size).
# `make historian` is the same plus the PostgreSQL client, for the plant server that runs
# `pmsm-agent historian` (docs/historian.md).
GATEWAY_VENV ?= /opt/pmsm-agent/.venv
gateway: INSTALL_LOCK := requirements.lock
historian: INSTALL_LOCK := requirements-historian.lock
gateway historian:
	$(PY) -m venv $(GATEWAY_VENV)
	$(GATEWAY_VENV)/bin/python -m pip install -q --upgrade pip
	$(GATEWAY_VENV)/bin/pip install -q -r $(INSTALL_LOCK)
	$(GATEWAY_VENV)/bin/pip install -q --no-deps --no-build-isolation . >/dev/null

$(VENV)/.stamp-test: $(VENV)/.stamp-run requirements-test.lock requirements-historian.lock
	$(BIN)/pip install -q -r requirements-test.lock
	touch $@

demo: setup
	$(BIN)/pmsm-agent demo

test: setup-test
	$(BIN)/python -m pytest -q $(XDIST) $(PYTEST_ARGS)

test-full: setup-test
	PMSM_SLOW=full $(BIN)/python -m pytest -q $(XDIST) $(PYTEST_ARGS)

bench: setup-test
	$(BIN)/python -m bench.run

# the agent at plant scale: zenoh payload sizes, a router's throughput on loopback, the historian's
# ingest and its PostgreSQL store (a few minutes; figures in bench/results/plant.json, docs/scale.md)
bench-plant: setup-test
	$(BIN)/python -m bench.bench_plant

# the agent at plant scale: 1, 10, 50 and 100 replayed drives in the real agent and its DSP workers,
# lossless and at real time, and one drive's chain against the revision before it (about 15 min;
# figures in docs/benchmarks.md; `make test` runs a short form)
bench-scale: setup-test
	$(BIN)/python -m bench.bench_scale

# false alarms per drive-day over 24 h of simulated operation per transmission, and detection
# delays (about an hour on two cores; figures in docs/benchmarks.md)
bench-alarms: setup-test
	$(BIN)/python -m bench.bench_alarms

# the workbench over a randomised family of drives (bench/family: 60 drives per effect, 800 null
# drives; resumable) and the check of the records it names where four fall short, then on the project's
# simulator and on motulator (a third-party one): hidden effects, two at once, 25 null record sets each,
# 10 with load steps and, for motulator, 10 without its encoder angle (about 65 min the first time;
# motulator records are cached)
bench-workbench: setup-test
	$(BIN)/python -m bench.bench_family
	$(BIN)/python -m bench.bench_settle
	$(BIN)/python -m bench.bench_workbench
	$(BIN)/python -m bench.bench_workbench --seconds 2.5

# the agent's detection and false alarms on motulator's drive, a third-party simulator (about 8 min
# the first time; its records are cached)
bench-detection: setup-test
	$(BIN)/python -m bench.bench_thirdparty_detection

docs: setup
	$(BIN)/python -m firmware_if.plc_registers --write docs/registers.md
	$(BIN)/python -m firmware_if.modbus_capture --write docs/modbus_capture.md

clean:
	rm -rf $(VENV) .pytest_cache build *.egg-info
	rm -f agent/_kernels.*.so
