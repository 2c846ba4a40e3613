# `make test` and `make demo` set everything up on a fresh machine (a .venv with the pinned packages).
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed-stamp

.PHONY: test demo bench clean readme-figures robots

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e ".[test]"
	touch $(STAMP)

# Public robot descriptions not shipped in blend_assets/robots/ (from PyPI; cached): see its README.md
ROBOTS_STAMP := blend_assets/robots/example-robot-data/FETCHED.json
robots: $(ROBOTS_STAMP)
$(ROBOTS_STAMP): blend_assets/robots/fetch.py $(STAMP)
	$(BIN)/python blend_assets/robots/fetch.py

test: $(STAMP) $(ROBOTS_STAMP)
	$(BIN)/lint-imports
	$(BIN)/ruff check .
	$(BIN)/python -m pytest -q

demo: $(STAMP) $(ROBOTS_STAMP)
	$(BIN)/skinsafe demo $(DEMO_ARGS)

bench: $(STAMP) $(ROBOTS_STAMP)
	for b in jacobians design sensing import retraction modulation safety pfl serial; do $(BIN)/skinsafe bench $$b || exit 1; done

clean:
	rm -rf $(VENV) out build *.egg-info

# The Blender extension zip (dist/skinsafe-<version>.zip) with the skinsafe wheel and its runtime deps.
.PHONY: addon
addon: $(STAMP)
	$(BIN)/python addon/package.py --out dist

# The README's figures from the committed results files (core/app/readme.py); `make test` checks them.
readme-figures: $(STAMP)
	$(BIN)/skinsafe readme
