# wiremap: every install step lives here and in pyproject.toml.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test check lint typecheck bench fuzz certs clean venv

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[dev]'
	$(BIN)/python -c 'from mapping.kernels import compile_kernels; compile_kernels()'
	touch $(STAMP)

venv: $(STAMP)

demo: $(STAMP)
	$(BIN)/wiremap run --world paper-small --robots 3 --duration 60 --stop-when-done --seed 1 --out out/demo

# The pure tests on both cores (pytest-xdist), then the tests that start processes and Zenoh
# sessions (marker `fleet`), two at a time: a fleet test asserts what arrives, not how fast (its
# timings are printed and recorded, and mean little on a shared machine), so two fleets at once
# only test it under load, as a real fleet's machine is. Serial, the fleet half took 5.5 min of
# an 8-min suite; two at a time 3.1-3.4 min (three runs, every test passing).
test: $(STAMP)
	$(BIN)/ruff check mapping wire_codec agents tests
	$(BIN)/mypy
	$(BIN)/python -m pytest -q -n 2 -m "not fleet"
	$(BIN)/python -m pytest -q -n 2 -m fleet

# The edit-test loop (under a minute): lint and the pure tests, without the tests that start
# processes or Zenoh sessions (marker `fleet`) or run long (`slow`). `make test` runs them all.
check: $(STAMP)
	$(BIN)/ruff check mapping wire_codec agents tests
	$(BIN)/python -m pytest -q -m "not fleet and not slow"

lint: $(STAMP)
	$(BIN)/ruff check mapping wire_codec agents tests

bench: $(STAMP)
	$(BIN)/wiremap bench codec --json
	$(BIN)/wiremap bench accuracy --world paper-small --seeds 3 --json
	$(BIN)/wiremap bench speed --pieces --json

fuzz: $(STAMP)
	$(BIN)/python -m pip install -q atheris || { echo "atheris does not install here"; exit 1; }
	$(BIN)/python tests/fuzz_codec.py -atheris_runs=200000

# Test certificates, passwords and credentials for a secure fleet (never committed; see
# broker_config/secure/README.md).
certs: $(STAMP)
	$(BIN)/python -m agents.fleet.secure init broker_config/secure --fleet default --robots r1,r2,r3 --force

clean:
	rm -rf out .pytest_cache .mypy_cache .ruff_cache
