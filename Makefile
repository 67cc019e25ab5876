# RS Elastic: build, test, demo and bench. Every target creates what it needs.
PYTHON311 ?= python3.11
VENV      := .venv
PY        := $(VENV)/bin/python
EXT_TOOL   = $(VENV)/lib/python3.11/site-packages/bpy/5.0/scripts/addons_core/bl_pkg/cli/blender_ext.py
VERSION   := $(shell sed -n 's/^version = "\(.*\)"/\1/p' blender_manifest.toml)
LINUX_ZIP := dist/rs_elastic-$(VERSION)-linux_x64.zip
SOURCES   := blender_manifest.toml $(wildcard *.py bridge/*.py operators/*.py panels/*.py solver/*.py)

.PHONY: all venv deps wheels build validate test test-solver test-blender demo bench clean

all: build

$(VENV)/.stamp: requirements-dev.txt
	@command -v $(PYTHON311) >/dev/null || { echo "make: $(PYTHON311) not found; install Python 3.11 or set PYTHON311=/path/to/python3.11"; exit 1; }
	$(PYTHON311) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -r requirements-dev.txt
	touch $@

venv: $(VENV)/.stamp

wheels: $(VENV)/.stamp
	$(PY) tools/fetch_wheels.py

# The solver tests run on the very wheels the linux-x64 package bundles.
.deps/.stamp: $(VENV)/.stamp blender_manifest.toml
	$(PY) tools/fetch_wheels.py --platform linux-x64
	rm -rf .deps
	$(PY) -m pip install --quiet --no-deps --target .deps wheels/*manylinux*.whl
	touch $@

deps: .deps/.stamp

validate: wheels
	$(PY) $(EXT_TOOL) validate .

build: wheels
	rm -rf dist && mkdir -p dist
	$(PY) $(EXT_TOOL) validate .
	$(PY) $(EXT_TOOL) build --split-platforms --output-dir dist
	@ls -1 dist

$(LINUX_ZIP): $(SOURCES)
	$(MAKE) build

test-solver: deps
	PYTHONPATH=.deps:. $(PY) -m pytest -q tests/solver

# No .deps here: inside Blender the extension must run on its bundled wheels only.
test-blender: venv $(LINUX_ZIP)
	RS_ELASTIC_ZIP=$(LINUX_ZIP) $(PY) -m pytest -q tests/blender

test: test-solver test-blender

demo: venv $(LINUX_ZIP)
	RS_ELASTIC_ZIP=$(LINUX_ZIP) $(PY) tools/demo.py --output demo_output

bench: deps
	PYTHONPATH=.deps:. $(PY) bench/run_bench.py --output bench_output

clean:
	rm -rf dist build demo_output bench_output .pytest_cache
