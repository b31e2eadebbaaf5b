# Two commands do all the set-up on a fresh machine (Python 3.11+ with venv, and EGL for previews):
#   make demo   install into .venv, run the built-in scene to out/demo.usdc and render out/demo.png
#   make test   install into .venv with the test extras and run the test suite
# The Blender add-on (blender/cfx_blender):
#   make test-blender   its bpy tests, in .venv-bpy (Python 3.11, bpy 5.0.1, numpy 1.26)
#   make blender-addon  the extension zip to install from disk: out/cfx_blender.zip
VENV ?= .venv
PYTHON ?= python3
BIN := $(VENV)/bin

$(BIN)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e ".[test]"
	touch $@

install: $(BIN)/.installed

demo: $(BIN)/.installed
	$(BIN)/cfx demo -o out/demo.usdc

test: $(BIN)/.installed
	$(BIN)/python -m pytest -q

# the whole suite again under numpy 1.26, which Blender's Python pins
test-numpy1:
	$(PYTHON) -m venv .venv-numpy1
	.venv-numpy1/bin/python -m pip install -q -e ".[test]" "numpy<2"
	# the sm_90 compile of every kernel (minutes) does not read numpy: `make test` checks it
	.venv-numpy1/bin/python -m pytest -q \
		--deselect tests/test_benchmarks.py::test_no_cuda_kernel_spills_more_than_its_recorded_baseline

bench: $(BIN)/.installed
	$(BIN)/python benchmarks/hair.py

# bpy 5.0.1 is built for Python 3.11 only and pins numpy 1.26; the tests compare against `cfx run`
# of the main venv, hence the dependency on it
PYTHON311 ?= python3.11
BPY_VENV := .venv-bpy

$(BPY_VENV)/bin/.installed: pyproject.toml
	@command -v $(PYTHON311) >/dev/null 2>&1 || { echo "make test-blender: $(PYTHON311) not found: bpy 5.0.1 needs Python 3.11 (install it, or pass PYTHON311=/path/to/python3.11)" >&2; exit 1; }
	$(PYTHON311) -m venv $(BPY_VENV)
	$(BPY_VENV)/bin/python -m pip install -q --upgrade pip
	$(BPY_VENV)/bin/python -m pip install -q "bpy==5.0.1" -e ".[test]" "numpy<2"
	touch $@

test-blender: $(BIN)/.installed $(BPY_VENV)/bin/.installed
	$(BPY_VENV)/bin/python -m pytest -q tests_blender

# the manifest and modules at the zip's top level, as `blender --command extension build` lays them out
blender-addon:
	mkdir -p out
	rm -f out/cfx_blender.zip
	cd blender/cfx_blender && $(PYTHON) -m zipfile -c ../../out/cfx_blender.zip blender_manifest.toml *.py

.PHONY: install demo test test-numpy1 bench test-blender blender-addon
