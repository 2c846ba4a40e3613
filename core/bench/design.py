"""`skinsafe bench design`: placing FPC modules (geodesic wrap, frames, checks) plus the Jacobian
mapping for all taxels, re-generating one 256-taxel module after a move, and Blender's Place Skin tool
(`first_place_s`, `preview_ms`).

Reference in the same run: the per-taxel `mj_jac` loop for the Jacobian mapping
(`TaxelKinematics.jacobians_loop`)."""
from __future__ import annotations

import time

import numpy as np
from tqdm import tqdm

from skinsafe.core.design.placement import build_design, place_module, replace_module, tile_bodies
from skinsafe.core.design.sample import sample_bodies
from skinsafe.core.design.surface import body_surfaces
from skinsafe.core.robot.kinematics import TaxelKinematics, retractability
from skinsafe.core.robot.models import build_ur5
from skinsafe.core.skin.model import Module, RobotRef
from skinsafe.core.timing import median_ms

TEMPLATE = Module(id=0, name="fpc16", body="", rows=16, cols=16, pitch=0.004, taxel_diameter=0.0024, margin=0.0008,
                  min_bend_radius=0.01)


def add_arguments(p) -> None:
    p.add_argument("--sizes", default="2560,10240", help="taxel totals to place (comma list, 256 per module)")
    p.add_argument("--repeat", type=int, default=3, help="repeats per size (median)")


def design_and_map(robot, surfaces, n: int):
    placed, refused = tile_bodies(surfaces, robot.model, TEMPLATE, sample_bodies(robot.model), limit=n)
    design = build_design(RobotRef("builtin", "ur5"), placed, capacity=1024)
    kin = TaxelKinematics(robot.model, design)
    J, _, frames = kin.jacobians(robot.home)
    return design, placed, kin, retractability(J, frames)


def rows(args) -> list[dict]:
    robot = build_ur5()
    t0 = time.perf_counter()
    surfaces = body_surfaces(robot.model, sample_bodies(robot.model))
    surf_s = time.perf_counter() - t0
    out = []
    for n in tqdm([int(s) for s in args.sizes.split(",")], desc="bench design", unit="size"):
        times = []
        for _ in range(args.repeat):
            t0 = time.perf_counter()
            design, placed, kin, _ = design_and_map(robot, surfaces, n)
            times.append(time.perf_counter() - t0)
        # re-generate one 256-taxel module after a 1 mm move along its rows
        p = placed[len(placed) // 2]
        others = [o for o in placed if o.module.body == p.module.body and o is not p]
        anchor = p.origin + 0.001 * p.origin_frame[:, 0]
        surf = surfaces[p.module.body]
        regen = median_ms(lambda: replace_module(design, place_module(surf, p.module, anchor, p.origin_frame[:, 0],
                                                                      others=others)), repeat=20)
        jac_ms = median_ms(lambda: kin.jacobians(robot.home), repeat=20)
        loop_ms = median_ms(lambda: kin.jacobians_loop(robot.home), repeat=3, warmup=1)
        out.append({"n_taxels": design.n_taxels, "modules": len(design.modules), "boards": len(design.boards),
                    "place_s": float(np.median(times)), "regen_ms": regen, "surfaces_s": surf_s,
                    "jac_ms": jac_ms, "jac_loop_ms": loop_ms, "jac_speedup": loop_ms / jac_ms})
    out.append(place_tool_row())
    return out


def place_tool_row() -> dict:
    """Blender's Place Skin tool in a fresh process (addon/bench_tool.py, its own process: bpy never shares
    one with this library): `first_place_s` from the process's start to its first 8x8 module placed,
    `preview_ms` its work per mouse move (ray cast and placement check)."""
    import json
    import subprocess
    import sys

    t0 = time.time()
    done = subprocess.run([sys.executable, "-m", "skinsafe.addon.bench_tool", str(t0)], capture_output=True,
                          text=True, timeout=600)
    if done.returncode:
        raise RuntimeError(f"bench design: the Place Skin run failed: {done.stderr.strip()[-400:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])
