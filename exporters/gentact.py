"""A skin design as the taxel CSV that the GenTact Toolbox's Blender add-on writes for its Isaac Sim contact
extension (github.com/cKohl10/GenTact_merge_update, sensor_bay_addon/operators/isaac_save_operator.py):

    Index,X,Y,Z,Radius,Parent

one row per taxel: Index the taxel's id (skinsafe's stable id, where GenTact counts 0..n-1), X Y Z its
position in its link's frame (m), Radius half its taxel diameter (m), Parent the link's path from the
robot's root as GenTact writes an object's (`/<robot>/<link>/.../<link>`)."""
from __future__ import annotations

import csv
import io
from pathlib import Path

from skinsafe.core.robot.models import Robot
from skinsafe.core.skin.files import atomic_write
from skinsafe.core.skin.model import SkinDesign

HEADER = ("Index", "X", "Y", "Z", "Radius", "Parent")


def link_path(model, body: str, robot_name: str) -> str:
    """`/<robot>/<root link>/.../<body>`: the body's chain of links below the world body."""
    b, chain = model.body(body).id, []
    while b > 0:
        chain.append(model.body(b).name)
        b = int(model.body_parentid[b])
    return "/" + "/".join([robot_name, *reversed(chain)])


def taxel_csv(design: SkinDesign, robot: Robot) -> str:
    """The CSV text (see the module docstring), taxels in design order."""
    design.validate("gentact csv", robot.body_names)
    t = design.taxels
    radius = {m.id: m.taxel_diameter / 2 for m in design.modules}
    paths = [link_path(robot.model, b, robot.name) for b in design.bodies]
    out = io.StringIO()
    w = csv.writer(out, lineterminator="\n")
    w.writerow(HEADER)
    for i in range(len(t)):
        x, y, z = (repr(float(c)) for c in t.positions[i])
        w.writerow([int(t.ids[i]), x, y, z, repr(float(radius[int(t.module[i])])), paths[int(t.body[i])]])
    return out.getvalue()


def export_csv(design: SkinDesign, robot: Robot, path: str | Path) -> Path:
    """Write `taxel_csv` to `path` atomically."""
    return atomic_write(path, taxel_csv(design, robot))

