"""Contact pruning for scenes: robot bodies that nothing can ever touch stop colliding."""
from __future__ import annotations

import mujoco
import numpy as np


def prune_contacts(spec: mujoco.MjSpec, model: mujoco.MjModel, obstacles: list) -> None:
    """Switch contacts off for robot bodies that nothing can ever touch.

    A moving body can touch a fixed geom only within its reach from the anchor of its chain
    (sum of body offsets down the chain plus its geoms' bounding spheres); it can touch another
    moving body when their contact masks meet and no exclude or parent/child relation filters
    them. Mocap or free obstacles can go anywhere: with one in the scene nothing is pruned.
    """
    if any(o.mocap or o.free for o in obstacles):
        return
    data = mujoco.MjData(model)
    if model.nkey:
        mujoco.mj_resetDataKeyframe(model, data, 0)
    mujoco.mj_kinematics(model, data)
    weld = model.body_weldid
    moving = [b for b in range(1, model.nbody) if weld[b] != 0]
    if any(model.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE for j in range(model.njnt)):
        return
    excluded = {frozenset((e.bodyname1, e.bodyname2)) for e in spec.excludes}
    names = [model.body(b).name for b in range(model.nbody)]
    geoms_of = {b: [g for g in range(model.ngeom) if model.geom_bodyid[g] == b and
                    (model.geom_contype[g] or model.geom_conaffinity[g])] for b in range(model.nbody)}
    fixed = [g for g in range(model.ngeom) if weld[model.geom_bodyid[g]] == 0 and
             (model.geom_contype[g] or model.geom_conaffinity[g])]

    def can_pair(g1, g2):
        return bool((model.geom_contype[g1] & model.geom_conaffinity[g2]) or
                    (model.geom_contype[g2] & model.geom_conaffinity[g1]))

    for b in moving:
        gs = geoms_of[b]
        if not gs:
            continue
        root = b
        while weld[model.body_parentid[root]] != 0:
            root = model.body_parentid[root]
        anchor = data.xpos[root]
        chain, node = 0.0, b
        while node != root:
            chain += float(np.linalg.norm(model.body_pos[node]))
            node = model.body_parentid[node]
        reach = chain + max(float(np.linalg.norm(model.geom_pos[g])) + model.geom_rbound[g] for g in gs)
        touchable = False
        for f in fixed:
            if not any(can_pair(g, f) for g in gs):
                continue
            if model.geom_type[f] == mujoco.mjtGeom.mjGEOM_PLANE:
                normal = data.geom_xmat[f].reshape(3, 3)[:, 2]
                dist = float(np.dot(anchor - data.geom_xpos[f], normal))
            else:
                dist = float(np.linalg.norm(anchor - data.geom_xpos[f])) - model.geom_rbound[f]
            if dist <= reach:
                touchable = True
                break
        if not touchable:
            for o in moving:
                if o == b or model.body_parentid[o] == b or model.body_parentid[b] == o:
                    continue
                if frozenset((names[b], names[o])) in excluded:
                    continue
                if any(can_pair(g, h) for g in gs for h in geoms_of[o]):
                    touchable = True
                    break
        if not touchable:
            for g in spec.body(names[b]).geoms:
                g.contype, g.conaffinity = 0, 0
