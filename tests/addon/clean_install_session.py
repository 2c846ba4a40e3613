"""Run by tests/addon/test_clean_install.py with the python of a virtual environment that holds
only bpy (one per tested Blender): install the extension zip into the Blender user folder the environment
names, enable it and design a skin through its operators as a Blender user would: place, check, File > Export,
Deploy to the (emulated) boards on PORTS, edit the module objects with Blender's own operators. Prints one JSON
line: the modules each step loaded (name -> file), sys.path, the extension folders and what the steps reported.

    python -I clean_install_session.py ZIP OUT_DIR ROBOT_XACRO PORTS
"""
import importlib.util
import json
import sys
import sysconfig
from pathlib import Path

import numpy as np

# isort: off
import bpy  # first: it puts Blender's own modules (addon_utils) on sys.path
import addon_utils
# isort: on

zip_path, out, xacro, ports = sys.argv[1], Path(sys.argv[2]), sys.argv[3], sys.argv[4]
ADDON = "bl_ext.user_default.skinsafe"
E = 0.13585 - 0.1197  # UR5 forearm capsule axis height (body frame)
steps, seen = {}, set(sys.modules)


def step(name: str) -> None:
    """Record the modules loaded since the last step, with the file each came from."""
    global seen
    new = set(sys.modules) - seen
    steps[name] = {m: getattr(sys.modules[m], "__file__", None) for m in sorted(new)}
    seen |= new


def module_settings(**kw) -> None:
    s = bpy.context.scene.skinsafe.new_module
    for k, v in {"template": "rect", "rows": 4, "cols": 6, "pitch": 0.01, "taxel_diameter": 0.006, "margin": 0.002,
                 "min_bend_radius": 0.01, "method": "geodesic", **kw}.items():
        setattr(s, k, v)


def ok(result) -> None:
    assert result == {"FINISHED"}, (result, bpy.context.scene.skinsafe.error)


def world_taxels() -> dict:
    """module object name -> its taxels' world positions, from the design after the edits' handlers ran."""
    from skinsafe.addon import blender_to_core as b2c  # the extension's, once installed

    bpy.context.view_layer.update()  # depsgraph_update_post: the add-on syncs the design with the objects
    scene = bpy.context.scene
    design, bodies = b2c.design_of(scene), b2c.body_objects(scene)
    out = {}
    for m in design.modules:
        W = np.array(bodies[m.body].matrix_world)
        out[m.name] = design.taxels.positions[design.taxels.module == m.id] @ W[:3, :3].T + W[:3, 3]
    return out


def select(name: str):
    for o in bpy.context.scene.objects:
        o.select_set(o.name == name)
    bpy.context.view_layer.objects.active = obj = bpy.data.objects[name]
    return obj


def use() -> dict:
    """Design, deploy, export, edit, import the xacro robot, paint the PFL map: what the steps reported."""
    ok(bpy.ops.skinsafe.import_robot(source="ur5"))
    module_settings()
    ok(bpy.ops.skinsafe.place_module(body="forearm_link", anchor=(-0.2, 0, E + 0.05), direction=(-1, 0, 0),
                                     use_cursor=False))
    ok(bpy.ops.skinsafe.assign_boards())
    ok(bpy.ops.skinsafe.map_jacobians())
    ok(bpy.ops.skinsafe.check(poses=4))
    ok(bpy.ops.skinsafe.export_taxel_map(filepath=str(out / "ur5_skin.json")))
    step("design")

    bpy.context.window_manager.skinsafe_deploy.ports = ports
    ok(bpy.ops.skinsafe.deploy("INVOKE_DEFAULT", dry_run=False))  # the panel's: dry run, confirmation, deploy
    deployed = bpy.context.window_manager.skinsafe_deploy.outcome
    step("deploy")

    ok(bpy.ops.skinsafe.export_mjcf(directory=str(out / "ur5_scene")))
    ok(bpy.ops.skinsafe.export_fab(directory=str(out)))
    step("export")

    # edits: a copy 12 cm along the forearm, deleted, the deletion undone (the push a window would do after each)
    bpy.ops.ed.undo_push(message="start")
    before = world_taxels()
    from skinsafe.addon.blender_to_core import body_objects  # the extension's

    axis = np.array(body_objects(bpy.context.scene)["forearm_link"].matrix_world)[:3, 0] * 0.12
    select("forearm_link_module0")
    ok(bpy.ops.object.duplicate_move(TRANSFORM_OT_translate={"value": tuple(axis)}))
    bpy.ops.ed.undo_push(message="Duplicate Objects")
    copied = world_taxels()
    select("forearm_link_module0.001")
    ok(bpy.ops.object.delete())
    bpy.ops.ed.undo_push(message="Delete")
    deleted = world_taxels()
    ok(bpy.ops.ed.undo())
    undone = world_taxels()
    copy = "forearm_link_module0.001"
    edits = {"modules": [sorted(t) for t in (before, copied, deleted, undone)],
             "taxels": [sum(map(len, t.values())) for t in (before, copied, deleted, undone)],
             "copy_moved_off": float(np.abs(copied[copy] - before["forearm_link_module0"] - axis).max()),
             "undo_off": float(np.abs(undone[copy] - copied[copy]).max())}
    step("edit")

    ok(bpy.ops.skinsafe.import_robot(source="FILE", filepath=xacro))
    step("xacro")

    ok(bpy.ops.skinsafe.import_robot(source="ur5"))
    ok(bpy.ops.skinsafe.place_module(body="forearm_link", anchor=(-0.2, 0, E + 0.05), direction=(-1, 0, 0),
                                     use_cursor=False))
    ok(bpy.ops.skinsafe.map_pfl(region="chest"))
    step("pfl")
    return {"message": bpy.context.scene.skinsafe.message, "deployed": deployed, "edits": edits}


present = {m: importlib.util.find_spec(m) is not None for m in ("skinsafe", "numba", "mujoco", "scipy", "torch", "ray")}
ok(bpy.ops.extensions.package_install_files(filepath=zip_path, repo="user_default", enable_on_install=True))
assert addon_utils.check(ADDON)[1], "the extension is installed but not enabled"
bpy.ops.wm.read_homefile(use_empty=True)  # keeps extensions enabled
step("enable")

try:
    used = use()
finally:  # a registered handler or timer would keep bpy from exiting, failed or not
    addon_file = sys.modules[ADDON].__file__
    bpy.ops.preferences.addon_disable(module=ADDON)
print(json.dumps({"present_before": present, "steps": steps, "sys_path": sys.path, "addon_file": addon_file,
                  "extensions": bpy.utils.user_resource("EXTENSIONS"), "stdlib": sysconfig.get_paths()["stdlib"],
                  **used}))
