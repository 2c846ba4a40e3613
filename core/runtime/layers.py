"""The stack a run uses, built from the map, the robot's own limits and the period - and rebuilt the same
way from a record's configuration for a replay.

The layers: tactile defensiveness (retraction, paper III-C) with the velocity and acceleration limits
of the driver (`limits()`: qd_max, qdd_max) on the final command; with a TDM checkpoint (`--tdm`),
also the strategy filter and the modulation over its danger potential (III-A, III-B), on the first
`state_dim` joints of the checkpoint.
"""
from __future__ import annotations

import hashlib
from collections.abc import Mapping
from dataclasses import fields
from pathlib import Path

import numpy as np

from skinsafe.core.robot.kinematics import TaxelKinematics
from skinsafe.core.robot.models import load_robot, only_joints
from skinsafe.core.runtime.limiter import limits_config
from skinsafe.core.safety.defensiveness import DefensivenessLayer
from skinsafe.core.safety.retraction import RetractionParams
from skinsafe.core.safety.stack import SafetyStack
from skinsafe.core.skin.model import SkinDesign

CONFIG_VERSION = 1


def build_stack(design: SkinDesign, robot_model, qd_max, qdd_max, period_s: float,
                params: RetractionParams | None = None, tdm_path: str | None = None, faults=None) -> SafetyStack:
    """`faults`: a run's FaultPlan (core/runtime/fault_plan.py), handed to the layers that can fail."""
    kin = TaxelKinematics(robot_model, design)
    d = DefensivenessLayer(kin, design.taxels.thresholds, qd_max, qdd_max, params or RetractionParams(), dt=period_s,
                           faults=faults)
    modulation = strategy = joints = None
    if tdm_path:
        from skinsafe.core.safety.modulation import ModulationLayer
        from skinsafe.core.safety.potential import DangerPotential
        from skinsafe.core.safety.stack import StrategyFilter
        from skinsafe.core.safety.tdm import load_tdm

        tdm = load_tdm(tdm_path)
        if tdm.config()["n_taxels"] != design.n_taxels:
            raise ValueError(f"--tdm {tdm_path}: the model predicts {tdm.config()['n_taxels']} taxels, the map has "
                             f"{design.n_taxels}; train it on this map")
        joints = np.arange(tdm.config()["state_dim"])
        modulation = ModulationLayer(DangerPotential(tdm))  # it evaluates the potential through FastPotential
        strategy = StrategyFilter(tdm)
    return SafetyStack(qd_max, d, modulation, strategy, joints=joints, acc_limits=qdd_max, dt=period_s, faults=faults)


def run_config(map_path: str | Path, driver, limits: Mapping, params: RetractionParams, excluded: np.ndarray,
               command: str, tdm_path: str | None) -> dict:
    """What a replay needs to rebuild the stack exactly (recorded as metadata)."""
    mp = Path(map_path).resolve()
    return {"config_version": CONFIG_VERSION, "map": str(mp), "map_sha256": hashlib.sha256(mp.read_bytes()).hexdigest(),
            "robot": driver.name, "joint_names": list(driver.joint_names), "period_s": driver.period_s,
            "qd_max": [float(x) for x in limits["qd_max"]], "qdd_max": [float(x) for x in limits["qdd_max"]],
            "retraction": {f.name: _plain(getattr(params, f.name)) for f in fields(params)}, "excluded": [int(i) for i in np.flatnonzero(excluded)],
            "command": command, "tdm": str(Path(tdm_path).resolve()) if tdm_path else None,
            "limits": limits_config(limits), "limiter_period_s": driver.period_s}


def _plain(x):
    return dict(x) if isinstance(x, Mapping) else x


def stack_from_config(config: dict, design: SkinDesign) -> SafetyStack:
    """The stack of a recorded run (see `run_config`)."""
    if config.get("config_version") != CONFIG_VERSION:
        raise ValueError(f"record configuration version {config.get('config_version')}; this skinsafe reads "
                         f"{CONFIG_VERSION}")
    robot = only_joints(load_robot(design.robot, base_dir=Path(config["map"]).parent), config["joint_names"])
    return build_stack(design, robot.model, np.array(config["qd_max"]), np.array(config["qdd_max"]), config["period_s"],
                       RetractionParams(**config["retraction"]), config["tdm"])
