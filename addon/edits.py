"""Edits, through Blender's app handlers: the design follows the module objects after every edit
(`designer.sync`: delete, duplicate, paste, append, rename, undo/redo), moved modules re-generate live, a scale
is applied once when its transform ends (a timer waits for it: Blender gives no transform-end event), and a loaded file
is checked the same way. All are removed on unregister (a bpy process hangs at exit otherwise); `step`
does one round without the event loop."""
import contextlib

import bpy
from bpy.app.handlers import persistent

from skinsafe.addon import blender_to_core as b2c
from skinsafe.addon import designer, integrity

_busy = False


def transforming() -> bool:
    """Whether an interactive transform (grab, rotate, scale, mirror) is running in some window."""
    wm = bpy.context.window_manager
    return any(op.bl_idname.upper().startswith("TRANSFORM") for w in (wm.windows if wm else ())
               for op in w.modal_operators)  # TRANSFORM_OT_resize (or transform.resize)


def step(scene, apply_scale: bool = True) -> list[str]:
    """One round: split joined modules back out, put the robot's links and the module objects back true
    (`integrity`: what an Object-menu edit changed, said in the panel's message), sync the design with the objects,
    then re-generate moved modules (scaled ones only with `apply_scale`). Returns the problems; the last is shown in the panel."""
    global _busy
    if _busy or not scene.skinsafe.robot_kind:
        return []
    _busy = True
    try:
        said = integrity.joined(scene)
        more, kept = integrity.links(scene)
        said += more + integrity.modules(scene, kept)
        if said:
            scene.skinsafe.message = "; ".join(said)
        errors = designer.sync(scene)
        if scene.skinsafe.auto_regenerate:
            errors += designer.regenerate_moved(scene, apply_scale)
        if errors:
            scene.skinsafe.error = errors[-1]
        return errors
    finally:
        _busy = False


@contextlib.contextmanager
def paused():
    """The add-on's own passing edits (a picture's cell tiles): no step runs while they stand, so they are
    neither synced into the design nor undone as a user's edit."""
    global _busy
    was, _busy = _busy, True
    try:
        yield
    finally:
        _busy = was


@persistent
def on_depsgraph_update(scene, depsgraph=None):
    busy = transforming()
    step(scene, apply_scale=not busy)
    if busy and not bpy.app.timers.is_registered(_after_transform):
        bpy.app.timers.register(_after_transform, first_interval=0.1)


def _after_transform():
    if transforming():
        return 0.1
    step(bpy.context.scene)
    return None


@persistent
def on_load(*_):
    b2c.clear_caches()
    for scene in bpy.data.scenes:
        said = integrity.converted_ids(scene) if scene.skinsafe.robot_kind else ""
        step(scene)
        if said:  # said last: the panel's message and the file's first report
            scene.skinsafe.message = said
            print(f"skinsafe: {said}")


HANDLERS = ((bpy.app.handlers.depsgraph_update_post, on_depsgraph_update), (bpy.app.handlers.load_post, on_load))


def register():
    for lst, fn in HANDLERS:
        if fn not in lst:
            lst.append(fn)


def unregister():
    if bpy.app.timers.is_registered(_after_transform):
        bpy.app.timers.unregister(_after_transform)
    for lst, fn in reversed(HANDLERS):
        while fn in lst:
            lst.remove(fn)
