"""Build blend_assets/ur5_skin.blend: the UR5 with a sample skin over the upper arm, forearm and
wrist, made with the add-on's own operators (run headless with the bpy module):

    .venv/bin/python blend_assets/build_sample.py [--out blend_assets/ur5_skin.blend]
"""
import argparse
import sys
from pathlib import Path

import bpy  # first: before anything that could import pymeshlab

import skinsafe.addon as addon
from skinsafe.addon import blender_to_core as b2c
from skinsafe.core.design.placement import ring_layout
from skinsafe.core.design.sample import sample_bodies, turned_poses
from skinsafe.core.skin.model import DesignError, Module

PITCH = 0.008
TEMPLATE = Module(id=0, name="fpc8", body="", rows=8, cols=8, pitch=PITCH, taxel_diameter=0.6 * PITCH,
                  margin=0.2 * PITCH, min_bend_radius=0.01)


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
        poses = turned_poses(robot.model, robot.home)  # slots under a joint housing are left out
        for body in sample_bodies(robot.model):
            for anchor, direction in ring_layout(robot.model, body, TEMPLATE, poses):
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
