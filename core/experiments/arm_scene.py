"""The UR5 scene the desk (Fig. 14) and collaboration (Fig. 15) experiments run in: the robot
with a skin, obstacles and optionally a person (`core.sim.human`), stepped at `control_dt` with
position servos tracking a velocity command, the layers built for that control period.

With a person, every physics step records what each body part feels (`PersonTrace`): the
robot's normal force on it, the peak pressure on the skin's taxels touching it (force over the
taxel's cell, `body_regions.contact_areas`), whether a taxel there read over its threshold
(sensed), whether it touched bare robot surface, and whether it was trapped against a fixture or
pinched between links (the contact's kinematics: could it recoil?).
"""
from __future__ import annotations

import mujoco
import numpy as np
import torch

from skinsafe.core.safety.stack import SafetyStack
from skinsafe.core.safety.tdm import TactileDangerModel, train_tdm

JOINTS = ("shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint", "wrist_1_joint", "wrist_2_joint", "wrist_3_joint")
STATE = np.arange(4)  # modulated joints: pan, lift, elbow, wrist 1
TORQUE_NM = (150.0, 150.0, 150.0, 28.0, 28.0, 28.0)  # UR5 joint torque limits (datasheet: size 3 and size 1 joints)


class PersonTrace:
    """Per physics step and body part: `force_N`, `pressure_N_cm2`, `sensed`, `touched` (a taxel
    read force from it), `trapped`, `pinched`, `body` (robot body id, -1 none); `time_s` per step."""

    FIELDS = ("force_N", "pressure_N_cm2", "sensed", "touched", "trapped", "pinched", "body")

    def __init__(self):
        self.time_s: list[float] = []
        self.rows: dict[str, list] = {f: [] for f in self.FIELDS}

    def add(self, t: float, **values) -> None:
        self.time_s.append(t)
        for f in self.FIELDS:
            self.rows[f].append(values[f])

    def arrays(self) -> dict[str, np.ndarray]:
        out = {f: np.array(v) for f, v in self.rows.items()}
        out["time_s"] = np.array(self.time_s)
        return out


class Scene:
    """UR5 + a skin (`design`, default the sample skin at `pitch`) + obstacles (+ a person whose
    parts also collide with the `fixtures`, geom names), stepped at `control_dt` (physics at
    `timestep`, default the robot model's); the servos within `torque_limits` (N m per joint, default
    the UR5's; None: unlimited)."""

    def __init__(self, obstacles, pitch: float = 0.01, control_dt: float = 0.01, human=None, design=None,
                 timestep: float | None = None, fixtures=(), torque_limits=TORQUE_NM):
        from skinsafe.core.design.sample import make_sample_design
        from skinsafe.core.robot.kinematics import TaxelKinematics, body_ids
        from skinsafe.core.robot.models import build_ur5
        from skinsafe.core.sim.body_regions import contact_areas
        from skinsafe.core.sim.readout import SkinReadout
        from skinsafe.core.sim.scene import SceneOptions, build_scene

        self.robot = build_ur5()
        self.design = design if design is not None else make_sample_design("ur5", pitch=pitch, robot=self.robot)
        obstacles = list(obstacles) + (human.obstacles() if human is not None else [])
        spec = build_scene(self.design, self.robot, obstacles, SceneOptions(timestep=timestep))
        if human is not None:  # a person (core.sim.human): compliant body regions with ISO/TS 15066 stiffness
            from skinsafe.core.sim.human import robot_collision_geoms
            human.attach(spec, robot_collision_geoms(self.robot.model, self.robot.arm_bodies), fixtures)
        self.model = spec.compile()
        self.data = mujoco.MjData(self.model)
        self.human = human
        if human is not None:
            human.bind(self.model)
        self.readout = SkinReadout(self.model, self.design)
        self.kin = TaxelKinematics(self.robot.model, self.design)
        self.qadr = np.array([self.model.jnt_qposadr[self.model.joint(j).id] for j in JOINTS])
        self.dadr = np.array([self.model.jnt_dofadr[self.model.joint(j).id] for j in JOINTS])
        self.act = np.array([self.model.actuator(f"{j}_pos").id for j in JOINTS])
        if torque_limits is not None:  # a blocked servo pushes with the motors' torque, no more
            self.model.actuator_forcelimited[self.act] = 1
            self.model.actuator_forcerange[self.act] = np.c_[-np.array(torque_limits), torque_limits]
        self.control_dt = control_dt
        self.substeps = max(1, int(round(control_dt / self.model.opt.timestep)))
        self.arm_geoms = [g for g in range(self.model.ngeom)
                          if self.model.body(self.model.geom_bodyid[g]).name in self.design.bodies]
        t = self.design.taxels
        self.taxel_body = body_ids(self.model, self.design)[t.body] if len(t) else np.zeros(0, int)
        self.cell_cm2 = contact_areas(self.design) * 1e4
        self.threshold = t.thresholds["force"]
        self.trace = PersonTrace()

    def defensiveness(self):
        """The tactile defensiveness layer for this skin, at the scene's control period."""
        from skinsafe.core.safety.defensiveness import DefensivenessLayer

        return DefensivenessLayer(self.kin, self.design.taxels.thresholds, self.robot.vel_limits,
                                  self.robot.acc_limits, dt=self.control_dt)

    def stack(self, defensiveness=None, modulation=None, pfl=None, strategy=None) -> SafetyStack:
        """A `SafetyStack` for this robot ticking at the scene's control period (the acceleration
        limits of `defensiveness` per tick of `control_dt`; none without it)."""
        return SafetyStack(self.robot.vel_limits, defensiveness, modulation, strategy=strategy, joints=STATE,
                           dt=self.control_dt, pfl=pfl)

    def reset(self, q0) -> None:
        mujoco.mj_resetData(self.model, self.data)
        self.data.qpos[self.qadr] = q0
        self.data.ctrl[self.act] = q0
        self.q_cmd = np.array(q0, float)
        mujoco.mj_forward(self.model, self.data)
        self.trace = PersonTrace()

    @property
    def q(self) -> np.ndarray:
        return self.data.qpos[self.qadr].copy()

    @property
    def qdot(self) -> np.ndarray:
        return self.data.qvel[self.dadr].copy()

    def step(self, v: np.ndarray, lead: float = 0.2) -> np.ndarray:
        """Command joint velocity v for one control tick; returns the peak taxel forces (N,)."""
        q = self.q
        self.q_cmd = np.clip(self.q_cmd + v * self.control_dt, q - lead, q + lead)
        self.data.ctrl[self.act] = self.q_cmd
        peak = np.zeros(self.design.n_taxels)
        if self.human is not None:
            self.human.update(self.data)
        for _ in range(self.substeps):
            if self.human is not None:
                self.human.drive(self.data)
            mujoco.mj_step(self.model, self.data)
            r = self.readout.read(self.data)
            np.maximum(peak, r, out=peak)
            if self.human is not None:
                self._record(r)
        return peak

    def _record(self, r: np.ndarray) -> None:
        """One physics step of `PersonTrace`: the touched taxels go to the nearest body part."""
        h, d = self.human, self.data
        st = h.state(d)
        P = len(h.parts)
        pressure, sensed, touched = np.zeros(P), np.zeros(P, bool), np.zeros(P, bool)
        on = np.flatnonzero(r > 0)
        if len(on):
            b = self.taxel_body[on]
            pos = d.xpos[b] + np.einsum("nij,nj->ni", d.xmat[b].reshape(-1, 3, 3), self.design.taxels.positions[on])
            owner = np.argmin(np.stack([_to_segment(pos, *self._segment(k)) for k in range(P)]), axis=0)
            for k in np.unique(owner):
                sel = on[owner == k]
                pressure[k] = float(np.max(r[sel] / self.cell_cm2[sel]))
                sensed[k] = bool(np.any(r[sel] >= self.threshold[sel]))
                touched[k] = True
        self.trace.add(float(d.time), force_N=st.robot_N, pressure_N_cm2=pressure, sensed=sensed, touched=touched,
                       trapped=st.trapped, pinched=st.pinched, body=st.body)

    def _segment(self, k: int):
        """Part k's core as a segment (world ends): a capsule's axis, else its centre."""
        g = self.human.geom[k]
        c = self.data.geom_xpos[g]
        half = self.model.geom_size[g][1] if self.model.geom_type[g] == mujoco.mjtGeom.mjGEOM_CAPSULE else 0.0
        axis = self.data.geom_xmat[g].reshape(3, 3)[:, 2] * half
        return c - axis, c + axis

    def clearance(self, geom: int) -> float:
        """Signed distance (m) between the skinned arm and a geom (negative: penetration)."""
        fromto = np.zeros(6)
        return min(mujoco.mj_geomDistance(self.model, self.data, g, geom, 0.5, fromto) for g in self.arm_geoms)


def _to_segment(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(n,) distance of points p (n,3) to the segment a-b."""
    ab = b - a
    u = np.clip((p - a) @ ab / max(float(ab @ ab), 1e-12), 0.0, 1.0)
    return np.linalg.norm(p - (a + u[:, None] * ab), axis=1)


def static_contact_tdm(S: np.ndarray, A: np.ndarray, D: np.ndarray, args) -> TactileDangerModel:
    """A TDM fitted to static contact samples (states S, actions A, per-taxel danger labels D),
    its head biased to a 1% prior danger per taxel; `args.steps` batches of 64, `args.seed`."""
    torch.manual_seed(args.seed)
    tdm = TactileDangerModel(S.shape[1], A.shape[1], D.shape[1], (64, 64))
    with torch.no_grad():
        tdm.head.bias.fill_(float(np.log(0.01 / D.shape[1])))
    train_tdm(tdm, S, A, D, epochs=max(1, args.steps * 64 // len(S)), lr=3e-3, batch_size=64, seed=args.seed,
              progress=False)
    return tdm.eval()
