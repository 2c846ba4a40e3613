"""The promise to Blender users: the extension zip `make addon` builds installs into a clean
Blender of each tested release (4.5 LTS and this project's bpy on Python 3.11, the newest on Python 3.13:
a virtual environment holding only that bpy, a fresh user folder), enables, imports robots (built-in, and
a xacro file with a Collada mesh above the triangle budget), places a module, writes a taxel map, deploys
it to emulated boards, exports a MuJoCo scene and the fabrication files, follows Blender's own duplicate,
delete and undo of a module and paints the PFL map, with nothing of this project's environment on its path.
The map it wrote is then checked with the core from here. One Blender session per release; the zip is
built once.

The bpy-only environments (`bpy_only.py`: kept between runs under the user's cache folder, keyed by the bpy
and Python versions) are built by `make test` beside its other installs, or here when missing (about a
minute each)."""
import hashlib
import json
import shutil
import subprocess
import sys
import textwrap
import tomllib
import zipfile
from pathlib import Path

import numpy as np
import pytest
from bpy_only import BLENDERS, NoPython, bpy_only_python

from skinsafe.core.design.audit import audit
from skinsafe.core.design.placement import place_module
from skinsafe.core.design.surface import body_surface
from skinsafe.core.robot.models import build_ur5
from skinsafe.core.skin import taxel_map
from skinsafe.core.skin.boards import assign_boards
from skinsafe.core.skin.model import Module
from skinsafe.hardware.board_config import board_configs
from skinsafe.hardware.emulator import EmulatorProcess, flash_path

pytestmark = pytest.mark.xdist_group("clean-install")  # one worker: the zip is built once, each session runs once
ROOT = Path(__file__).resolve().parents[2]
SESSION = Path(__file__).with_name("clean_install_session.py")
E = 0.13585 - 0.1197  # UR5 forearm capsule axis height (body frame)
INERTIA = '<inertial><mass value="1"/><inertia ixx="0.01" iyy="0.01" izz="0.01" ixy="0" ixz="0" iyz="0"/></inertial>'
BUNDLED = {"skinsafe", "mujoco", "scipy", "trimesh", "collada", "dateutil", "six", "xacro", "yaml", "pymeshlab",
           "numba", "llvmlite", "serial", "kiutils", "ezdxf", "potpourri3d"}  # import names of the zip's wheels


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


def _version(text: str) -> tuple[int, ...]:
    return tuple(int(x) for x in text.split("."))


@pytest.fixture(scope="module")
def extension(tmp_path_factory):
    """The zip and the manifest in it."""
    tmp = tmp_path_factory.mktemp("extension")
    # `make addon` runs addon/package.py from the checkout; here from elsewhere, with a relative --out
    subprocess.run([sys.executable, str(ROOT / "addon" / "package.py"), "--out", "dist"], cwd=tmp, check=True,
                   capture_output=True)
    (zip_path,) = (tmp / "dist").glob("skinsafe-*.zip")
    with zipfile.ZipFile(zip_path) as z:
        return zip_path, tomllib.loads(z.read("blender_manifest.toml").decode())


@pytest.fixture(scope="module", params=BLENDERS, ids=lambda b: b.name)
def session(request, extension, tmp_path_factory):
    try:
        python = bpy_only_python(request.param)
    except NoPython as e:
        pytest.skip(str(e))
    tmp = tmp_path_factory.mktemp(f"clean_{request.param.name}")
    out = tmp / "out"
    out.mkdir()
    env = {"PATH": "/usr/bin:/bin", "HOME": str(tmp), "BLENDER_USER_RESOURCES": str(tmp / "user")}
    # the session's one board (a 24-taxel module: board 0 of the default 256 channels), emulated on a pty
    (board,), _ = assign_boards(np.array([0]), {0: 24}, 256)
    with EmulatorProcess([(board.uid, board.capacity)], tmp / "flash", "--link-dir", str(tmp / "ports")):
        r = subprocess.run([str(python), "-I", str(SESSION), str(extension[0]), str(out), str(_xacro_robot(tmp)),
                            str(tmp / "ports" / "board-*")], cwd=tmp, env=env, capture_output=True, text=True,
                           timeout=600)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    yield {**json.loads(r.stdout.strip().splitlines()[-1]), "out": out, "user": tmp / "user", "venv": python.parents[1],
           "flash": tmp / "flash", "blender": request.param}
    shutil.rmtree(tmp / "user")  # the installed wheels: 0.4 GB


def test_the_zip_carries_each_tested_blenders_wheels_and_admits_each(extension):
    _, manifest = extension
    lo, hi = _version(manifest["blender_version_min"]), _version(manifest["blender_version_max"])
    assert all(lo <= _version(b.bpy) < hi for b in BLENDERS), (lo, hi)  # the maximum is exclusive
    newest = max(_version(b.bpy) for b in BLENDERS)
    assert hi == (newest[0], newest[1] + 1, 0)  # up to the newest tested release's series, no later
    wheels = [Path(w).name for w in manifest["wheels"]]
    pythons = {"cp" + b.python.replace(".", "") for b in BLENDERS}
    assert pythons == {"cp311", "cp313"}
    for name in ("scipy", "mujoco_core", "numba", "llvmlite", "pymeshlab", "pyyaml", "lz4", "potpourri3d"):
        assert {w.split("-")[2] for w in wheels if w.split("-")[0].lower() == name} == pythons, name


def test_nothing_of_this_project_leaks_into_the_clean_blender(session):
    assert not any(session["present_before"].values()), session["present_before"]  # bpy and its own deps only
    ext = Path(session["extensions"])
    assert _inside(ext, session["user"]) and _inside(session["addon_file"], ext / "user_default" / "skinsafe")
    here = [Path(sys.prefix), ROOT]
    assert not [p for p in session["sys_path"] if any(_inside(p, h) for h in here)], session["sys_path"]
    allowed = [ext, session["venv"], Path(session["stdlib"])]  # the extension, bpy's venv, its Python's stdlib
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
    assert not loaded & {"torch", "ray", "gymnasium", "matplotlib", "daqp"}
    assert "serial" in top["deploy"] and not (top["enable"] | top["design"]) & {"serial"}  # pyserial on Deploy only
    assert {"kiutils", "ezdxf"} <= top["export"]  # the fabrication files
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


def test_deploy_from_the_clean_blender_writes_the_maps_board_configs(session):
    design = taxel_map.load(session["out"] / "ur5_skin.json", build_ur5().body_names)
    (cfg,) = board_configs(design)
    assert ": updated [committed]" in session["deployed"], session["deployed"]
    assert hashlib.sha256(flash_path(session["flash"], cfg.uid).read_bytes()).digest() == cfg.sha256
    fab = json.loads((session["out"] / "fab" / "fab.json").read_text())
    assert [m["pads"] for m in fab["modules"]] == [24] and (session["out"] / "fab" / "sheets.pdf").is_file()


def test_the_design_follows_blenders_duplicate_delete_and_undo(session):
    e = session["edits"]
    one, two = ["forearm_link_module0"], ["forearm_link_module0", "forearm_link_module0.001"]
    assert e["modules"] == [one, two, one, two] and e["taxels"] == [24, 48, 24, 48]
    assert e["copy_moved_off"] < 1e-6 and e["undo_off"] < 1e-9  # the copy's taxels moved with it, undo restores them


def test_the_docs_state_the_blenders_the_manifest_admits():
    manifest = tomllib.loads((ROOT / "addon" / "blender_manifest.toml").read_text())
    lo, hi = _version(manifest["blender_version_min"]), _version(manifest["blender_version_max"])
    span = f"Blender {lo[0]}.{lo[1]} to {hi[0]}.{hi[1] - 1}"  # the maximum is exclusive: x.y+1.0
    for doc in ("README.md", "docs/design/addon.md"):
        assert span in " ".join((ROOT / doc).read_text().split()), f"{doc} does not say {span!r}"
    install = (ROOT / "docs" / "design" / "addon.md").read_text()
    assert all(b.bpy in install for b in BLENDERS), "the install page names each tested bpy"
