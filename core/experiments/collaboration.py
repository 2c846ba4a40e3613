"""`skinsafe experiment collaboration` (paper Fig. 15) as an ISO/TS 15066 power-and-force-limiting
test of the skin and the three layers, run the way a safety assessor would.

Scenarios (`SCENARIOS`), each with a person (`core.sim.human`: ISO/TS 15066 masses and springs per
region, force-limited muscles) beside the UR5 on its table:

- `delivery` (robot-driven): the UR5 delivers a part with a fast pan sweep (`--duration`) while the
  person's lower arm and hand reach radially into the wrist's path, stay `--stay` s and withdraw;
  the planner (or a teleoperation stream, `--source teleoperation`) then completes the delivery;
- `clamp` (robot-driven): the hand rests flat on the table and the robot lowers its flange onto it
  (a part placed on the table): the hand can be trapped against the table;
- `person` (person-driven): the robot holds still where the delivery meets the hand and the person
  moves the hand into the wrist at `--person-speed` (0.5 m/s), pushing on past the surface for a
  moment before withdrawing.

Stacks: `none` (the joint velocity limits only), `retraction` (defensiveness), `full`
(defensiveness + modulation by a TDM learned from static contacts with the person, scaled by
`--presence`), `full+pfl` (`full` + the PFL cap, `core.safety.pfl.PFLCap`: the person's regions at
`--pfl-factor` of v_max, pressure from the taxels' cells, clamping against the table, the person's
parts and velocities observed). Every stack ticks at the scene's control period (`Scene.stack`).

The skin (`collaboration_skin`): the sample skin plus modules placed (`design.placement`) where the
person meets the robot in these scenarios, found by simulating them; every contact row says
whether the skin sensed it (`sensed`, `sensed_ms` after its start), which layers acted during it
(`acted`), and a contact on bare surface is named in `findings`.

Contacts (`contact_events`) come from the physics steps: a run of robot force on a body part (gaps
under `GAP_S` merged). Its kind is the contact's kinematics: `clamp` when the robot pressed the part
against the table, `quasi_static` when it pinched it between links, `transient` when the part could
recoil (the transient limits for its first `TRANSIENT_S`, the quasi-static ones for any longer
push). `ratio` is the worst of peak force and peak pressure over their limits.

The robustness sweep (`--sweep`, Ray over `--workers`): contact damping ratio x the person's
attachment stiffness x physics timestep, for every scenario, the `--sweep-stacks`; each cell's
`worst_ratio`, and for the person-driven scenario its peak against the `none` run's.

The experiment's parts: core/experiments/collaboration_scenario.py (the options, scenarios, scene, one run),
collaboration_person.py (the person's TDM), collaboration_skin.py (the skin), collaboration_result.py (contact
events, the result file, tables and figure); this module runs the cells (Ray) and is the command.
"""
from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from skinsafe.core.experiments.collaboration_person import learn_person
from skinsafe.core.experiments.collaboration_result import contact_events, save_plot, summarise, tables, trace_every
from skinsafe.core.experiments.collaboration_scenario import (
    NOMINAL,
    SCENARIOS,
    STACKS,
    SWEEP,
    CollabConfig,
    build,
    episode,
    layout,
)
from skinsafe.core.experiments.collaboration_skin import collaboration_skin

# ------------------------------------------------------------------------------------ one cell

def cell(method: str, seed: int, scenario: str, damping_ratio: float, attachment_N_m: float, dt_ms: float,
         stacks: list, config: dict, skin: str, detail: bool = False) -> dict:
    """One scenario at one (damping, attachment, timestep) with each stack: its contact events, and
    with `detail` the force and pan traces and the task times (with and without the person). `config`:
    `CollabConfig.to_json()` (a Ray task's JSON), its seed `seed`."""
    from skinsafe.core.realtime import single_thread_blas
    from skinsafe.core.robot.kinematics import TaxelKinematics
    from skinsafe.core.skin.taxel_map import load

    torch.set_num_threads(1)
    single_thread_blas()
    cfg = CollabConfig.from_json({**config, "seed": seed})
    if not detail:  # no task time: the run ends soon after the last contact can happen
        cfg = replace(cfg, finish=0.3)
    design = load(skin)
    sc = None
    out = {"scenario": scenario, "damping_ratio": damping_ratio, "attachment_N_m": attachment_N_m, "dt_ms": dt_ms,
           "stacks": {}}
    for stack in stacks:
        if sc is None:
            kin = TaxelKinematics(_ur5().model, design)
            lay = layout(scenario, kin, cfg)
            sc = build(lay, design, damping_ratio, attachment_N_m, dt_ms, cfg)
            pot = learn_person(sc, lay, cfg) if any(s.startswith("full") for s in stacks) else None
        run = episode(sc, lay, stack, pot, cfg)
        names = [sc.model.body(b).name for b in range(sc.model.nbody)]
        events = contact_events(run["trace"], [p.region for p in lay.parts], sc.control_dt, run["acted"], names)
        res = {"events": events, "task_time_s": run["done"], "cap_retreats": run["cap_retreats"],
               "unstable": run["unstable"]}
        if detail:
            tr = run["trace"]
            every = trace_every(dt_ms)  # the force trace at 1 ms, or at the step where it is coarser
            res["force_N"] = tr["force_N"].sum(axis=1)[::every].round(2).tolist() if len(tr["time_s"]) else []
            res["pan_rad"] = run["pan"].round(4).tolist()
            res["no_person_task_time_s"] = episode(sc, lay, stack, pot, cfg, person=False)["done"] \
                if lay.goal is not None else None
        out["stacks"][stack] = res
    return out


def _ur5():
    from skinsafe.core.robot.models import build_ur5

    return build_ur5()


# ------------------------------------------------------------------------------------ the experiment

def config(args) -> CollabConfig:
    """The options every cell needs, from the command's flags."""
    return CollabConfig(args.pitch, args.duration, args.stay, args.finish, args.presence, args.pfl_factor,
                        tuple(args.pfl_regions) if args.pfl_regions else None, args.samples, args.steps, args.source,
                        args.person_speed, args.push, args.seed)


def run_experiment(args) -> dict:
    """Nominal runs of every scenario with every stack, then the sweep (module docstring)."""
    from skinsafe.core.experiments.runner import run_tasks
    from skinsafe.core.skin.taxel_map import load, save

    out_dir = Path(args.out or "results/collaboration")
    cfg = config(args)
    skin = Path(args.skin) if args.skin else out_dir / "collaboration_skin.json"
    if args.skin and not skin.is_file():
        raise SystemExit(f"--skin: '{skin}' is not a file; give a taxel map (or leave --skin out to design one)")
    if not args.skin and (args.redesign or not skin.exists()):
        save(collaboration_skin(cfg, args.cover_rounds, progress=not args.no_progress)[0], skin)
    design = load(skin)
    tasks = [_task(s, NOMINAL, list(args.stacks), cfg, skin, args.seed, detail=True) for s in SCENARIOS]
    if args.sweep:
        for s in SCENARIOS:
            for z in args.sweep_damping:
                for k in args.sweep_attach:
                    for dt in args.sweep_dt:
                        tasks.append(_task(s, {"damping_ratio": z, "attachment_N_m": k, "dt_ms": dt},
                                           list(args.sweep_stacks), cfg, skin, args.seed))
    results = run_tasks(cell, tasks, out_dir / "tasks", address=args.address, workers=args.workers,
                        progress=not args.no_progress, desc="collaboration", fresh=args.fresh,
                        cost=lambda t: (3 if t["detail"] else 1) * len(t["stacks"]) / t["dt_ms"])
    return summarise(results[:len(SCENARIOS)], results[len(SCENARIOS):], design, cfg)


def _task(scenario, cell_cfg, stacks, cfg, skin, seed, detail=False) -> dict:
    tag = f"{scenario}_z{cell_cfg['damping_ratio']:g}_k{cell_cfg['attachment_N_m']:g}_dt{cell_cfg['dt_ms']:g}"
    return {"method": tag + ("_detail" if detail else ""), "seed": seed, "scenario": scenario, **cell_cfg,
            "stacks": stacks, "config": cfg.to_json(), "skin": str(skin), "detail": detail}



# ------------------------------------------------------------------------------------ command

def add_arguments(p) -> None:
    import os

    D = CollabConfig  # the defaults

    p.add_argument("--out", default=None, help="output folder (default results/collaboration)")
    p.add_argument("--pitch", type=float, default=D.pitch, help="skin pitch (m)")
    p.add_argument("--duration", type=float, default=D.duration, help="the delivery sweep and the placing motion (s)")
    p.add_argument("--stay", type=float, default=D.stay, help="seconds the person stays in the path (the robot holds as long)")
    p.add_argument("--finish", type=float, default=D.finish, help="seconds for the robot to complete its task afterwards")
    p.add_argument("--presence", type=float, default=D.presence,
                   help="fraction of deliveries with the person at the bench (scales the learned danger)")
    p.add_argument("--samples", type=int, default=D.samples, help="static contact samples for the TDM")
    p.add_argument("--steps", type=int, default=D.steps, help="TDM training steps (batch 64)")
    p.add_argument("--source", choices=["planner", "teleoperation"], default=D.source,
                   help="the command source the stack filters in the delivery")
    p.add_argument("--person-speed", type=float, default=D.person_speed, help="the person's hand speed into the still robot (m/s)")
    p.add_argument("--push", type=float, default=D.push_N, help="the most the person's muscles push or pull a part (N)")
    p.add_argument("--pfl-regions", nargs="+", default=None,
                   help="body regions the PFL cap protects (default: the person's regions)")
    p.add_argument("--pfl-factor", type=float, default=D.pfl_factor,
                   help="PFL cap as a fraction of v_max (margin for the servos and the sampling)")
    p.add_argument("--sweep", action=argparse.BooleanOptionalAction, default=True,
                   help="run the robustness sweep (--no-sweep: the nominal runs only)")
    p.add_argument("--stacks", nargs="+", default=list(STACKS), choices=STACKS, help="the stacks of the nominal runs")
    p.add_argument("--sweep-stacks", nargs="+", default=["none", "full+pfl"], choices=STACKS)
    p.add_argument("--sweep-damping", type=float, nargs="+", default=list(SWEEP["damping_ratio"]),
                   help="contact damping ratios of the sweep")
    p.add_argument("--sweep-attach", type=float, nargs="+", default=list(SWEEP["attachment_N_m"]),
                   help="the person's attachment stiffnesses of the sweep (N/m)")
    p.add_argument("--sweep-dt", type=float, nargs="+", default=list(SWEEP["dt_ms"]), help="physics timesteps of the sweep (ms)")
    p.add_argument("--cover-rounds", type=int, default=3,
                   help="rounds of simulating the scenarios and covering where the person is met")
    p.add_argument("--redesign", action="store_true", help="place the skin's person modules again")
    p.add_argument("--skin", default=None,
                   help="a taxel map to run on as it is (default: OUT/collaboration_skin.json, designed when missing)")
    p.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1), help="local Ray CPUs (default %(default)s; 0: the tasks in this process, no Ray)")
    p.add_argument("--address", default=None, help="join this Ray cluster instead of starting a local Ray")
    p.add_argument("--fresh", action="store_true", help="re-run every cell instead of reusing finished ones")
    p.add_argument("--seed", type=int, default=D.seed)
    p.add_argument("--no-progress", action="store_true")


def check_args(args) -> None:
    """Refuse out-of-range options with a message naming the option and the fix."""
    from skinsafe.core.sim.body_regions import REGIONS

    checks = (("--pfl-factor", args.pfl_factor, 0 < args.pfl_factor <= 1, "a fraction of v_max in (0, 1]"),
              ("--presence", args.presence, 0 <= args.presence <= 1, "a fraction in [0, 1]"),
              ("--duration", args.duration, args.duration > 0, "seconds > 0"),
              ("--stay", args.stay, args.stay >= 0, "seconds >= 0"),
              ("--finish", args.finish, args.finish > 0, "seconds > 0"),
              ("--pitch", args.pitch, 0.005 <= args.pitch <= 0.05, "a pitch in [0.005, 0.05] m"),
              ("--person-speed", args.person_speed, 0 < args.person_speed <= 2, "m/s in (0, 2]"),
              ("--push", args.push, args.push > 0, "a force > 0 (N)"),
              ("--samples", args.samples, args.samples >= 10, "at least 10 static samples"),
              ("--steps", args.steps, args.steps >= 1, "at least 1 training step"),
              ("--workers", args.workers, args.workers >= 0, "0 (in this process) or more"),
              ("--cover-rounds", args.cover_rounds, args.cover_rounds >= 0, "0 or more rounds"))
    for name, value, ok, want in checks:
        if not (np.isfinite(value) and ok):
            raise SystemExit(f"{name} is {value}; give {want}")
    for name, values, lo, hi in (("--sweep-damping", args.sweep_damping, 0, 2), ("--sweep-attach", args.sweep_attach, 1, 1e5),
                                 ("--sweep-dt", args.sweep_dt, 0.05, 10)):
        for v in values:
            if not (np.isfinite(v) and lo <= v <= hi):
                raise SystemExit(f"{name} has {v}; give values in [{lo:g}, {hi:g}]")
    for r in args.pfl_regions or ():
        if r not in REGIONS:
            raise SystemExit(f"--pfl-regions: '{r}' is unknown; use one of {', '.join(REGIONS)}")


def run(args) -> int:
    from skinsafe.core.skin.files import atomic_write

    check_args(args)
    out_dir = Path(args.out or "results/collaboration")
    t0 = time.perf_counter()
    res = run_experiment(args)
    res["seconds"] = time.perf_counter() - t0
    atomic_write(out_dir / "collaboration.json", json.dumps(res, indent=1))
    atomic_write(out_dir / "collaboration.md", tables(res))
    save_plot(res, out_dir / "collaboration.png")
    for k, r in res["runs"].items():
        print(f"{k}: events={r['events']} within={r['within']} sensed={r['sensed']} peak_N={r['peak_N']:.0f} "
              f"worst_ratio={r['worst_ratio']:.2f} task_time_s={r['task_time_s']}")
    for row in res["sweep"]:
        if row["stack"] == "full+pfl":
            print(f"sweep {row['scenario']} zeta={row['damping_ratio']} attach={row['attachment_N_m']:g} "
                  f"dt={row['dt_ms']}ms: worst_ratio={row['worst_ratio']:.2f} peak_vs_none={row['peak_vs_none']}")
    for f in res["findings"]:
        print("finding:", f)
    print(f"wrote {out_dir / 'collaboration.json'}, collaboration.md and collaboration.png")
    return 0


