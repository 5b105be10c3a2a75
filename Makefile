# One command for each job; the first one creates .venv and installs everything.
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
MODEL  ?= kidney
ARGS   ?=

.PHONY: venv precompute test bench clean

venv: $(BIN)/.installed

$(BIN)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[test]'
	touch $@

## make precompute MODEL=kidney [ARGS="--force ..."]: write artifacts/$(MODEL).h5
precompute: venv
	$(BIN)/pmask precompute $(MODEL) $(ARGS)

## make test: the whole test suite (what CI runs)
test: venv
	$(BIN)/python -m pytest -q

clean:
	rm -rf $(VENV) artifacts .pytest_cache .hypothesis
