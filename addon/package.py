"""Build the Blender extension zip: the add-on files, a skinsafe wheel built from this checkout
and (unless --no-deps) the wheels of what the add-on's import path loads that Blender lacks.

    python addon/package.py [--out dist] [--no-deps]

Runs Blender's own extension builder (`blender --command extension build`, here through the bpy
module's bundled `blender_ext.py`), which validates the manifest and writes
`skinsafe-<version>.zip`. Not shipped in the zip (see blender_manifest.toml)."""
from __future__ import annotations

import argparse
import importlib.util
import re
import shutil
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
# What the add-on's import path loads beyond Blender's Python (which ships numpy and requests), as
# measured by tests/addon/test_clean_install.py in a virtual environment holding only bpy: MuJoCo
# (mujoco-core holds its compiled library; its viewers are never imported) and scipy for robots,
# surfaces and placement; trimesh, pycollada (with python-dateutil, six), xacro and PyYAML read
# ROS descriptions; pymeshlab decimates CAD meshes above the per-link triangle budget; numba and
# llvmlite for the body surfaces' closest-point kernels (core/design/surface_kernels.py, loaded by the
# first surface, never at enable) and the PFL heat map; mcap, mcap-ros2-support and lz4 read a run's
# record for the live link (addon/live.py, on attach); pyserial talks to the boards (addon/deploy.py, on Deploy);
# kiutils and ezdxf (with pyparsing, fonttools, typing_extensions) write the FPC fabrication files (File > Export);
# potpourri3d traces the independent round trip of each module a cover places (core/design/roundtrip.py).
DEPS = ["mujoco", "mujoco-core", "scipy", "trimesh", "pycollada", "python-dateutil", "six", "xacro", "PyYAML",
        "pymeshlab", "numba", "llvmlite", "mcap", "mcap-ros2-support", "lz4", "pyserial", "kiutils", "ezdxf",
        "pyparsing", "fonttools", "typing_extensions", "potpourri3d"]
# The platform the manifest names (`platforms = ["linux-x64"]`: glibc 2.35+, pymeshlab's floor; pip
# does not widen a --platform to older manylinux tags itself).
PLATFORM = [a for glibc in range(35, 16, -1) for a in ("--platform", f"manylinux_2_{glibc}_x86_64")] + [
    "--platform", "manylinux2014_x86_64", "--implementation", "cp", "--only-binary=:all:"]
# The Pythons of the Blenders the manifest admits: 3.11 (Blender 4.2-5.0) and 3.13 (5.1 and later). The zip
# carries each one's wheels; Blender installs those matching its own Python.
PYTHONS = ("3.11", "3.13")


def blender_ext() -> Path:
    spec = importlib.util.find_spec("bpy")
    if spec is None or spec.origin is None:
        sys.exit("package: the bpy module is not installed; run with the project's venv python")
    found = sorted(Path(spec.origin).parent.glob("*/scripts/addons_core/bl_pkg/cli/blender_ext.py"))
    if not found:
        sys.exit("package: blender_ext.py not found in the bpy module; use `blender --command extension build`")
    return found[-1]


def build(out: Path, with_deps: bool = True) -> Path:
    out = out.resolve()  # the builder runs in the staging folder
    stage = ROOT / "build" / "addon" / "skinsafe"
    shutil.rmtree(stage, ignore_errors=True)
    wheels = stage / "wheels"
    wheels.mkdir(parents=True)
    for f in list(HERE.glob("*.py")) + [HERE / "blender_manifest.toml"]:
        if f.name != "package.py":
            shutil.copy2(f, stage / f.name)
    pip = [sys.executable, "-m", "pip", "--disable-pip-version-check", "-q"]
    subprocess.run(pip + ["wheel", "--no-deps", "--no-build-isolation", "-w", str(wheels), str(ROOT)], check=True)
    if with_deps:
        from importlib.metadata import version  # the versions this checkout is tested with
        pinned = [f"{d}=={version(d)}" for d in DEPS]
        for python in PYTHONS:  # a pure-Python wheel comes once: pip keeps the file already there
            subprocess.run(pip + ["download", "--no-deps", "-d", str(wheels), "--python-version", python] + PLATFORM
                           + pinned, check=True)
    names = sorted(f"./wheels/{w.name}" for w in wheels.glob("*.whl"))
    manifest = stage / "blender_manifest.toml"
    text = re.sub(r"(?m)^wheels = \[\]$", "wheels = [\n" + "".join(f'  "{n}",\n' for n in names) + "]",
                  manifest.read_text())
    manifest.write_text(text)
    out.mkdir(parents=True, exist_ok=True)
    version = re.search(r'(?m)^version = "([^"]+)"', text).group(1)
    target = out / f"skinsafe-{version}.zip"
    subprocess.run([sys.executable, str(blender_ext()), "build", "--source-dir", str(stage),
                    "--output-filepath", str(target)], check=True, cwd=stage)
    return target


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", default=str(ROOT / "dist"), help="folder for the zip (default dist/)")
    p.add_argument("--no-deps", action="store_true", help="bundle only the skinsafe wheel (offline builds, tests)")
    a = p.parse_args()
    print(build(Path(a.out), not a.no_deps))
    return 0


if __name__ == "__main__":
    sys.exit(main())
