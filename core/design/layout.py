"""Automatic layouts on any link: copies of one module template tiled over a body's surface.

Capsule and cylinder links are tiled in rings (`placement.ring_layout`); every other link (a
mesh from a robot's own description) by surface tiling: anchors spread over the surface by
farthest-point sampling at the module's span, rows along the link's principal axis, each
placed geodesically and kept only where `place_module` accepts it (on the surface, within the
FPC's bend radius and in-plane strain, no overlap) and the independent wrap of its flat pattern
agrees (`roundtrip.disagreement`).
"""
from __future__ import annotations

from dataclasses import replace

import mujoco
import numpy as np

from skinsafe.core.design.audit import SURFACE_TOL as OVERHANG_TOL
from skinsafe.core.design.audit import outline_overhang
from skinsafe.core.design.placement import (
    PlacedModule,
    PlacementError,
    clearance,
    place_module,
    placement_record,
    ring_layout,
)
from skinsafe.core.design.roundtrip import TOL as ROUNDTRIP_TOL
from skinsafe.core.design.roundtrip import disagreement
from skinsafe.core.design.surface import Surface
from skinsafe.core.skin.model import Module


def _has_ring(model, body: str) -> bool:
    """A body whose skin goes on a capsule or cylinder (built-in robots: no visual meshes)."""
    geoms = np.flatnonzero(model.geom_bodyid == model.body(body).id)
    if any(model.geom_contype[g] == 0 and model.geom_conaffinity[g] == 0 for g in geoms):
        return False
    return any(int(model.geom_type[g]) in (int(mujoco.mjtGeom.mjGEOM_CAPSULE), int(mujoco.mjtGeom.mjGEOM_CYLINDER))
               for g in geoms)


def surface_layout(surface: Surface, module: Module, seed: int = 0) -> list[tuple[np.ndarray, np.ndarray]]:
    """Anchors and row directions (body frame) spread over a surface at the module's span."""
    span = max(module.rows, module.cols) * module.pitch + 2 * clearance(module)
    pts = surface.random_points(int(min(20000, max(200, 20 * surface.area / span ** 2))), seed)
    centred = surface.vertices - surface.vertices.mean(axis=0)
    axis = np.linalg.svd(centred, full_matrices=False)[2][0]
    # farthest-point sampling down to the span
    chosen = [int(np.argmax(np.linalg.norm(pts - pts.mean(axis=0), axis=1)))]
    d = np.linalg.norm(pts - pts[chosen[0]], axis=1)
    while d.max() > span:
        i = int(np.argmax(d))
        chosen.append(i)
        d = np.minimum(d, np.linalg.norm(pts - pts[i], axis=1))
    return [(pts[i], axis) for i in chosen]


def tile_body(surface: Surface, model, template: Module, body: str, first_id: int, limit: int | None = None,
              ) -> tuple[list[PlacedModule], list[str]]:
    """Copies of `template` placed on one body (ring layout on capsules/cylinders, surface tiling
    elsewhere); returns the placed modules and the refusal messages."""
    layout = ring_layout(model, body, template) if _has_ring(model, body) else surface_layout(surface, template)
    mine: list[PlacedModule] = []
    refused: list[str] = []
    for anchor, direction in layout:
        if limit is not None and sum(len(p) for p in mine) + template.rows * template.cols > limit:
            break
        m = replace(template, id=first_id + len(mine), name=f"{body}_m{len(mine)}", body=body)
        try:
            p = place_module(surface, m, anchor, direction, others=mine)
        except PlacementError as e:
            refused.append(e.args[0])  # a strain refusal without its offer (worked out only when read)
            continue
        over = outline_overhang(surface, p.positions, p.frames, m.pitch / 2, m.min_bend_radius)
        if over.max() > OVERHANG_TOL:
            refused.append(f"module {m.id} '{m.name}': its outline overhangs '{body}' by {over.max() * 1e3:.1f} mm")
            continue
        off = disagreement(surface, p)
        if off > ROUNDTRIP_TOL:
            refused.append(f"module {m.id} '{m.name}': an independent wrap of its flat pattern puts a pad "
                           f"{off * 1e3:.1f} mm from the placement's (over {ROUNDTRIP_TOL * 1e3:.0f} mm: where it lands "
                           "is unsure)")
            continue
        p.module = replace(m, placement=placement_record(p.origin, p.origin_frame[:, 0], "geodesic"))
        mine.append(p)
    return mine, refused


def without_buried(design, model, home, poses: int = 1):
    """The design minus the modules with a taxel buried inside another link at every one of
    `poses` sampled poses (`audit.buried_taxels`; the default, 1, is the home pose: no skin where
    the robot covers itself at home, a superset of what `check` refuses) or enclosed by its own
    link's mesh (`audit.enclosed_taxels`). Returns (design, dropped module ids)."""
    from skinsafe.core.design.audit import buried_taxels, enclosed_taxels
    from skinsafe.core.design.placement import build_design, placed_from_design

    buried = buried_taxels(design, model, home, poses) | enclosed_taxels(design, model, home)
    bad = {int(m) for m in np.unique(design.taxels.module[buried])}
    if not bad:
        return design, []
    keep = [placed_from_design(design, m.id) for m in design.modules if m.id not in bad]
    for k, p in enumerate(keep):
        p.module = replace(p.module, id=k)
    bodies = [b for b in design.bodies if any(p.module.body == b for p in keep)]
    return build_design(design.robot, keep, max([b.capacity for b in design.boards], default=512),
                        float(np.median(design.taxels.thresholds["force"])), bodies=bodies), sorted(bad)
