# ashc: `make demo` designs and simulates the paper's Cuk converter; `make test` runs the suite.
# Both create .venv and install the package from pyproject.toml on first use.

PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
SPEC   ?= specs/cuk_converter.yaml
OUT    ?= outputs/cuk_converter

.PHONY: install demo test clean

$(BIN)/ashc: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e ".[test]"
	touch $@

install: $(BIN)/ashc

demo: install
	$(BIN)/ashc design $(SPEC) --out $(OUT)
	$(BIN)/ashc simulate $(SPEC) --out $(OUT)
	$(BIN)/ashc summary $(OUT)

test: install
	$(BIN)/python -m pytest -q

clean:
	rm -rf outputs/*/ .pytest_cache
