"""Taxel frames: Toggle Taxel Frames, and the viewport overlay that draws them (x red, y green, z blue) or the
normals, with `gpu`. Its operator registers with the others' (addon/__init__.py); `register` adds the overlay,
only with a screen (never in background mode, where no viewport draws)."""
import bpy
import numpy as np

from skinsafe.addon import blender_to_core as b2c
from skinsafe.addon.shared import has_skin
from skinsafe.core.robot.kinematics import TaxelKinematics

_handle = None


def frame_lines(scene) -> tuple[np.ndarray, np.ndarray]:
    """Line segment end points (2k,3) and colours (2k,4) of the taxel frames at the scene's pose."""
    design = b2c.design_of(scene)
    if design is None or not design.n_taxels:
        return np.zeros((0, 3)), np.zeros((0, 4))
    kin = TaxelKinematics(b2c.robot_for(scene).model, design)
    pos, frames = kin.poses(b2c.pose(scene))
    s = scene.skinsafe
    axes = (2,) if s.frame_style == "NORMALS" else (0, 1, 2)
    colours = {0: (1, 0.2, 0.2, 1), 1: (0.2, 1, 0.2, 1), 2: (0.3, 0.5, 1, 1)}
    pts, col = [], []
    for a in axes:
        end = pos + s.frame_scale * frames[:, :, a]
        pts.append(np.stack([pos, end], 1).reshape(-1, 3))
        col.append(np.tile(colours[a], (2 * len(pos), 1)))
    return np.concatenate(pts), np.concatenate(col)


def _draw():
    scene = bpy.context.scene
    if not scene.skinsafe.show_frames or not scene.skinsafe.robot_kind:
        return
    import gpu
    from gpu_extras.batch import batch_for_shader
    pts, col = frame_lines(scene)
    if not len(pts):
        return
    shader = gpu.shader.from_builtin("FLAT_COLOR")
    batch = batch_for_shader(shader, "LINES", {"pos": pts.astype(np.float32), "color": col.astype(np.float32)})
    shader.bind()
    batch.draw(shader)


class SKINSAFE_OT_toggle_frames(bpy.types.Operator):
    """Draw the taxel frames (axes or normals) in the viewport"""

    bl_idname = "skinsafe.toggle_frames"
    bl_label = "Toggle Taxel Frames"

    poll = classmethod(lambda cls, context: has_skin(context))

    def execute(self, context):
        s = context.scene.skinsafe
        s.show_frames = not s.show_frames
        for area in context.screen.areas if context.screen else ():
            area.tag_redraw()
        return {"FINISHED"}


OPERATORS = (SKINSAFE_OT_toggle_frames,)


def register():
    global _handle
    if not bpy.app.background:
        _handle = bpy.types.SpaceView3D.draw_handler_add(_draw, (), "WINDOW", "POST_VIEW")


def unregister():
    global _handle
    if _handle is not None:
        bpy.types.SpaceView3D.draw_handler_remove(_handle, "WINDOW")
        _handle = None
