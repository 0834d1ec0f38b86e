# Set-up and checks. `make test` and `make demo` are self-sufficient on a fresh machine.
PY     ?= $(shell command -v python3.11 || command -v python3)
VENV   := .venv
BIN    := $(VENV)/bin
PYTEST_ARGS ?=

.PHONY: setup setup-test demo test test-full bench bench-alarms docs clean

setup: $(VENV)/.stamp-run

setup-test: $(VENV)/.stamp-test

$(BIN)/python:
	$(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip

$(VENV)/.stamp-run: $(BIN)/python requirements.lock pyproject.toml agent/_kernels.c
	$(BIN)/pip install -q -r requirements.lock
	$(BIN)/pip install -q --no-deps --no-build-isolation -e .
	touch $@

$(VENV)/.stamp-test: $(VENV)/.stamp-run requirements-test.lock
	$(BIN)/pip install -q -r requirements-test.lock
	touch $@

demo: setup
	$(BIN)/pmsm-agent demo

test: setup-test
	$(BIN)/python -m pytest -q $(PYTEST_ARGS)

test-full: setup-test
	PMSM_SLOW=full $(BIN)/python -m pytest -q $(PYTEST_ARGS)

bench: setup-test
	$(BIN)/python -m bench.run

# false alarms per drive-day over 24 h of simulated operation per transmission, and detection
# delays (about an hour on two cores; figures in docs/benchmarks.md)
bench-alarms: setup-test
	$(BIN)/python -m bench.bench_alarms

docs: setup
	$(BIN)/python -m firmware_if.plc_registers --write docs/registers.md
	$(BIN)/python -m firmware_if.modbus_capture --write docs/modbus_capture.md

clean:
	rm -rf $(VENV) .pytest_cache build *.egg-info
	rm -f agent/_kernels.*.so
