"""App handlers: live re-generation of moved modules and cache reset on file load. Both are
removed on unregister (a bpy process hangs at exit otherwise); the re-generation step is
`designer.regenerate_moved`, callable without the event loop."""
import bpy
from bpy.app.handlers import persistent

from skinsafe.addon import blender_to_core as b2c
from skinsafe.addon import designer

_busy = False


@persistent
def on_depsgraph_update(scene, depsgraph=None):
    global _busy
    if _busy or not scene.skinsafe.auto_regenerate or not scene.skinsafe.robot_kind:
        return
    _busy = True
    try:
        errors = designer.regenerate_moved(scene)
        if errors:
            scene.skinsafe.error = errors[-1]
    finally:
        _busy = False


@persistent
def on_load(*_):
    b2c.clear_caches()


HANDLERS = ((bpy.app.handlers.depsgraph_update_post, on_depsgraph_update), (bpy.app.handlers.load_post, on_load))


def register():
    for lst, fn in HANDLERS:
        if fn not in lst:
            lst.append(fn)


def unregister():
    for lst, fn in reversed(HANDLERS):
        while fn in lst:
            lst.remove(fn)
