"""`skinsafe pfl`: ISO/TS 15066 power and force limiting from a skin design.

At a pose: every taxel's effective robot mass along its outward normal and the highest safe
approach speed per body region (summary per link and region; `--json FILE` writes every taxel).
Along a trajectory (`--trajectory FILE`: CSV or .npy, rows `t, q_1..q_n`): each taxel's speed along
its normal (finite differences of q) against its v_max at every sample; the report names the
taxels and links where the planned trajectory exceeds it, the worst time and by how much (the JSON
adds every taxel's fastest approach and lowest v_max along the way).
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from skinsafe.core.robot.kinematics import TaxelKinematics
from skinsafe.core.safety.pfl import REGIONS, NormalRows, inverse_effective_mass, v_max
from skinsafe.core.skin.files import atomic_write
from skinsafe.core.skin.model import DesignError


def add_arguments(p) -> None:
    p.add_argument("map", nargs="?", help="taxel map JSON (or --sample)")
    p.add_argument("--sample", choices=["ur5", "panda"], help="use the built-in sample skin on this robot")
    p.add_argument("--pitch", type=float, default=0.01, help="sample skin pitch (m)")
    p.add_argument("--q", type=float, nargs="+", help="joint configuration (rad; default: the robot's home)")
    p.add_argument("--trajectory", help="CSV or .npy with rows t, q_1..q_n (s, rad)")
    p.add_argument("--regions", nargs="+", default=None, help=f"body regions (default: all that allow transient contact): {', '.join(REGIONS)}")
    p.add_argument("--top", type=int, default=10, help="how many exceeding taxels to list")
    p.add_argument("--json", dest="json_out", help="write the full per-taxel report here")


def _design(args):
    from skinsafe.core.robot.models import load_robot
    from skinsafe.core.skin.taxel_map import load

    if args.sample:
        from skinsafe.core.design.sample import make_sample_design
        from skinsafe.core.robot.models import BUILTIN

        robot = BUILTIN[args.sample]()
        return robot, make_sample_design(args.sample, pitch=args.pitch, robot=robot)
    if not args.map:
        raise DesignError("pfl: give a taxel map JSON or --sample ur5|panda")
    path = Path(args.map)
    design = load(path)
    robot = load_robot(design.robot, base_dir=path.parent)
    design.validate(str(path), robot.body_names)
    return robot, design


def load_trajectory(path: str, nq: int) -> tuple[np.ndarray, np.ndarray]:
    """Times (T,) and configurations (T, nq) from a CSV or .npy file (rows t, q_1..q_nq)."""
    p = Path(path)
    if not p.is_file():
        raise DesignError(f"pfl: trajectory file '{p}' not found")
    try:
        arr = np.load(p) if p.suffix == ".npy" else np.loadtxt(p, delimiter=",", ndmin=2)
    except ValueError as e:
        raise DesignError(f"pfl: trajectory '{p}' is not numbers in rows (t, q_1..q_{nq}): {e}") from None
    arr = np.asarray(arr, float)
    if arr.ndim != 2 or arr.shape[1] != nq + 1 or len(arr) < 2:
        raise DesignError(f"pfl: trajectory '{p}' has shape {arr.shape}; give at least 2 rows of t and {nq} joint values")
    if not np.all(np.isfinite(arr)) or np.any(np.diff(arr[:, 0]) <= 0):
        raise DesignError(f"pfl: trajectory '{p}': times must increase strictly and every value be finite")
    return arr[:, 0], arr[:, 1:]


def analyse(robot, design, regions, q=None, trajectory=None) -> dict:
    """The report: per taxel effective mass and v_max per region at q; with a trajectory
    (times, qs), per taxel and region the worst ratio of normal speed to v_max."""
    kin = TaxelKinematics(robot.model, design)
    rows_of = NormalRows(kin)
    q = robot.home.copy() if q is None else np.asarray(q, float)
    if q.shape != (robot.model.nq,) or not np.all(np.isfinite(q)):
        raise DesignError(f"pfl: --q has {q.size} values ({q.tolist()}); give {robot.model.nq} finite joint values (rad)")
    inv = inverse_effective_mass(kin, rows_of(q))
    with np.errstate(divide="ignore"):
        mass = np.where(inv > 0, 1 / np.maximum(inv, 1e-300), np.inf)
    link = np.array(design.bodies)[design.taxels.body]
    rep = {"robot": robot.name, "n_taxels": design.n_taxels, "q": q.tolist(), "regions": list(regions),
           "taxel_ids": design.taxels.ids.tolist(), "links": link.tolist(),
           "effective_mass_kg": np.where(np.isfinite(mass), mass, -1).round(4).tolist(),
           "v_max_m_s": {r: v_max(r, inv).round(4).tolist() for r in regions}}
    if trajectory is not None:
        times, qs = trajectory
        qd = np.gradient(qs, times, axis=0)
        worst = {r: np.zeros(design.n_taxels) for r in regions}
        when = {r: np.zeros(design.n_taxels) for r in regions}
        lowest = {r: np.full(design.n_taxels, np.inf) for r in regions}
        fastest = np.zeros(design.n_taxels)
        for t, qk, vk in zip(times, qs, qd):
            rows = rows_of(qk)
            inv_k = inverse_effective_mass(kin, rows)
            vn = rows @ vk
            np.maximum(fastest, vn, out=fastest)
            for r in regions:
                vm = v_max(r, inv_k)
                np.minimum(lowest[r], vm, out=lowest[r])
                ratio = np.where(vn > 0, vn / np.maximum(vm, 1e-12), 0.0)
                more = ratio > worst[r]
                worst[r][more], when[r][more] = ratio[more], t
        rep["trajectory_max_normal_speed_m_s"] = fastest.round(4).tolist()
        rep["trajectory_min_v_max_m_s"] = {r: lowest[r].round(4).tolist() for r in regions}
        rep["exceeds"] = []
        for r in regions:
            for i in np.flatnonzero(worst[r] > 1.0):
                rep["exceeds"].append({"region": r, "taxel": int(design.taxels.ids[i]), "link": str(link[i]),
                                       "time_s": float(when[r][i]), "speed_over_v_max": float(worst[r][i])})
        rep["exceeds"].sort(key=lambda e: -e["speed_over_v_max"])
    return rep


def run(args) -> int:
    robot, design = _design(args)
    regions = args.regions or [r for r, reg in REGIONS.items() if reg.transient_N is not None]
    for r in regions:
        if r not in REGIONS:
            raise DesignError(f"pfl: body region '{r}' is unknown; use one of {', '.join(REGIONS)}")
    traj = load_trajectory(args.trajectory, robot.model.nq) if args.trajectory else None
    rep = analyse(robot, design, regions, args.q, traj)
    mass = np.array(rep["effective_mass_kg"])
    links = np.array(rep["links"])
    print(f"{robot.name}: {design.n_taxels} taxels; effective robot mass along the taxel normals (kg) and the "
          "highest safe approach speed (m/s, min over the link's taxels) per body region")
    regs = [r for r in regions if REGIONS[r].transient_N is not None]
    print("link".ljust(16) + "m_R median".rjust(11) + "".join(r[:10].rjust(11) for r in regs))
    for b in design.bodies:
        on = links == b
        if not on.any():
            continue
        m = mass[on]
        cells = [f"{np.median(np.where(m < 0, np.inf, m)):.3g}".rjust(11)]
        cells += [f"{np.min(np.array(rep['v_max_m_s'][r])[on]):.3g}".rjust(11) for r in regs]
        print(b[:16].ljust(16) + "".join(cells))
    banned = [r for r in regions if REGIONS[r].transient_N is None]
    if banned:
        print(f"no transient contact allowed (v_max 0): {', '.join(banned)}")
    if traj is not None:
        ex = rep["exceeds"]
        print(f"trajectory: {len(traj[0])} samples over {traj[0][-1] - traj[0][0]:.3g} s; "
              f"{len({e['taxel'] for e in ex})} taxels exceed v_max for some region")
        for e in ex[:args.top]:
            print(f"  taxel {e['taxel']} on {e['link']}: {e['speed_over_v_max']:.2f} x v_max ({e['region']}) "
                  f"at t = {e['time_s']:.3g} s")
    if args.json_out:
        atomic_write(Path(args.json_out), json.dumps(rep))
        print(f"wrote {args.json_out}")
    return 0
