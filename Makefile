# ashc: `make demo` designs, simulates and reports on the paper's Cuk converter; `make test` runs the suite.
# Both create .venv and install the package from pyproject.toml on first use.

SHELL  := /bin/bash
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
SPEC   ?= specs/cuk_converter.yaml
OUT    ?= outputs/cuk_converter

.PHONY: install demo test bench fuzz docs clean

$(BIN)/ashc: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e ".[test]"
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

test: install
	$(BIN)/python -m pytest -q

# Wall time and peak memory per stage on the ladder family (n = 4..128) and the Cuk spec; prints a table.
bench: install
	$(BIN)/python bench/bench.py

# A longer fuzz than the suite's: FUZZ_EXAMPLES cases per property; hypothesis prints the counts.
FUZZ_EXAMPLES ?= 20000
fuzz: install
	ASHC_FUZZ_EXAMPLES=$(FUZZ_EXAMPLES) $(BIN)/python -m pytest -q tests/test_fuzz.py -p no:cacheprovider --hypothesis-show-statistics \
	  | grep -E "passing examples|failing|passed|failed|test_" ; \
	  status=$${PIPESTATUS[0]}; echo "fuzz: $(FUZZ_EXAMPLES) cases per property, exit $$status"; exit $$status

# Regenerate docs/bad-inputs.md (every bad input of tests/bad_inputs.py and the message it gets) and
# docs/cli.md (the command-line reference, from the typer app).
docs: install
	$(BIN)/python -m tests.bad_inputs docs/bad-inputs.md
	$(BIN)/python docs/generate_cli.py docs/cli.md

clean:
	rm -rf outputs/*/ .pytest_cache
