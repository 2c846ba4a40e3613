# `make test` and `make demo` set everything up on a fresh machine (a .venv with the pinned packages).
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed-stamp

.PHONY: test demo bench clean franky-sim

# franky-sim 1.0.4 (the FR3 over the libfranka protocol, MuJoCo inside) needs numpy >= 2, which bpy
# forbids: it gets its own environment, with the numpy/numba parts of skinsafe that its world runs
# (core/sim/franky_world.py: the skin readout and the force feed).
FRANKY       := .venv-franky
FRANKY_STAMP := $(FRANKY)/.installed-stamp
FRANKY_PKGS  := franky-sim==1.0.4 mujoco==4.0.0 pin==4.1.0 numpy==2.4.6 numba==0.68.1 scipy==1.17.1 pyserial==3.5

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e ".[test]"
	touch $(STAMP)

$(FRANKY_STAMP): pyproject.toml Makefile
	test -x $(FRANKY)/bin/python || $(PYTHON) -m venv $(FRANKY)
	$(FRANKY)/bin/python -m pip install -q --upgrade pip
	$(FRANKY)/bin/python -m pip install -q $(FRANKY_PKGS)
	$(FRANKY)/bin/python -m pip install -q --no-deps -e .
	touch $(FRANKY_STAMP)

franky-sim: $(FRANKY_STAMP)

test: $(STAMP) $(FRANKY_STAMP)
	$(BIN)/lint-imports
	$(BIN)/ruff check .
	$(BIN)/python -m pytest -q

demo: $(STAMP)
	$(BIN)/skinsafe demo

bench: $(STAMP)
	for b in jacobians design sensing import retraction modulation safety pfl serial; do $(BIN)/skinsafe bench $$b || exit 1; done

clean:
	rm -rf $(VENV) $(FRANKY) out build *.egg-info

# The Blender extension zip (dist/skinsafe-<version>.zip) with the skinsafe wheel and its runtime deps.
.PHONY: addon
addon: $(STAMP)
	$(BIN)/python addon/package.py --out dist
