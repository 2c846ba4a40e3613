"""Run by tests/addon/test_clean_install.py with the python of a virtual environment that holds
only bpy: install the extension zip into the Blender user folder the environment names, enable
it and design a skin through its operators as a Blender user would. Prints one JSON line: the
modules each step loaded (name -> file), sys.path and the extension folders.

    python -I clean_install_session.py ZIP OUT_DIR ROBOT_XACRO
"""
import importlib.util
import json
import sys
from pathlib import Path

# isort: off
import bpy  # first: it puts Blender's own modules (addon_utils) on sys.path
import addon_utils
# isort: on

zip_path, out, xacro = sys.argv[1], Path(sys.argv[2]), sys.argv[3]
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


present = {m: importlib.util.find_spec(m) is not None for m in ("skinsafe", "numba", "mujoco", "scipy", "torch", "ray")}
ok(bpy.ops.extensions.package_install_files(filepath=zip_path, repo="user_default", enable_on_install=True))
assert addon_utils.check(ADDON)[1], "the extension is installed but not enabled"
bpy.ops.wm.read_homefile(use_empty=True)  # keeps extensions enabled
step("enable")

ok(bpy.ops.skinsafe.import_robot(source="ur5"))
module_settings()
ok(bpy.ops.skinsafe.place_module(body="forearm_link", anchor=(-0.2, 0, E + 0.05), direction=(-1, 0, 0),
                                 use_cursor=False))
ok(bpy.ops.skinsafe.assign_boards())
ok(bpy.ops.skinsafe.map_jacobians())
ok(bpy.ops.skinsafe.check(poses=4))
ok(bpy.ops.skinsafe.export_taxel_map(filepath=str(out / "ur5_skin.json")))
step("design")

ok(bpy.ops.skinsafe.export_mjcf(directory=str(out / "ur5_scene")))
step("export")

ok(bpy.ops.skinsafe.import_robot(source="FILE", filepath=xacro))
step("xacro")

ok(bpy.ops.skinsafe.import_robot(source="ur5"))
ok(bpy.ops.skinsafe.place_module(body="forearm_link", anchor=(-0.2, 0, E + 0.05), direction=(-1, 0, 0),
                                 use_cursor=False))
ok(bpy.ops.skinsafe.map_pfl(region="chest"))
step("pfl")

ext = Path(bpy.utils.user_resource("EXTENSIONS"))
addon_file, message = sys.modules[ADDON].__file__, bpy.context.scene.skinsafe.message
bpy.ops.preferences.addon_disable(module=ADDON)  # a registered handler would keep bpy from exiting
print(json.dumps({"present_before": present, "steps": steps, "sys_path": sys.path, "extensions": str(ext),
                  "addon_file": addon_file,
                  "message": message}))
