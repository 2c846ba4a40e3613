"""The add-on's operators and manifest as Blender reads them: every operator that writes the design
has UNDO and a poll that refuses a scene without a robot or skin; File > Export holds the taxel map,
MuJoCo scene, URDF, GenTact taxel CSV and FPC fabrication entries (the last tested in test_addon_fab), the
URDF entry writes a file MuJoCo compiles and the CSV holds every taxel as the design has it; the manifest passes
Blender's own strict validator and declares the network permission (Live opens TCP)."""
import csv
import importlib.util
from pathlib import Path

import bpy
import mujoco
import numpy as np
import pytest

import skinsafe.addon as addon_pkg
from skinsafe.addon import (
    analysis,
    check,
    cover,
    deploy,
    export,
    findings,
    fpc_modules,
    frames,
    live,
    pfl,
    place_tool,
    robot,
)
from skinsafe.addon import blender_to_core as b2c

E = 0.13585 - 0.1197  # UR5 forearm capsule axis height (body frame)
WRITERS = ("import_robot", "set_pose", "place_module", "regenerate", "remove_module", "assign_boards",
           "map_jacobians", "coverage", "check", "cover_link", "map_pfl", "place_skin", "show_finding")


def _classes():
    every = (*robot.OPERATORS, *fpc_modules.OPERATORS, *analysis.OPERATORS, *check.OPERATORS, *export.OPERATORS,
             *frames.OPERATORS, cover.SKINSAFE_OT_cover_link, pfl.SKINSAFE_OT_map_pfl, place_tool.SKINSAFE_OT_place_skin,
             *findings.CLASSES, *deploy.CLASSES, *live.CLASSES)
    return {c.bl_idname.split(".")[1]: c for c in every if issubclass(c, bpy.types.Operator)}


def test_design_writers_have_undo_and_every_operator_a_poll_that_refuses_an_empty_scene():
    ops = _classes()
    assert len(ops) == 22
    for name in WRITERS:
        assert {"REGISTER", "UNDO"} <= set(ops[name].bl_options), name
    assert all(any("poll" in vars(k) for k in c.__mro__ if k.__module__.startswith("skinsafe")) for c in ops.values())
    bpy.ops.wm.read_homefile(use_empty=True)
    b2c.clear_caches()
    allowed = {n for n in ops if getattr(bpy.ops.skinsafe, n).poll()}
    assert allowed == {"import_robot"}  # no robot, no skin, no live source: nothing else to do
    bpy.ops.skinsafe.import_robot(source="ur5")
    allowed = {n for n in ops if getattr(bpy.ops.skinsafe, n).poll()}
    assert allowed == {"import_robot", "set_pose", "place_module", "cover_link", "place_skin"}


def test_file_export_menu_and_the_urdf_entry(tmp_path):
    drawn = [f for f in bpy.types.TOPBAR_MT_file_export.draw._draw_funcs if f is export.export_menu]
    assert len(drawn) == 1
    assert [op.bl_idname for op, _ in export.EXPORTS] == ["skinsafe.export_taxel_map", "skinsafe.export_mjcf",
                                                             "skinsafe.export_urdf", "skinsafe.export_taxel_csv",
                                                             "skinsafe.export_fab"]
    bpy.ops.wm.read_homefile(use_empty=True)
    b2c.clear_caches()
    bpy.ops.skinsafe.import_robot(source="ur5")
    bpy.ops.skinsafe.place_module(body="forearm_link", anchor=(-0.25, 0, E + 0.05), direction=(-1, 0, 0),
                                  use_cursor=False)
    path = tmp_path / "skin.urdf"
    assert bpy.ops.skinsafe.export_urdf(filepath=str(path)) == {"FINISHED"}
    model = mujoco.MjModel.from_xml_path(str(path))
    ids = b2c.design_of(bpy.context.scene).taxels.ids
    assert all(mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, f"taxel_{int(i)}") >= 0 for i in ids)
    with pytest.raises(RuntimeError, match="Permission denied|not a directory|No such file"):
        bpy.ops.skinsafe.export_urdf(filepath="/proc/skin.urdf")
    # the GenTact taxel CSV: a row per taxel, link-frame positions, half the diameter, the link's path
    assert bpy.ops.skinsafe.export_taxel_csv(filepath=str(tmp_path / "skin.csv")) == {"FINISHED"}
    with open(tmp_path / "skin.csv", newline="") as f:
        rows = list(csv.reader(f))
    design = b2c.design_of(bpy.context.scene)
    assert rows[0] == ["Index", "X", "Y", "Z", "Radius", "Parent"] and len(rows) == 1 + design.n_taxels
    assert [int(r[0]) for r in rows[1:]] == design.taxels.ids.tolist()
    assert np.array_equal(np.array([[float(v) for v in r[1:4]] for r in rows[1:]]), design.taxels.positions)
    assert {float(r[4]) for r in rows[1:]} == {design.modules[0].taxel_diameter / 2} and abs(float(rows[1][4]) - 0.003) < 1e-9
    assert {r[5] for r in rows[1:]} == {"/ur5/base_link/shoulder_link/upper_arm_link/forearm_link"}


def test_manifest_passes_blenders_validator_and_declares_network():
    cli = Path(bpy.utils.system_resource("SCRIPTS")) / "addons_core" / "bl_pkg" / "cli" / "blender_ext.py"
    spec = importlib.util.spec_from_file_location("blender_ext", cli)
    ext = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(ext)
    manifest = ext.pkg_manifest_from_toml_and_validate_all_errors(
        str(Path(addon_pkg.__file__).parent / "blender_manifest.toml"), strict=True)
    assert not isinstance(manifest, list), manifest
    assert set(manifest.permissions) == {"files", "network"}
