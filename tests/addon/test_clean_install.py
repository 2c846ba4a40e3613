"""The promise to Blender users: the extension zip `make addon` builds installs into a clean
Blender (a virtual environment holding only bpy, a fresh user folder), enables, imports robots
(built-in, and a xacro file with a Collada mesh above the triangle budget), places a module,
writes a taxel map, exports a MuJoCo scene and paints the PFL map, with nothing of this
project's environment on its path. The map it wrote is then checked with the core from here.

The bpy-only environment (`bpy_only.py`: kept between runs under the user's cache folder, keyed by the bpy
version) is built by `make test` beside its other installs, or here when missing (about 40 s)."""
import json
import shutil
import subprocess
import sys
import sysconfig
import textwrap
from pathlib import Path

import numpy as np
import pytest
from bpy_only import bpy_only_python

from skinsafe.core.design.audit import audit
from skinsafe.core.design.placement import place_module
from skinsafe.core.design.surface import body_surface
from skinsafe.core.robot.models import build_ur5
from skinsafe.core.skin import taxel_map
from skinsafe.core.skin.model import Module

pytestmark = pytest.mark.xdist_group("clean-install")  # one worker: the module's clean Blender session runs once
ROOT = Path(__file__).resolve().parents[2]
SESSION = Path(__file__).with_name("clean_install_session.py")
E = 0.13585 - 0.1197  # UR5 forearm capsule axis height (body frame)
INERTIA = '<inertial><mass value="1"/><inertia ixx="0.01" iyy="0.01" izz="0.01" ixy="0" ixz="0" iyz="0"/></inertial>'
BUNDLED = {"skinsafe", "mujoco", "scipy", "trimesh", "collada", "dateutil", "six", "xacro", "yaml", "pymeshlab",
           "numba", "llvmlite"}  # import names of the zip's wheels


def _xacro_robot(folder: Path) -> Path:
    """A xacro robot whose link carries a Collada visual of 20,480 triangles (above the per-link
    budget: decimated by pymeshlab) beside a URDF primitive."""
    import trimesh

    ball = trimesh.creation.icosphere(subdivisions=5, radius=0.06)
    (folder / "ball.dae").write_bytes(trimesh.exchange.dae.export_collada(ball))
    path = folder / "bot.urdf.xacro"
    path.write_text(textwrap.dedent(f"""\
        <robot name="bot" xmlns:xacro="http://www.ros.org/wiki/xacro">
          <xacro:property name="reach" value="0.3"/>
          <link name="base"><collision><geometry><box size="0.2 0.2 0.1"/></geometry></collision>{INERTIA}</link>
          <link name="ball"><visual><geometry><mesh filename="ball.dae"/></geometry></visual>
            <collision><geometry><sphere radius="0.06"/></geometry></collision>{INERTIA}</link>
          <joint name="j1" type="revolute"><parent link="base"/><child link="ball"/><origin xyz="0 0 ${{reach}}"/>
            <axis xyz="0 0 1"/><limit lower="-2" upper="2" effort="1" velocity="1.5"/></joint>
        </robot>"""))
    return path


def _inside(path: str, folder: Path) -> bool:
    return Path(path).resolve().is_relative_to(folder.resolve())


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    python = bpy_only_python()
    tmp = tmp_path_factory.mktemp("clean_blender")
    # `make addon` runs addon/package.py from the checkout; here from elsewhere, with a relative --out
    subprocess.run([sys.executable, str(ROOT / "addon" / "package.py"), "--out", "dist"], cwd=tmp, check=True,
                   capture_output=True)
    (zip_path,) = (tmp / "dist").glob("skinsafe-*.zip")
    out = tmp / "out"
    out.mkdir()
    env = {"PATH": "/usr/bin:/bin", "HOME": str(tmp), "BLENDER_USER_RESOURCES": str(tmp / "user")}
    r = subprocess.run([str(python), "-I", str(SESSION), str(zip_path), str(out), str(_xacro_robot(tmp))],
                       cwd=tmp, env=env, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    yield {**json.loads(r.stdout.strip().splitlines()[-1]), "out": out, "user": tmp / "user", "venv": python.parents[1]}
    shutil.rmtree(tmp / "user")  # the installed wheels: 0.8 GB


def test_nothing_of_this_project_leaks_into_the_clean_blender(session):
    assert not any(session["present_before"].values()), session["present_before"]  # bpy and its own deps only
    ext = Path(session["extensions"])
    assert _inside(ext, session["user"]) and _inside(session["addon_file"], ext / "user_default" / "skinsafe")
    here = [Path(sys.prefix), ROOT]
    assert not [p for p in session["sys_path"] if any(_inside(p, h) for h in here)], session["sys_path"]
    allowed = [ext, session["venv"], Path(sysconfig.get_paths()["stdlib"])]  # the extension, bpy's venv, the stdlib
    for step, modules in session["steps"].items():
        for name, path in modules.items():
            if path is None:
                continue
            assert not any(_inside(path, h) for h in here), f"{step}: {name} came from this project: {path}"
            assert any(_inside(path, a) for a in allowed), f"{step}: {name} from {path}"
            if name.split(".")[0] in BUNDLED:
                assert _inside(path, ext), f"{step}: {name} from {path}, not the extension's wheels"


def test_the_import_path_loads_what_the_zip_bundles_and_no_compiler_until_a_surface_is_built(session):
    top = {step: {m.split(".")[0] for m in mods} for step, mods in session["steps"].items()}
    loaded = set().union(*top.values())
    assert {"skinsafe", "mujoco", "scipy", "trimesh", "collada", "xacro", "pymeshlab", "numba"} <= loaded
    assert not loaded & {"torch", "ray", "gymnasium", "matplotlib", "serial", "daqp"}
    # enabling loads no compiler: the first body surface (placing a module) loads the bundled numba
    # for its closest-point kernels (core/design/surface_kernels.py), the PFL map reuses it
    assert not top["enable"] & {"numba", "llvmlite"}
    assert "numba" in top["design"] and "llvmlite" in top["design"]
    assert "chest: safe approach speed" in session["message"]
    assert "pymeshlab" in top["xacro"] and "collada" in top["xacro"]  # the DAE above the budget


def test_the_map_written_in_blender_passes_the_core_checks(session):
    robot = build_ur5()
    path = session["out"] / "ur5_skin.json"
    design = taxel_map.load(path, robot.body_names)  # validated: frames, channels, boards, bodies
    assert design.n_taxels == 24 and [m.body for m in design.modules] == ["forearm_link"]
    assert audit(design, robot.model, robot.home, poses=4) == []
    # the same module placed headless by the core lands on the same taxels
    m = Module(0, "m", "forearm_link", rows=4, cols=6, pitch=0.01, taxel_diameter=0.006, margin=0.002,
               min_bend_radius=0.01)
    placed = place_module(body_surface(robot.model, "forearm_link"), m, anchor=[-0.2, 0, E + 0.05],
                          direction=[-1, 0, 0])
    assert np.abs(design.taxels.positions - placed.positions).max() < 1e-4
    assert np.abs(design.taxels.frames - placed.frames).max() < 1e-3
    assert (session["out"] / "ur5_scene" / "scene.xml").is_file()
