"""`skinsafe experiment desk` (Fig. 14): the UR5 with the sample skin in MuJoCo (`arm_scene.Scene`),
readings from `SkinReadout`, and the layers through `SafetyStack`.

- desk: a probe presses on top of the forearm; the defensiveness layer retracts the touched
  taxels along -z, i.e. down toward a desk under the arm. The modulation potential is a TDM
  learned from static contacts with the desk (random configurations around the start, labels
  from the skin readout), used as f_phi and as the distilled 2-step w_phi. Reported: the
  clearance between arm and desk (min signed distance, negative = penetration) and the desk
  contact force, without modulation, with f_phi and with w_phi.

`skinsafe experiment collaboration` (Fig. 15) is `collaboration.py`.
"""
from __future__ import annotations

import io
import json
import time
from pathlib import Path

import mujoco
import numpy as np
import torch
from tqdm.auto import tqdm

from skinsafe.core.experiments.arm_scene import STATE, Scene, static_contact_tdm
from skinsafe.core.safety.modulation import ModulationLayer
from skinsafe.core.safety.potential import (
    DangerPotential,
    EulerDynamics,
    NStepConfig,
    UniformPolicy,
    distill_nstep,
    single_thread_blas,
)
from skinsafe.core.safety.stack import SafetyStack
from skinsafe.core.skin.files import atomic_write

# ------------------------------------------------------------------------------------------ desk

DESK_Q = np.array([0.0, -1.2, 1.6, -1.97, -1.5708, 0.0])


def _desk_layout(robot, design, gap: float):
    """Desk top `gap` below the lowest forearm/wrist taxel at DESK_Q; probe above the forearm."""
    from skinsafe.core.robot.kinematics import TaxelKinematics

    kin = TaxelKinematics(robot.model, design)
    pos, frames = kin.poses(DESK_Q)
    names = design.bodies
    fore = design.taxels.body == names.index("forearm_link")
    arm = np.isin(design.taxels.body, [names.index(b) for b in ("forearm_link", "wrist_1_link", "wrist_2_link")])
    low = pos[arm, 2].min()
    lo, hi = pos[arm, :2].min(0) - 0.1, pos[arm, :2].max(0) + 0.1
    hi[0] = min(hi[0], -0.2)  # keep clear of the shoulder and the upper arm's root
    centre = np.r_[(lo + hi) / 2, low - gap - 0.05]
    half = np.r_[(hi - lo) / 2, 0.05]
    up = np.where(fore, frames[:, 2, 2], -np.inf)  # forearm taxels facing up
    top = np.flatnonzero(up >= np.sort(up[fore])[-max(1, fore.sum() // 20)])
    target = pos[top[np.argmin(np.abs(pos[top, 0] - pos[fore, 0].mean()))]]
    return centre, half, target


def desk(args) -> dict:
    from skinsafe.core.design.sample import make_sample_design
    from skinsafe.core.robot.models import build_ur5
    from skinsafe.core.sim.scene import Obstacle

    robot = build_ur5()
    design = make_sample_design("ur5", pitch=args.pitch, robot=robot)
    centre, half, target = _desk_layout(robot, design, args.gap)
    probe_r = 0.02
    park = target + np.array([0, 0, 0.3])
    obstacles = [Obstacle("desk", "box", tuple(half), pos=tuple(centre), rgba=(0.6, 0.45, 0.3, 1)),
                 Obstacle("probe", "sphere", (probe_r,), pos=tuple(park), mocap=True)]
    sc = Scene(obstacles, args.pitch)
    desk_geom = sc.model.geom("desk").id
    f_pot, w_pot = _learn_desk(sc, desk_geom, args)
    out = {"gap_m": args.gap, "runs": {}}
    for name, pot in (("no modulation", None), ("TDM modulation", f_pot), ("2-step TDM modulation", w_pot)):
        mod = None if pot is None else ModulationLayer(pot, tangent_gain=args.tangent_gain)
        stack = SafetyStack(sc.robot.vel_limits, sc.defensiveness(), mod, joints=STATE)
        sc.reset(DESK_Q)
        clear, desk_force, trace = [], 0.0, []
        v = np.zeros(6)
        for k in range(int(args.duration / sc.control_dt)):
            t = k * sc.control_dt
            press = 0.1 <= t < 0.2  # the touch: the probe pushes 3 mm into the forearm top
            sc.data.mocap_pos[0] = target + np.array([0, 0, probe_r - 0.003]) if press else park
            force = sc.step(v)
            v = stack.tick(t, sc.q, {"force": force}, np.zeros(6), sc.control_dt)
            clear.append(sc.clearance(desk_geom))
            desk_force = max(desk_force, _contact_force(sc, desk_geom))
            trace.append(clear[-1])
        out["runs"][name] = {"min_clearance_mm": 1e3 * float(np.min(clear[int(0.25 / sc.control_dt):])),
                             "desk_force_N": desk_force, "clearance_mm": (1e3 * np.array(trace)).round(2).tolist()}
    return out


def _contact_force(sc: Scene, geom: int) -> float:
    d, total, f = sc.data, 0.0, np.zeros(6)
    for i in range(d.ncon):
        if geom in (d.contact[i].geom1, d.contact[i].geom2):
            mujoco.mj_contactForce(sc.model, d, i, f)
            total += abs(f[0])
    return total


def _learn_desk(sc: Scene, desk_geom: int, args):
    """A TDM from static contacts around DESK_Q (labels from the skin readout), and its 2-step potential."""
    rng = np.random.default_rng(args.seed)
    n = args.samples
    S = DESK_Q[STATE] + rng.uniform(-1, 1, (n, len(STATE))) * np.array([0.15, 0.35, 0.35, 0.35])
    A = rng.uniform(-1, 1, (n, len(STATE)))
    D = np.zeros((n, sc.design.n_taxels), np.float32)
    m, d = sc.model, sc.data
    for i in tqdm(range(n), desc="desk contacts", disable=args.no_progress, leave=False):
        q = DESK_Q.copy()
        q[STATE] = S[i]
        mujoco.mj_resetData(m, d)
        d.qpos[sc.qadr] = q
        d.mocap_pos[0] = [0, 0, 5]
        mujoco.mj_forward(m, d)
        # static contact: any penetration of the desk counts, at the taxels nearest to it
        D[i] = sc.readout.read(d) > 0
    f_pot = DangerPotential(static_contact_tdm(S, A, D, args))
    net, _ = distill_nstep(f_pot, S, A, EulerDynamics(0.15), UniformPolicy(-np.ones(len(STATE)), np.ones(len(STATE))),
                           NStepConfig(2, 0.9, 8), state_noise=0.03, epochs=40, seed=args.seed)
    return f_pot, net.eval()


# ------------------------------------------------------------------------------------- command

def add_arguments(p) -> None:
    p.add_argument("--out", default=None, help="output folder (default results/<scene>)")
    p.add_argument("--pitch", type=float, default=0.01, help="sample skin pitch (m)")
    p.add_argument("--duration", type=float, default=1.5, help="seconds")
    p.add_argument("--gap", type=float, default=0.1, help="desk: gap between the desk and the lowest taxel (m)")
    p.add_argument("--samples", type=int, default=3000, help="desk: static contact samples for the TDM")
    p.add_argument("--steps", type=int, default=1500, help="desk: TDM training steps (batch 64)")
    p.add_argument("--tangent-gain", type=float, default=0.0,
                   help="desk: modulation's tangential gain (1 = the paper's 1+f; 0 never speeds up)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--no-progress", action="store_true")


def run(args) -> int:
    torch.set_num_threads(1)
    single_thread_blas()
    name = args.command_name
    if name != "desk":
        raise SystemExit(f"experiment scenes serves 'desk', not '{name}' (collaboration: core.experiments.collaboration)")
    if args.duration <= 0:
        raise SystemExit(f"--duration is {args.duration}; give a positive number of seconds")
    out_dir = Path(args.out or f"results/{name}")
    t0 = time.perf_counter()
    res = desk(args)
    res["seconds"] = time.perf_counter() - t0
    atomic_write(out_dir / f"{name}.json", json.dumps(res, indent=1))
    _plot(name, res, out_dir / f"{name}.png")
    for k, r in res["runs"].items():
        print(k + ": " + ", ".join(f"{a}={b:.3g}" if isinstance(b, float) else f"{a}={b}"
                                   for a, b in r.items() if not isinstance(b, list)))
    print(f"wrote {out_dir / (name + '.json')} and {out_dir / (name + '.png')}")
    return 0


def _plot(name: str, res: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.5))
    for label, r in res["runs"].items():
        y = np.array(r["clearance_mm"])
        ax.plot(np.arange(len(y)) * 0.01, y, label=label)
    ax.axhline(0, color="k", lw=0.8)
    ax.set_xlabel("time (s)")
    ax.set_ylabel("arm-desk clearance (mm)")
    ax.set_title("Fig. 14: retraction toward a desk")
    ax.legend(fontsize=7)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    atomic_write(path, buf.getvalue())
