"""`skinsafe bench retraction`: one defensiveness tick with K active taxels out of N.

`ms`: the default tick (prioritised QP with the no-push constraints and the limits, DAQP), median;
`ms_closed_form`: the same layer with the closed-form merge (`merge="joint"`, the reference the
QP replaced), timed interleaved with it in blocks of 20 ticks, and `qp_over_closed_form` the ratio of the
medians; `_p99`, `_worst` (maximum) and `_best` (minimum: on a loaded machine the closest to the
unloaded cost) beside each; `loop_ms`: the closed form
written as a straightforward loop (one `mj_jac`, one SVD and one Gram-Schmidt step per active
taxel), `speedup_vs_loop` = loop_ms / ms and `max_abs_diff` between the compiled closed form
and that loop (they must agree to rounding)."""
from __future__ import annotations

from dataclasses import replace

import mujoco
import numpy as np

from skinsafe.core.design.sample import design_with
from skinsafe.core.robot.kinematics import TaxelKinematics
from skinsafe.core.robot.models import build_ur5
from skinsafe.core.safety.defensiveness import DefensivenessLayer
from skinsafe.core.safety.retraction import RetractionParams, dls_pinv, merge_loop, task_jacobians, task_velocities
from skinsafe.core.timing import interleaved_ms, median_ms

DT = 0.002  # s: the control period of the benched ticks (a 500 Hz robot)


class LoopLayer(DefensivenessLayer):
    """The same layer with its hot path written as per-taxel loops (the reference)."""

    def _jacobians(self, idx, q):
        kin = self.kin
        pos, frames = kin.poses(q)
        J = np.zeros((len(idx), 6, kin.model.nv))
        for k, i in enumerate(idx):
            jp, jr = np.zeros((3, kin.model.nv)), np.zeros((3, kin.model.nv))
            mujoco.mj_jac(kin.model, kin.data, jp, jr, pos[i], int(kin.body_id[i]))
            J[k, :3], J[k, 3:] = jp, jr
        return J, pos[idx].copy(), frames[idx].copy()

    def _merged(self, J, back, speed):
        p = self.params
        qdots, rows = np.zeros((len(J), J.shape[2])), np.zeros((len(J), J.shape[2]))
        for k in range(len(J)):
            Jt = task_jacobians(J[k:k + 1], p.form)
            rdot = task_velocities(back[k:k + 1], speed[k:k + 1], p.form)
            qdots[k] = dls_pinv(Jt, p.damping, p.sv_threshold)[0] @ rdot[0]
            rows[k] = J[k, :3].T @ back[k]
        return merge_loop(qdots, rows, p.epsilon, p.rank_tol)


def add_arguments(p) -> None:
    p.add_argument("--taxels", type=int, default=4096, help="skin size N")
    p.add_argument("--active", default="1,8,64,512", help="active taxel counts K (comma-separated)")
    p.add_argument("--repeat", type=int, default=200, help="timed repeats per K")
    p.add_argument("--epsilon", type=float, default=1.0, help="merge tuning factor")


def primed(layer: DefensivenessLayer, q: np.ndarray, active: np.ndarray, n: int) -> dict:
    """Trigger `active` at t=0 and return the readings; ticks at t>0 then retract."""
    force = np.zeros(n)
    force[active] = np.linspace(5.0, 20.0, len(active))
    readings = {"force": force}
    layer.tick(0.0, q, readings)
    return readings


def rows(args) -> list[dict]:
    robot = build_ur5()
    design, _ = design_with(args.taxels, robot)
    kin = TaxelKinematics(robot.model, design)
    params = RetractionParams(epsilon=args.epsilon)
    rng = np.random.default_rng(0)
    q = robot.home + rng.normal(0, 0.2, robot.model.nq)
    th = design.taxels.thresholds
    out = []
    for k in (int(s) for s in args.active.split(",")):
        active = np.sort(rng.choice(args.taxels, k, replace=False))
        closed = replace(params, merge="joint")
        qp = DefensivenessLayer(kin, th, robot.vel_limits, robot.acc_limits, params, DT)
        fast = DefensivenessLayer(kin, th, robot.vel_limits, robot.acc_limits, closed, DT)
        loop = LoopLayer(kin, th, robot.vel_limits, robot.acc_limits, closed, DT)
        readings = primed(fast, q, active, args.taxels)
        primed(loop, q, active, args.taxels)
        primed(qp, q, active, args.taxels)
        t = 0.1 * params.T
        diff = float(np.abs(fast.tick(t, q, readings) - loop.tick(t, q, readings)).max())
        ms, ms_closed = interleaved_ms([lambda: qp.tick(t, q, readings), lambda: fast.tick(t, q, readings)],
                                       repeat=args.repeat, warmup=5)
        ms_loop = median_ms(lambda: loop.tick(t, q, readings), repeat=max(5, args.repeat // 10), warmup=2)
        med, med_closed = float(np.median(ms)), float(np.median(ms_closed))
        out.append({"active": k, "n_taxels": args.taxels, "ms": round(med, 4), "ms_p99": round(float(np.percentile(ms, 99)), 4),
                    "ms_worst": round(float(ms.max()), 3), "ms_best": round(float(ms.min()), 4),
                    "ms_closed_form": round(med_closed, 4), "ms_closed_form_best": round(float(ms_closed.min()), 4),
                    "ms_closed_form_p99": round(float(np.percentile(ms_closed, 99)), 4),
                    "ms_closed_form_worst": round(float(ms_closed.max()), 3),
                    "qp_over_closed_form": round(med / med_closed, 2), "loop_ms": round(ms_loop, 3),
                    "speedup_vs_loop": round(ms_loop / med, 1), "max_abs_diff": diff})
    return out
