# `make test` and `make demo` set everything up on a fresh machine (a .venv with the pinned packages).
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed-stamp

.PHONY: test demo bench clean readme-figures robots franky-sim docs bpy-only

# the set-up steps a target needs run two at a time (two cores: the installs overlap; each step's own
# prerequisites still come first)
MAKEFLAGS += --jobs=2

# franky-sim 1.0.4 (the FR3 over the libfranka protocol, MuJoCo inside) needs numpy >= 2, which bpy
# forbids: it gets its own environment, with the numpy/numba parts of skinsafe that its world runs
# (core/sim/franky_world.py: the skin readout and the force feed).
FRANKY       := .venv-franky
FRANKY_PKGS_STAMP := $(FRANKY)/.packages-stamp
FRANKY_STAMP := $(FRANKY)/.installed-stamp
FRANKY_PKGS  := franky-sim==1.0.4 mujoco==4.0.0 pin==4.1.0 numpy==2.4.6 numba==0.68.1 scipy==1.17.1 pyserial==3.5 \
               tqdm==4.70.1 pytest==9.2.0 hypothesis==6.170.17

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e ".[test]"
	touch $(STAMP)

$(FRANKY_PKGS_STAMP): Makefile
	test -x $(FRANKY)/bin/python || $(PYTHON) -m venv $(FRANKY)
	$(FRANKY)/bin/python -m pip install -q --upgrade pip
	$(FRANKY)/bin/python -m pip install -q $(FRANKY_PKGS)
	touch $(FRANKY_PKGS_STAMP)

# skinsafe itself after .venv's editable install (two at once would build its metadata in the same tree)
$(FRANKY_STAMP): $(FRANKY_PKGS_STAMP) $(STAMP) pyproject.toml
	$(FRANKY)/bin/python -m pip install -q --no-deps -e .
	touch $(FRANKY_STAMP)

franky-sim: $(FRANKY_STAMP)

# Public robot descriptions not shipped in blend_assets/robots/ (from PyPI; cached): see its README.md
ROBOTS_STAMP := blend_assets/robots/example-robot-data/FETCHED.json
robots: $(ROBOTS_STAMP)
$(ROBOTS_STAMP): blend_assets/robots/fetch.py $(STAMP)
	$(BIN)/python blend_assets/robots/fetch.py

# the clean-Blender test's bpy-only environments, one per tested Blender (tests/addon/bpy_only.py: 4.5 LTS and
# 5.0.1 on Python 3.11, 5.3.0 on Python 3.13 from PATH or pyenv; under $SKINSAFE_CACHE, a 300-400 MB wheel and
# about a minute each, two at a time; at once when they are there)
bpy-only: $(STAMP)
	$(BIN)/python tests/addon/bpy_only.py > /dev/null

# numba's kernels compiled into its cache once, before anything runs them: a fresh clone's test processes would
# otherwise each compile those they meet before the cache holds them (a second when the cache is already full);
# first after .venv's install, the longest of the steps that follow it
.PHONY: precompile
precompile: $(STAMP)
	$(BIN)/skinsafe precompile --quiet

test: $(STAMP) precompile $(ROBOTS_STAMP) $(FRANKY_STAMP) test-numpy2 docs bpy-only
	$(BIN)/lint-imports
	$(BIN)/ruff check .
	$(BIN)/python -m pytest -q -n auto --dist loadgroup --durations=20

# The documentation site (docs/, mkdocs.yml) into build/site; --strict: a broken link or reference fails it
docs: $(STAMP)
	NO_MKDOCS_2_WARNING=1 $(BIN)/mkdocs build --strict --quiet

# hardware/ runs under numpy 2 too (emulated boards run in franky-sim's environment): its protocol, stream
# and link-fault tests in franky-sim's numpy-2 environment (no bpy there: no conftest)
.PHONY: test-numpy2
test-numpy2: $(FRANKY_STAMP)
	$(FRANKY)/bin/python -c "import numpy; assert numpy.__version__ >= '2', numpy.__version__"
	$(FRANKY)/bin/python -m pytest -q --noconftest -p no:cacheprovider tests/hardware/test_hardware_protocol.py \
		tests/hardware/test_hardware_protocol_doc.py tests/hardware/test_hardware_stream.py \
		tests/hardware/test_hardware_link_faults.py

demo: $(STAMP) $(ROBOTS_STAMP)
	$(BIN)/skinsafe demo $(DEMO_ARGS)

bench: $(STAMP) $(ROBOTS_STAMP)
	for b in jacobians design sensing import retraction modulation safety pfl serial runtime; do $(BIN)/skinsafe bench $$b || exit 1; done

clean:
	rm -rf $(VENV) $(FRANKY) out build *.egg-info

# The Blender extension zip (dist/skinsafe-<version>.zip) with the skinsafe wheel and its runtime deps.
.PHONY: addon
addon: $(STAMP)
	$(BIN)/python addon/package.py --out dist

# The README's figures from the committed results files (core/app/readme.py); `make test` checks them.
readme-figures: $(STAMP)
	$(BIN)/skinsafe readme
