# One command for each job; the first one creates .venv and installs everything.
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
MODEL  ?= kidney
ARGS   ?=

.PHONY: venv precompute test bench reference figures stroke clean

NATIVE := $(VENV)/lib/pmask/.built

venv: $(BIN)/.installed $(NATIVE)

$(BIN)/.installed: pyproject.toml tools/install_cholmod.sh
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[test]'
	bash tools/install_cholmod.sh $(BIN)/pip
	touch $@

# the C over CHOLMOD (precompute/native.py); rebuilt when its source changes
$(NATIVE): $(BIN)/.installed precompute/_selected_inverse.c tools/build_native.sh
	bash tools/build_native.sh $(VENV)
	touch $@

## make precompute MODEL=kidney [ARGS="--force ..."]: write artifacts/$(MODEL).h5
precompute: venv
	$(BIN)/pmask precompute $(MODEL) $(ARGS)

## make test: the whole test suite (what CI runs)
test: venv
	$(BIN)/python -m pytest -q

## make bench: precompute and runtime benchmarks -> bench/results.json, bench/results.md
bench: venv
	$(BIN)/python bench/run.py

## make reference: recompute tests/reference from the stored meshes and show the diff (REMESH=1: mesh anew)
reference: venv
	$(BIN)/pmask reference $(if $(REMESH),--remesh,)
	git diff --stat -- tests/reference || true

## make figures: the Figure 6 maps of the kidney and the 1 kHz stroke traces into docs/
figures: venv
	$(BIN)/pmask figures $(MODEL) --out docs
	$(BIN)/python examples/stroke.py artifacts/$(MODEL).h5 --out docs

clean:
	rm -rf $(VENV) artifacts .pytest_cache .hypothesis
