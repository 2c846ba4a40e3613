# `make test` and `make demo` set everything up on a fresh machine (a .venv with the pinned packages).
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed-stamp

.PHONY: test demo bench clean

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e ".[test]"
	touch $(STAMP)

test: $(STAMP)
	$(BIN)/lint-imports
	$(BIN)/ruff check .
	$(BIN)/python -m pytest -q

demo: $(STAMP)
	$(BIN)/skinsafe demo

bench: $(STAMP)
	for b in jacobians design sensing import retraction modulation safety pfl serial runtime; do $(BIN)/skinsafe bench $$b || exit 1; done

clean:
	rm -rf $(VENV) out build *.egg-info

# The Blender extension zip (dist/skinsafe-<version>.zip) with the skinsafe wheel and its runtime deps.
.PHONY: addon
addon: $(STAMP)
	$(BIN)/python addon/package.py --out dist
