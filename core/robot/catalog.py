"""Public robot descriptions beside the built-ins, by name: the ROS descriptions shipped in
`blend_assets/` (their sources and licences in each folder's SOURCE.md) and those `make robots`
fetches from PyPI (`blend_assets/robots/fetch.py`)."""
from __future__ import annotations

from pathlib import Path

from skinsafe.core.skin.model import DesignError, RobotRef

ASSETS = Path(__file__).resolve().parents[2] / "blend_assets"
ROBOTS = ASSETS / "robots"
# name -> (file under blend_assets, package folders under blend_assets, xacro arguments)
DESCRIPTIONS = {
    "franka": ("franka_description/robots/panda/panda.urdf.xacro", ("franka_description",), {}),
    "ur5e": ("robots/ur_description/urdf/ur.urdf.xacro", ("robots",), {"name": "ur5e", "ur_type": "ur5e"}),
    "gen3": ("robots/kortex_description/robots/gen3.xacro", ("robots",), {"dof": "7"}),
    "xarm7": ("robots/example-robot-data/robots/xarm_description/urdf/xarm7.urdf", ("robots",), {}),
}


def description(name: str) -> RobotRef:
    """The RobotRef of a named public description (absolute paths)."""
    if name not in DESCRIPTIONS:
        raise DesignError(f"robot: '{name}' is not a bundled description; use one of {', '.join(DESCRIPTIONS)}")
    file, dirs, args = DESCRIPTIONS[name]
    path = ASSETS / file
    if not path.is_file():
        raise DesignError(f"robot '{name}': '{path}' is missing; run `make robots` to fetch it")
    return RobotRef("urdf", name, str(path), tuple(str(ASSETS / d) for d in dirs), dict(args))
