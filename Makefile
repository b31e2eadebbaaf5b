# Two commands do all the set-up on a fresh machine (Python 3.11+ with venv, and EGL for previews):
#   make demo   install into .venv, run the built-in scene to out/demo.usdc and render out/demo.png
#   make test   install into .venv with the test extras and run the test suite
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
	.venv-numpy1/bin/python -m pytest -q

bench: $(BIN)/.installed
	$(BIN)/python benchmarks/hair.py

.PHONY: install demo test test-numpy1 bench
