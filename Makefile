# RS Elastic: build, test, demo and bench. Every target creates what it needs.
#
# Blender as a Python module (bpy from the package index) stands in for Blender. Blender 4.2 to 5.0
# embed Python 3.11, 5.1 and later Python 3.13, so each tested Blender gets its own venv:
#   .venv          the newest LTS (make test, demo, bench)
#   .venv-bpy-X.Y  the older versions of `make test-matrix`
# pinned by requirements/bpy-X.Y.txt.
PYTHON311 ?= $(shell tools/find_python.sh 3.11)
PYTHON313 ?= $(shell tools/find_python.sh 3.13)

NEWEST    := 5.2
MATRIX    := 4.2 4.5 5.0
MATRIX_VENVS := $(foreach v,$(MATRIX),.venv-bpy-$(v)/.stamp)
MATRIX_TESTS := $(addprefix test-matrix-,$(MATRIX))
VENV      := .venv
PY        := $(VENV)/bin/python
VERSION   := $(shell sed -n 's/^version = "\(.*\)"/\1/p' blender_manifest.toml)
LINUX_ZIP := dist/rs_elastic-$(VERSION)-linux_x64.zip
SOURCES   := blender_manifest.toml $(wildcard *.py bridge/*.py operators/*.py panels/*.py solver/*.py farm/*.js)

# Flamenco (the farm tests and bench): its manager and worker, built from source with Go into
# build/flamenco/, once (delete the folder to rebuild). The version is the add-on's, so that the
# Flamenco add-on accepts the manager.
FLAMENCO_SRC     ?= ../shared/flamenco
FLAMENCO_BIN     := build/flamenco
FLAMENCO_VERSION := $(shell sed -n 's/^__version__ = "\(.*\)"/\1/p' $(FLAMENCO_SRC)/addon/flamenco/manager/__init__.py 2>/dev/null)
FLAMENCO_LDFLAGS := -X projects.blender.org/studio/flamenco/internal/appinfo.ApplicationVersion=$(FLAMENCO_VERSION) \
                    -X projects.blender.org/studio/flamenco/internal/appinfo.ReleaseCycle=release

# The Python a Blender version embeds, and the interpreter found for it.
python_version = $(if $(filter 4.% 5.0,$(1)),3.11,3.13)
python_for     = $(PYTHON$(subst .,,$(call python_version,$(1))))

.PHONY: all venv deps wheels build validate test test-solver test-blender test-matrix $(MATRIX_TESTS) test-ui test-zoo ui-root test-farm flamenco demo bench clean

all: build

# $(1) venv folder, $(2) Blender version X.Y
define make_venv
	@test -n "$(call python_for,$(2))" || { echo "make: Python $(call python_version,$(2)) not found (Blender $(2) embeds it); install it (pyenv install $(call python_version,$(2))) or set PYTHON$(subst .,,$(call python_version,$(2)))=/path/to/python$(call python_version,$(2))"; exit 1; }
	rm -rf $(1)
	$(call python_for,$(2)) -m venv $(1)
	$(1)/bin/python -m pip install --quiet --upgrade pip
	$(1)/bin/python -m pip install --quiet -r requirements/bpy-$(2).txt
	touch $(1)/.stamp
endef

$(VENV)/.stamp: requirements/bpy-$(NEWEST).txt
	$(call make_venv,$(VENV),$(NEWEST))

.venv-bpy-%/.stamp: requirements/bpy-%.txt
	$(call make_venv,.venv-bpy-$*,$*)

venv: $(VENV)/.stamp

wheels: $(VENV)/.stamp
	$(PY) tools/fetch_wheels.py

# The solver tests run on the very wheels the linux-x64 package bundles for this Python.
.deps/.stamp: $(VENV)/.stamp blender_manifest.toml
	rm -rf .deps
	$(PY) -m pip install --quiet --no-deps --target .deps \
	    $$($(PY) tools/fetch_wheels.py --platform linux-x64 --this-python --print)
	touch $@

deps: .deps/.stamp

validate: wheels
	$(PY) tools/ext_tool.py validate .

# Blender's own tool validates the source, builds one zip per platform (each carries the wheels
# of both Pythons) and validates every zip it built.
build: wheels
	rm -rf dist && mkdir -p dist
	$(PY) tools/ext_tool.py validate .
	$(PY) tools/ext_tool.py build --split-platforms --output-dir dist
	for zip in dist/*.zip; do $(PY) tools/ext_tool.py validate "$$zip" || exit 1; done
	@ls -1 dist

$(LINUX_ZIP): $(SOURCES)
	$(MAKE) build

# In a shuffled order (pytest-random-order, seeded): a test that passes only after another is a
# bug. `make test-solver SEED=N` tries another order.
SEED ?= 1
test-solver: deps
	PYTHONPATH=.deps:. $(PY) -m pytest -q -p random_order --random-order-bucket=global \
	    --random-order-seed=$(SEED) tests/solver

# No .deps here: inside Blender the extension must run on its bundled wheels only.
test-blender: venv $(LINUX_ZIP)
	RS_ELASTIC_ZIP=$(LINUX_ZIP) $(PY) -m pytest -q tests/blender

# The scene zoo in full (tests/blender/test_zoo.py): scenes generated so that every pair of
# scene-feature values meets (every mesh modifier type, transforms, modes, linkage, bake targets,
# frame ranges, bakers), each case in its own Blender process; test-blender runs its first cases.
# The failures, grouped by cause: build/zoo-report.md.
test-zoo: venv $(LINUX_ZIP)
	mkdir -p build
	RS_ELASTIC_ZOO=full RS_ELASTIC_ZOO_REPORT=build/zoo-report.md RS_ELASTIC_ZIP=$(LINUX_ZIP) \
	    $(PY) -m pytest -q tests/blender/test_zoo.py

# The whole suite: solver, Blender on the newest LTS and on every older supported Blender, then
# the GUI tier, then the farm (a Flamenco manager and worker built from source, baking shots end
# to end). Everything they need is made first, one thing at a time (venvs, wheels, zips); then the
# solver and Blender tiers run two at a time (each keeps about 1.3 of this machine's 2 cores
# busy, and none races a clock: their timeouts are minutes), each tier's output in one piece
# when it ends, and the GUI tier's Debian root and the Flamenco binaries are built last in that
# phase (in the lane the other tier's last suite leaves idle); the GUI tier and the farm, which
# drive a window and a farm against timeouts, run alone after them.
test:
	$(MAKE) --no-print-directory deps $(LINUX_ZIP) $(MATRIX_VENVS)
	$(MAKE) --no-print-directory -j2 --output-sync=target test-solver test-blender $(MATRIX_TESTS) \
	    ui-root flamenco
	$(MAKE) --no-print-directory test-ui
	$(MAKE) --no-print-directory test-farm

# The whole Blender suite on each older version (test-matrix-X.Y for one), with the same zips
# (validated by that version's own extension tool first).
test-matrix: $(MATRIX_TESTS)

$(MATRIX_TESTS): test-matrix-%: $(LINUX_ZIP) .venv-bpy-%/.stamp
	@echo "== Blender $* (bpy module, Python $$(.venv-bpy-$*/bin/python -c 'import sys; print(sys.version.split()[0])'))"
	@for zip in dist/*.zip; do .venv-bpy-$*/bin/python tools/ext_tool.py validate "$$zip" || exit 1; done
	RS_ELASTIC_ZOO_SAMPLE=8 RS_ELASTIC_ZIP=$(LINUX_ZIP) .venv-bpy-$*/bin/python -m pytest -q tests/blender

# The GUI tier (tests/ui): Debian's Blender in a real window under Xvfb, driven by real input
# events, inside a Debian root that tools/ui/build_root.sh builds into build/ui-root (as root:
# about 4 minutes from nothing, a second when cached). Where this machine cannot build it (exit
# 77: not root, no network) the tests are skipped with the reason; RS_ELASTIC_REQUIRE_UI=1 (CI)
# turns that skip into a failure. Screenshots and Blender's log: build/ui-artifacts/.
UI_ROOT := build/ui-root

ui-root:
	@tools/ui/build_root.sh $(UI_ROOT) || [ $$? -eq 77 ]

test-ui: venv $(LINUX_ZIP) ui-root
	RS_ELASTIC_ZIP=$(LINUX_ZIP) RS_ELASTIC_UI_ROOT=$(UI_ROOT) $(PY) -m pytest -q -rs tests/ui

# The source may be read-only (nothing is written into it: no VCS stamp, the binaries go to
# build/flamenco); Go fetches the modules it needs from the module proxy into its own cache.
$(FLAMENCO_BIN)/flamenco-%:
	@test -d $(FLAMENCO_SRC)/cmd/flamenco-$* || { echo "make: no Flamenco source in $(FLAMENCO_SRC) (set FLAMENCO_SRC=/path/to/flamenco)"; exit 1; }
	@command -v go >/dev/null || { echo "make: Go is not installed (Flamenco needs Go 1.26 or later)"; exit 1; }
	mkdir -p $(FLAMENCO_BIN)
	cd $(FLAMENCO_SRC) && go build -buildvcs=false -ldflags "$(FLAMENCO_LDFLAGS)" -o $(abspath $@).part ./cmd/flamenco-$*
	mv $@.part $@

flamenco: $(FLAMENCO_BIN)/flamenco-manager $(FLAMENCO_BIN)/flamenco-worker

# Farm tests: manager and worker on 127.0.0.1 with temporary folders, the worker's Blender being
# tools/bpy-blender (the bpy module behind Blender's command line).
test-farm: venv $(LINUX_ZIP) flamenco
	FLAMENCO_SRC=$(FLAMENCO_SRC) FLAMENCO_BIN=$(FLAMENCO_BIN) RS_ELASTIC_ZIP=$(LINUX_ZIP) \
	    $(PY) -m pytest -q --rootdir=tests tests/farm

demo: venv $(LINUX_ZIP)
	RS_ELASTIC_ZIP=$(LINUX_ZIP) $(PY) tools/demo.py --output demo_output

# The bench's before/after rows measure the solver of BENCH_BASELINE (main before the speed work
# of Prepare, the cubature, the space-time solve and the dynamics) against the current one.
BENCH_BASELINE ?= e08decd

bench: deps $(LINUX_ZIP) flamenco
	FLAMENCO_SRC=$(FLAMENCO_SRC) FLAMENCO_BIN=$(FLAMENCO_BIN) \
	    PYTHONPATH=.deps:. $(PY) bench/run_bench.py --output bench_output --baseline $(BENCH_BASELINE)

clean:
	rm -rf dist build demo_output bench_output .pytest_cache
