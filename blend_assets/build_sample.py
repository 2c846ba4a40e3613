"""Build blend_assets/ur5_skin.blend: the UR5 with a sample skin over the upper arm, forearm and
wrist, made with the add-on's own operators (run headless with the bpy module):

    .venv/bin/python blend_assets/build_sample.py [--out blend_assets/ur5_skin.blend]
"""
import argparse
import sys
from pathlib import Path

import bpy  # first: before anything that could import pymeshlab
import mujoco
import numpy as np

import skinsafe.addon as addon
from skinsafe.addon import blender_to_core as b2c
from skinsafe.core.design.placement import clearance, ring_layout
from skinsafe.core.design.sample import SAMPLE_BODIES, exposed_span, turned_poses
from skinsafe.core.skin.model import DesignError, Module

PITCH = 0.008
TEMPLATE = Module(id=0, name="fpc8", body="", rows=8, cols=8, pitch=PITCH, taxel_diameter=0.6 * PITCH,
                  margin=0.2 * PITCH, min_bend_radius=0.01)


def exposed_slots(robot, body: str) -> list[tuple[np.ndarray, np.ndarray]]:
    """`ring_layout`'s slots on `body` whose cells no joint housing covers at every turned pose
    (`skinsafe check` refuses taxels buried there), as the core's sample skin does."""
    model, poses = robot.model, turned_poses(robot.model, robot.home)
    g = int(np.flatnonzero(model.geom_bodyid == model.body(body).id)[0])
    R = np.zeros(9)
    mujoco.mju_quat2Mat(R, model.geom_quat[g])
    R = R.reshape(3, 3)
    r = model.geom_size[g][0]
    half_along = (TEMPLATE.cols - 1) * TEMPLATE.pitch / 2 + clearance(TEMPLATE)
    half_angle = ((TEMPLATE.rows - 1) * TEMPLATE.pitch / 2 + clearance(TEMPLATE)) / r
    out = []
    for anchor, direction in ring_layout(model, body, TEMPLATE):
        rel = (anchor - model.geom_pos[g]) @ R  # geom frame
        phi = np.arctan2(rel[1], rel[0]) + np.linspace(-half_angle, half_angle, 7)
        span = exposed_span(model, poses, g, TEMPLATE.pitch, 0.5 * TEMPLATE.pitch, phi)
        if span and span[0] <= rel[2] - half_along + TEMPLATE.pitch / 2 and rel[2] + half_along - TEMPLATE.pitch / 2 <= span[1]:
            out.append((anchor, direction))
    return out


def build(out: Path, capacity: int = 512) -> dict:
    addon.register()
    try:
        bpy.ops.wm.read_homefile(use_empty=True)
        scene = bpy.context.scene
        bpy.ops.skinsafe.import_robot(source="ur5")
        s = scene.skinsafe
        s.auto_regenerate = True
        s.board_capacity = capacity
        nm = s.new_module
        for k in ("rows", "cols", "pitch", "taxel_diameter", "margin", "min_bend_radius"):
            setattr(nm, k, getattr(TEMPLATE, k))
        robot = b2c.robot_for(scene)
        refused = 0
        for body in SAMPLE_BODIES["ur5"]:
            for anchor, direction in exposed_slots(robot, body):
                try:
                    bpy.ops.skinsafe.place_module(body=body, anchor=anchor, direction=direction, use_cursor=False)
                except RuntimeError:  # refused (overlap at a joint, off the surface): skip that slot
                    refused += 1
        bpy.ops.skinsafe.assign_boards()
        bpy.ops.skinsafe.map_jacobians()
        bpy.ops.skinsafe.coverage()
        design = b2c.design_of(scene)
        if design.n_taxels < 1500 or len(design.boards) < 2:
            raise DesignError(f"sample: only {design.n_taxels} taxels on {len(design.boards)} boards")
        out.parent.mkdir(parents=True, exist_ok=True)
        bpy.ops.wm.save_as_mainfile(filepath=str(out), compress=True)
        return {"taxels": design.n_taxels, "modules": len(design.modules), "boards": len(design.boards),
                "refused_slots": refused, "bodies": sorted(set(m.body for m in design.modules))}
    finally:
        addon.unregister()


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", default=str(Path(__file__).with_name("ur5_skin.blend")))
    a = p.parse_args()
    print(build(Path(a.out)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
