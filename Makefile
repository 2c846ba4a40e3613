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

test: $(STAMP) $(ROBOTS_STAMP) test-numpy2
	$(BIN)/lint-imports
	$(BIN)/ruff check .
	$(BIN)/python -m pytest -q

# hardware/ runs under numpy 2 too (emulated boards may run in franky-sim's environment): its protocol,
# stream and link-fault tests in a venv with numpy 2 and only hardware's own dependencies (no bpy: no conftest)
NP2       := .venv-numpy2
NP2_STAMP := $(NP2)/.installed-stamp
.PHONY: test-numpy2
$(NP2_STAMP): pyproject.toml
	test -x $(NP2)/bin/python || $(PYTHON) -m venv $(NP2)
	$(NP2)/bin/python -m pip install -q "numpy>=2,<3" "pyserial>=3.5" "tqdm>=4.66" "pytest>=8" "hypothesis>=6.100"
	$(NP2)/bin/python -m pip install -q --no-deps -e .
	touch $(NP2_STAMP)

test-numpy2: $(NP2_STAMP)
	$(NP2)/bin/python -c "import numpy; assert numpy.__version__ >= '2', numpy.__version__"
	$(NP2)/bin/python -m pytest -q --noconftest -p no:cacheprovider tests/hardware/test_hardware_protocol.py \
		tests/hardware/test_hardware_protocol_doc.py tests/hardware/test_hardware_stream.py \
		tests/hardware/test_hardware_link_faults.py

demo: $(STAMP) $(ROBOTS_STAMP)
	$(BIN)/skinsafe demo $(DEMO_ARGS)

bench: $(STAMP) $(ROBOTS_STAMP)
	for b in jacobians design sensing import retraction modulation safety pfl serial runtime; do $(BIN)/skinsafe bench $$b || exit 1; done

clean:
	rm -rf $(VENV) $(NP2) out build *.egg-info

# The Blender extension zip (dist/skinsafe-<version>.zip) with the skinsafe wheel and its runtime deps.
.PHONY: addon
addon: $(STAMP)
	$(BIN)/python addon/package.py --out dist

# The README's figures from the committed results files (core/app/readme.py); `make test` checks them.
readme-figures: $(STAMP)
	$(BIN)/skinsafe readme
