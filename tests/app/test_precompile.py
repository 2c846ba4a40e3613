"""`skinsafe precompile`: every kernel numba caches gets a cache entry, and one without an entry is named."""
import argparse
import os
import re
import subprocess
import sys
from pathlib import Path

from skinsafe.core.app import precompile

ROOT = Path(__file__).resolve().parents[2]


def test_the_kernels_found_are_the_cached_ones_the_sources_declare():
    found = {f"{m}.{k.__name__}" for m, ks in precompile.cached_kernels().items() for k in ks}
    declared = set()
    for pkg, folder in (("skinsafe.core", "core"), ("skinsafe.hardware", "hardware")):
        for path in (ROOT / folder).rglob("*.py"):
            mod = ".".join([pkg, *path.relative_to(ROOT / folder).with_suffix("").parts])
            for deco, name in re.findall(r"@numba\.njit\(([^)]*)\)\s*\ndef (\w+)", path.read_text()):
                if "cache=True" in deco and 'inline="always"' not in deco:
                    declared.add(f"{mod}.{name}")
    assert found == declared and len(found) >= 45, sorted(found ^ declared)
    assert {"skinsafe.core.safety.qp._levels", "skinsafe.core.sim.readout._readout",
            "skinsafe.core.design.surface_kernels.march"} <= found


def test_precompile_fills_the_cache_and_an_empty_cache_is_named_kernel_by_kernel(tmp_path):
    assert precompile.run(argparse.Namespace(quiet=True)) == 0
    assert precompile.missing() == []
    every = sorted(f"{m}.{k.__name__}" for m, ks in precompile.cached_kernels().items() for k in ks)
    code = "from skinsafe.core.app.precompile import missing; print('\\n'.join(sorted(missing())))"
    out = subprocess.run([sys.executable, "-c", code], env={**os.environ, "NUMBA_CACHE_DIR": str(tmp_path)},
                         capture_output=True, text=True, check=True).stdout.split()
    assert out == every
