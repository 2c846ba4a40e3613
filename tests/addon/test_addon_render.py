"""The pictures' framing and taxel tiles (addon.headless), without rendering: every vertex of the
robot and its skin inside the camera's view, tiles filling the cells and put back afterwards."""
import bpy
import numpy as np

from skinsafe.addon import blender_to_core as b2c
from skinsafe.addon import headless

E = 0.13585 - 0.1197  # UR5 forearm capsule axis height (body frame)


def test_frame_holds_the_whole_robot_and_tiles_fill_cells():
    bpy.ops.wm.read_homefile(use_empty=True)
    b2c.clear_caches()
    scene = bpy.context.scene
    bpy.ops.skinsafe.import_robot(source="ur5")
    s = scene.skinsafe.new_module
    for k, v in {"rows": 4, "cols": 4, "pitch": 0.01, "taxel_diameter": 0.004, "margin": 0.002,
                 "min_bend_radius": 0.01}.items():
        setattr(s, k, v)
    assert bpy.ops.skinsafe.place_module(body="forearm_link", anchor=(-0.2, 0, E + 0.05), direction=(-1, 0, 0),
                                         use_cursor=False) == {"FINISHED"}
    objs = [o for o in scene.objects if o.type == "MESH"]
    view = (0.6, -1.0, 0.7)
    headless._frame(scene, objs, view, 400)
    cam = scene.camera
    R = np.array(cam.matrix_world)[:3, :3]
    rel = headless._world_points(objs) - np.array(cam.location)
    x, y, z = rel @ R[:, 0], rel @ R[:, 1], rel @ R[:, 2]
    r = scene.render
    half_w = cam.data.ortho_scale / 2 * r.resolution_x / max(r.resolution_x, r.resolution_y)
    half_h = cam.data.ortho_scale / 2 * r.resolution_y / max(r.resolution_x, r.resolution_y)
    assert np.abs(x).max() <= half_w and np.abs(y).max() <= half_h  # nothing cut off, the base included
    assert max(np.ptp(x) / (2 * half_w), np.ptp(y) / (2 * half_h)) > 0.9  # and the robot fills the picture
    assert (-z > cam.data.clip_start).all() and (-z < cam.data.clip_end).all()  # in front of the camera

    (module,) = b2c.module_objects(scene)
    before = np.array([v.co[:] for v in module.data.vertices])
    tiles = headless._CellTiles([module], {0: 0.01}, lift=0.0015)
    grown = np.array([v.co[:] for v in module.data.vertices]).reshape(-1, 6, 3)
    centre = grown.mean(axis=1, keepdims=True)
    assert np.allclose(np.linalg.norm(grown - centre, axis=2), 0.005, atol=1e-6)  # corners at half the pitch
    # lifted 1.5 mm off the forearm (a capsule along its body x axis at height E): away from its axis
    to_body = np.linalg.inv(np.array(b2c.body_objects(scene)["forearm_link"].matrix_world)) @ np.array(
        module.matrix_world)

    def radius(local):
        p = local @ to_body[:3, :3].T + to_body[:3, 3]
        return np.hypot(p[:, 1], p[:, 2] - E)

    lift = radius(centre[:, 0]) - radius(before.reshape(-1, 6, 3).mean(axis=1))
    assert np.allclose(lift, 0.0015, atol=5e-5)
    tiles.restore()
    assert np.array_equal(np.array([v.co[:] for v in module.data.vertices]), before)
