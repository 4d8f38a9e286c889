# ashc: `make demo` designs, simulates and reports on the paper's Cuk converter; `make test` runs the suite.
# Both create .venv and install the package from pyproject.toml on first use.

SHELL  := /bin/bash
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
SPEC   ?= specs/cuk_converter.yaml
OUT    ?= outputs/cuk_converter

.PHONY: install demo test test-fast bench fuzz docs lock clean

# The pinned set (constraints.txt: pip, the build tools and every package make test installs). pyproject.toml
# keeps ranges; `make lock` refreshes the pins from the registry's newest releases, on purpose.
CONSTRAINTS := constraints.txt

$(BIN)/ashc: pyproject.toml $(CONSTRAINTS)
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade -c $(CONSTRAINTS) pip
	$(BIN)/pip install --quiet -c $(CONSTRAINTS) --build-constraint $(CONSTRAINTS) -e ".[test]"
	touch $@

install: $(BIN)/ashc

demo: install
	$(BIN)/ashc design $(SPEC) --out $(OUT)
	$(BIN)/ashc simulate $(SPEC) --out $(OUT)
	$(BIN)/ashc report $(SPEC) --out $(OUT) --runs 32 --t-final 10
	$(BIN)/ashc summary $(OUT)
	@echo ""
	@echo "Done: the design is in $(OUT)/ (open $(OUT)/report.html). To use ashc yourself, put it on PATH:"
	@echo "    source $(VENV)/bin/activate     # then: ashc --help, ashc check $(SPEC)"
	@echo "or call it as $(BIN)/ashc. Next: write a spec of your plant (docs/spec-format.md) and run ashc design on it."

# The suite on two cores (pytest-xdist; CI has two). `make test-fast` leaves out the tests marked slow
# (whole designs and campaigns through the CLI): about a third of the time, for the edit-test loop.
test: install
	$(BIN)/python -m pytest -q -n 2

test-fast: install
	$(BIN)/python -m pytest -q -n 2 -m "not slow"

# Wall time and peak memory per stage on the ladder family (n = 4..128) and the Cuk spec; prints a table.
# BENCH_AGAINST=REV: only the closed loops, this tree against git revision REV side by side (paired runs).
bench: install
	$(BIN)/python bench/bench.py $(if $(BENCH_AGAINST),--against $(BENCH_AGAINST))

# A longer fuzz than the suite's: FUZZ_EXAMPLES cases per property; hypothesis prints the counts.
FUZZ_EXAMPLES ?= 20000
fuzz: install
	ASHC_FUZZ_EXAMPLES=$(FUZZ_EXAMPLES) $(BIN)/python -m pytest -q tests/test_fuzz.py -p no:cacheprovider --hypothesis-show-statistics \
	  | grep -E "passing examples|failing|passed|failed|test_" ; \
	  status=$${PIPESTATUS[0]}; echo "fuzz: $(FUZZ_EXAMPLES) cases per property, exit $$status"; exit $$status

# Regenerate docs/bad-inputs.md (every bad input of tests/bad_inputs.py and the message it gets) and
# docs/cli.md (the command-line reference, from the typer app) and the equation table of docs/theory.md.
docs: install
	$(BIN)/python -m tests.bad_inputs docs/bad-inputs.md
	$(BIN)/python docs/generate_cli.py docs/cli.md
	$(BIN)/python docs/generate_theory.py docs/theory.md

# Refresh constraints.txt: a fresh venv with the newest releases pyproject.toml's ranges admit, frozen; then
# run `make test` on the new pins before committing them (README, "Pinned dependencies").
LOCK_VENV := .venv-lock
lock:
	rm -rf $(LOCK_VENV)
	$(PYTHON) -m venv $(LOCK_VENV)
	$(LOCK_VENV)/bin/pip install --quiet --upgrade pip setuptools wheel
	$(LOCK_VENV)/bin/pip install --quiet -e ".[test]"
	{ sed -n '1,/^# Build tools/p' $(CONSTRAINTS); \
	  $(LOCK_VENV)/bin/pip freeze --all | grep -E '^(pip|setuptools|wheel)=='; \
	  echo "# Runtime and test dependencies (pip freeze of the venv):"; \
	  $(LOCK_VENV)/bin/pip freeze --exclude-editable | grep -vE '^(pip|setuptools|wheel)=='; } > $(CONSTRAINTS).new
	mv $(CONSTRAINTS).new $(CONSTRAINTS)
	rm -rf $(LOCK_VENV)
	@echo "constraints.txt refreshed; now: rm -rf $(VENV) && make test, then commit constraints.txt"

clean:
	rm -rf outputs/*/ .pytest_cache
