"""The robot and skin a `skinsafe trade` point runs on: the UR5 sample skin, or the robot and
skin of any taxel map (`skinsafe design` writes one), loaded once per worker process."""
from __future__ import annotations

from pathlib import Path

import numpy as np

_SKINS: dict = {}


def skin_of(where: str | None, pitch: float = 0.01):
    """(robot, design) for a point: the UR5 sample skin at `pitch`, or the robot and skin of the
    taxel map at `where` (loaded once per process)."""
    from skinsafe.core.design.sample import make_sample_design
    from skinsafe.core.robot.models import build_ur5, load_robot
    from skinsafe.core.skin import taxel_map

    if where is None:
        robot = build_ur5()
        return robot, make_sample_design("ur5", pitch=float(pitch), robot=robot)
    if where not in _SKINS:
        robot = load_robot(taxel_map.load(where).robot, base_dir=Path(where).parent)
        _SKINS[where] = robot, taxel_map.load(where, robot.body_names)
    return _SKINS[where]


def map_pitch(where: str) -> float:
    return float(np.median([m.pitch for m in skin_of(where)[1].modules]))


def retiled(where: str, pitch: float):
    """The map's skin tiled again (`skinsafe design`'s layout: its links, its module shape) at `pitch`."""
    from skinsafe.core.app.design import design_robot

    robot, design = skin_of(where)
    m = design.modules[0]
    spec = {"module": {"rows": m.rows, "cols": m.cols, "pitch": float(pitch), "min_bend_radius": m.min_bend_radius},
            "bodies": list(design.bodies)}
    return robot, design_robot(robot, design.robot, spec)[0]


def map_probe_points(where: str, per_body: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Probe points and normals (world, at home) on a map's skin: random taxels of each probed
    link of the map as given (the same points whatever pitch the skin is tiled at)."""
    from skinsafe.core.robot.kinematics import TaxelKinematics
    from skinsafe.core.sim.probes import probe_bodies

    robot, design = skin_of(where)
    pos, frames = TaxelKinematics(robot.model, design).poses(robot.home)
    rng = np.random.default_rng(seed)
    idx = np.concatenate([rng.choice(np.flatnonzero(design.taxels.body == design.bodies.index(b)), per_body)
                          for b in probe_bodies(design)])
    return pos[idx], frames[idx, :, 2]
