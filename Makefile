# One command for each job.  The first `make` creates .venv and installs the package into it; it
# never changes the system: `make system-deps` (as root, printing what it installs) adds the C
# libraries and the browser the fast routes and the viewer tests use.
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
MODEL  ?= kidney
ARGS   ?=
EXTRAS ?= precompute,figures,segmentation,repair,test,docs
PIP    := $(BIN)/pip install --quiet -c constraints.txt

.PHONY: help view venv system-deps precompute test test-slow test-pip sanitize docs bench reference figures stroke clean distclean

## make: this list
help:
	@echo "pmask: make TARGET (the first run creates .venv and installs pmask into it)"
	@sed -n 's/^## make /  make /p' $(MAKEFILE_LIST)

## make view [MODEL=kidney]: the model in a browser (pmask view; Ctrl-C stops)
view: venv
	$(BIN)/pmask view artifacts/$(MODEL).h5 $(ARGS)

## make system-deps: Debian packages for the native routes, the viewer's build (npm) and its browser tests
## (chromium + chromedriver), and valgrind for the bench's instruction counts (root; prints what it installs)
# Debian's npm only where no Node.js is installed (a NodeSource nodejs brings its own npm and conflicts with it)
SYSTEM_PACKAGES := gcc libsuitesparse-dev libopenblas0-pthread chromium chromium-driver valgrind $(if $(shell command -v npm),,nodejs npm)
system-deps:
	@echo "installing with apt-get: $(SYSTEM_PACKAGES)"
	apt-get update
	DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends $(SYSTEM_PACKAGES)

venv: $(VENV)/.installed

# the package in editable mode; the build backend (setup.py) compiles the C extensions in place
$(VENV)/.installed: pyproject.toml setup.py constraints.txt $(wildcard precompute/*.c runtime/servo/*.c runtime/servo/*.h runtime/servo/core/*.c runtime/servo/core/*.h viewer/src/*.js viewer/package-lock.json)
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip "setuptools>=77" wheel 2>&1 | grep -v "^WARNING: Location" || true
	@# (setuptools warns that a folder named like the package may shadow an editable install; pmask/__init__.py
	@# handles a checkout's root, so the warning is not shown)
	PYTHONWARNINGS="ignore:Editable installation" $(PIP) --no-build-isolation -e '.[$(EXTRAS)]'
	@$(BIN)/pmask --version
	touch $@

## make precompute MODEL=kidney [ARGS="--force ..."]: write artifacts/$(MODEL).h5
precompute: venv
	$(BIN)/pmask precompute $(MODEL) $(ARGS)

# the suites run on two processes (pytest-xdist), one test file per process at a time so that a file's
# module fixtures (a precomputed model, a LocalCluster) are built once, but the files tests/conftest.py names
# in SPREAD_FILES test by test; JOBS=1 runs them serially
JOBS   ?= 2
XDIST  := $(if $(filter 1,$(JOBS)),,-n $(JOBS) --dist loadfile)
# and each process with one BLAS and OpenMP thread: two processes each running OpenBLAS's and CHOLMOD's two
# threads on two cores spin against each other (the reference, Green's-function, materials and hollow tests took
# 126 s, 51 s of it in the kernel, against 108 s and 26 s, on one 2-core machine); what asks for more threads
# gets them (the W sweep's threadpool_limits, the sanitizer's OMP_NUM_THREADS)
ONE_THREAD := $(if $(filter 1,$(JOBS)),,OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1 MKL_NUM_THREADS=1)

## make test [JOBS=2]: the fast test suite (what a developer runs; CI runs it and the slow tests)
test: venv
	$(ONE_THREAD) $(BIN)/python -m pytest -q $(XDIST) $(PYTEST_ARGS)

## make test-slow: the long solves and the P2 reference rows
test-slow: venv
	$(ONE_THREAD) $(BIN)/python -m pytest -q -m slow $(XDIST) $(PYTEST_ARGS)

## make test-pip: the Green's-function and runtime tests again on the pip-only route
test-pip: venv
	PMASK_CHOLMOD=cvxopt $(BIN)/python -m pytest -q tests/test_greens.py tests/test_runtime.py tests/test_selinv.py

## make sanitize: the C example, the servo core's threads and the selected inversion under ASan+UBSan and TSan
sanitize: venv
	$(BIN)/python tests/c/sanitize.py

## make docs: the documentation from the code into docs/_build/html (warnings are errors; runs the examples)
docs: venv
	$(BIN)/pmask -q precompute kidney
	$(BIN)/python -m sphinx -W --keep-going -q -b html docs docs/_build/html
	@echo "open docs/_build/html/index.html"

## make bench: precompute and runtime benchmarks -> bench/results.json and docs/generated/benchmarks.md (ONLY=haptics, viewer, display or compress: that section alone; ONLY=compress-kidneys: its dense-against-compressed rows alone; ONLY=compress-c: its grasp in C on the organ-scale table alone; ONLY=organ: the 50,000-vertex organ, ~30-45 min; ONLY=organ-5mm: the same with masks up to 5 mm; ONLY=organ-p2: the 20,000-vertex organ with P2; ONLY=reads: the model of W's reads at both organ sizes, ~10 min)
bench: venv
	$(BIN)/python bench/run.py $(if $(ONLY),--only $(ONLY),)

## make reference: recompute tests/reference from the stored meshes, show the diff, rewrite docs/generated/reference.md (REMESH=1: mesh anew)
reference: venv
	$(BIN)/pmask reference $(if $(REMESH),--remesh,)
	git diff --stat -- tests/reference || true

## make figures: the paper's figures for the kidney and the stroke traces into docs/
figures: precompute
	$(BIN)/pmask figures $(MODEL) --out docs
	$(BIN)/python examples/stroke.py artifacts/$(MODEL).h5 --out docs

## make clean: build products and caches (keeps artifacts/); make distclean: also artifacts/ and .venv
clean:
	rm -rf build *.egg-info .pytest_cache .hypothesis docs/_build docs/auto_examples docs/api/generated
	find precompute runtime -name '*.so' -delete
	rm -f viewer/static/viewer.bundle.js
distclean: clean
	rm -rf $(VENV) artifacts
