"""The Place Skin tool's benchmark in a fresh process (`skinsafe bench design` starts it):
`python -m skinsafe.addon.bench_tool T0` prints one JSON row, `first_place_s` and `preview_ms`."""
import json
import os
import sys
import time

import bpy  # first: before anything that could import pymeshlab
import numpy as np

from skinsafe.addon import blender_to_core as b2c
from skinsafe.addon import place_tool
from skinsafe.addon import register as register_addon
from skinsafe.addon import unregister as unregister_addon


def bench(t0: float, moves: int = 50) -> dict:
    """This process's first placement (the UR5 imported, an 8x8 module placed with the tool along a ray) in
    s since `t0` (time.time() when the process was started), then the tool's work per mouse move (`preview`:
    ray cast and placement check) median over `moves` rays along the forearm, in ms; `loadavg`: the machine's
    1, 5 and 15-minute load averages as it ran (both figures are wall-clock times)."""
    load = os.getloadavg()
    register_addon()
    try:
        bpy.ops.wm.read_homefile(use_empty=True)
        scene = bpy.context.scene
        bpy.ops.skinsafe.import_robot(source="ur5")
        st = scene.skinsafe.new_module
        st.rows, st.cols, st.pitch, st.taxel_diameter, st.margin = 8, 8, 0.01, 0.006, 0.002
        W = np.array(b2c.body_objects(scene)["forearm_link"].matrix_world)
        e = 0.13585 - 0.1197 + 0.04  # the forearm capsule's top (body frame)

        def ray(x):
            return tuple(W[:3, :3] @ (x, 0.0, e + 0.05) + W[:3, 3]), tuple(-W[:3, 2])

        o, d = ray(-0.3)
        assert bpy.ops.skinsafe.place_skin(ray_origin=o, ray_direction=d) == {"FINISHED"}
        first = time.time() - t0
        times = []
        for x in np.linspace(-0.2, -0.06, moves):
            o, d = ray(x)
            t = time.perf_counter()
            pv = place_tool.preview(scene, o, d)
            times.append(time.perf_counter() - t)
            assert pv.body == "forearm_link"
        return {"tool": "place_skin", "module": "8x8", "n_taxels": 64, "modules": 1, "first_place_s": first,
                "preview_ms": float(np.median(times) * 1e3), "preview_ms_max": float(np.max(times) * 1e3),
                "moves": moves, "loadavg": [round(x, 2) for x in load]}
    finally:
        unregister_addon()


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit("usage: python -m skinsafe.addon.bench_tool T0 (time.time() when the process was started)")
    print(json.dumps(bench(float(sys.argv[1]))))
