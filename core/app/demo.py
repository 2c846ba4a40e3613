"""`skinsafe demo`: the whole product on the bundled sample scene, headless, into one report.

Stages: open `blend_assets/ur5_skin.blend` with the add-on in its own bpy process (re-generate
the skin, map Jacobians, export the taxel map, render the heat maps); export the MuJoCo scene;
poke and retract; the strategy layer in the maze; TDM learning and modulated tracking; deploy
the map to emulated boards and stream back; the speed/accuracy sweep; the benchmarks; then
`out/report.html`. Reduced configurations by default (minutes); `--full` runs the experiments
at full length. The demo is the application layer: it reaches into every package lazily.
"""
from __future__ import annotations

import importlib
import json
import subprocess
import sys
import time
import traceback
from pathlib import Path

import numpy as np
from tqdm import tqdm

from skinsafe.core.app import cli
from skinsafe.core.app.report import Section, write_report
from skinsafe.core.design.coverage import coverage_report
from skinsafe.core.robot.models import build_ur5
from skinsafe.core.skin.taxel_map import load

REPO = Path(__file__).resolve().parents[2]
SAMPLE_BLEND = REPO / "blend_assets" / "ur5_skin.blend"


def add_arguments(p) -> None:
    p.add_argument("--out", default="out", help="output folder (default: out)")
    p.add_argument("--blend", default=str(SAMPLE_BLEND), help="the skin scene to open")
    p.add_argument("--full", action="store_true", help="full-length experiments (tens of minutes) instead of the reduced ones")
    p.add_argument("--skip", default="", help="comma-separated stages to skip: " + ",".join(STAGES))


def _command(module: str, argv: list[str], name: str, bench: bool = False):
    """Run a skinsafe command or benchmark in this process with its own argument parser."""
    mod = importlib.import_module(module)
    args = cli.module_args(mod, f"skinsafe {name}", "", argv, name, bench)
    if bench:
        return mod.rows(args)
    rc = int(mod.run(args) or 0)
    if rc:
        raise RuntimeError(f"skinsafe {name} {' '.join(argv)} exited with {rc}")
    return rc


def stage_blender(ctx) -> Section:
    out = ctx["out"] / "blender"
    proc = subprocess.run([sys.executable, "-m", "skinsafe.addon.headless", "--blend", ctx["blend"], "--out", str(out)],
                          capture_output=True, text=True)
    if proc.returncode:
        raise RuntimeError(f"the Blender stage failed:\n{proc.stderr[-3000:]}")
    info = json.loads(proc.stdout.strip().splitlines()[-1])
    robot = build_ur5()
    design = load(info["taxel_map"], robot.body_names)
    ctx.update(design=design, robot=robot, map=info["taxel_map"])
    cov = coverage_report(design, robot.model)
    rows = [{"body": k, **{c: v[c] for c in ("taxels", "modules", "fraction", "density_per_cm2")}}
            for k, v in cov.items() if k != "total"]
    return Section(
        "The skin, designed in Blender",
        f"{ctx['blend']} opened headless with the add-on: {info['modules']} FPC modules re-generated "
        f"(conformal geodesic wrap on the link meshes), {info['taxels']} taxels on {info['boards']} boards, "
        "each with its frame (z the outward normal) and its Jacobian mapping at the scene's pose.",
        images=[(info["pictures"][0], "Retractability |J_p^T z| per taxel at the scene's pose (bright: the robot can "
                                      "pull this taxel back fast; dark: a dead spot)"),
                (info["pictures"][1], "FPC modules coloured by interface board")],
        tables=[(rows, "fraction: skinned share of the link's surface; density: taxels per cm² of skin.")])


def stage_export(ctx) -> Section:
    import mujoco

    out = ctx["out"] / "scene"
    _command("skinsafe.exporters.cli_export", [ctx["map"], str(out), "--probe", "0.01"], "export")
    model = mujoco.MjModel.from_xml_path(str(out / "scene.xml"))
    rows = [{"file": "scene.xml", "bodies": model.nbody, "geoms": model.ngeom, "taxel sites": model.nsite - 1,
             "dof": model.nv, "timestep_s": model.opt.timestep}]
    return Section("MuJoCo export", "The design exported with MjSpec (the robot's own spec, one site per taxel in "
                   "its body frame, a probe obstacle) and loaded back with plain mujoco.MjModel.from_xml_path.",
                   tables=[(rows, "taxel sites: one per taxel, oriented as the taxel frame.")])


def stage_poke(ctx) -> Section:
    out = ctx["out"] / "poke"
    argv = ["--out", str(out), "--map", ctx["map"]]
    if not ctx["full"]:
        argv += ["--depths", "0.0005,0.001,0.0015,0.002,0.003", "--forms-stride", "60"]
    _command("skinsafe.core.experiments.poke", argv, "poke")
    res = json.loads((out / "poke_results.json").read_text())
    fs = res["force_sweep"]
    rows = [{"merge": r["merge"], "epsilon": r["epsilon"], "contacts": r["contacts"],
             "dominant_fraction": r["dominant_fraction"], "others_fraction": str(r["others_fraction"])}
            for r in res["multicontact"]]
    forms = [{"form": k, **{c: v[c] for c in ("achieved_median", "achieved_p10", "within_5pct", "drift_median")}}
             for k, v in res["forms"].items()]
    return Section(
        "Tactile defensiveness: pokes and retraction (paper Fig. 7, 8, 12)",
        f"Pokes of increasing force on taxel {fs['taxel']} ({fs['body']}) in MuJoCo: retraction distance = "
        f"{fs['slope'] * 100:.4f} cm/N x force (alpha/12 = {res['params']['alpha'] / 12 * 100:.4f}), R² = {fs['r2']:.5f}: "
        "heavier touch, further retraction, linearly, as the paper shows qualitatively.",
        images=[(str(p), p.stem.replace("_", " ")) for p in sorted(out.glob("*.png"))],
        tables=[(rows, "Multi-contact merge: fraction of each taxel's own eq. 10 distance achieved; the dominant "
                       "(highest-priority) taxel first."),
                (forms, "6-D (paper, zero rotation) vs 3-D (position only) task: achieved/commanded -z distance.")])


DEMO_MAZE_METHODS = "SAC,SAC-TDM,AC,AC-TDM"


def stage_maze(ctx) -> Section:
    from skinsafe.core.experiments import maze

    out = ctx["out"] / "maze"
    argv = ["--out", str(out), "--no-progress"] + ([] if ctx["full"] else ["--demo", "--methods", DEMO_MAZE_METHODS])
    _command("skinsafe.core.experiments.maze", argv, "maze")
    res = json.loads((out / "maze_results.json").read_text())["summary"]
    rows = [{"method": m, **{k: v[k] for k in ("total_contacts_mean", "total_contacts_std", "goal_rate_mean",
                                                 "goal_rate_last_mean", "mean_steps")}} for m, v in res["methods"].items()]
    cfg = res["config"]
    text = res["claim"]["statement"]
    if not ctx["full"]:
        text = (f"Reduced budget: {cfg['seeds']} seeds x {cfg['episodes']} episodes (at most {cfg['max_steps']} "
                f"macro-actions) of {len(rows)} of the {len(maze.METHODS)} methods; the paper's budget is "
                f"`skinsafe experiment maze` ({maze.FULL['seeds']} seeds x {maze.FULL['episodes']} episodes, all nine). "
                "What this run can show: the -TDM variants' contact events stopping within the first episodes (cost "
                "curves) and whether each method finds the goal at this budget. What it cannot show: the nine-way "
                "ranking of Fig. 9b over 5 seeds (the full grid's result is in the README and results/maze/). ")
        slow = [m for m, v in res["methods"].items() if v["goal_rate_last_mean"] < maze.LEARNED_AT]
        text += (f"Here {', '.join(slow)} reached the goal in fewer than {maze.LEARNED_AT:.0%} of the last "
                 f"{min(maze.LAST, cfg['episodes'])} episodes, so their totals are not yet those of a trained policy.\n\n"
                 if slow else f"Every method shown reached the goal in at least {maze.LEARNED_AT:.0%} of the last "
                 f"{min(maze.LAST, cfg['episodes'])} episodes.\n\n") + res["claim"]["statement"]
    return Section("Strategy layer: the maze (paper Fig. 9)", text,
                   images=[(str(out / "maze_curves.png"), "Return and contact-event (cost) curves per method")],
                   tables=[(rows, "total_contacts: contact events over all training episodes (lower is safer); "
                                  "goal_rate_last: share of the last 20 episodes that reached the goal.")])


def stage_tracking(ctx) -> Section:
    out = ctx["out"] / "tracking"
    _command("skinsafe.core.experiments.tracking", ["--out", str(out), "--no-progress"] + ([] if ctx["full"] else ["--quick"]),
             "tracking")
    res = json.loads((out / "tracking.json").read_text())
    cfg = res["config"]
    ticks = list(res["path_contact_ticks"].values())
    text = (f"Vanilla velocity tracking vs TDM modulation vs 2-step TDM modulation, the TDM re-trained on all "
            f"experience after each episode; contacts from the skin readout of {res['n_taxels']} taxels. The balls "
            f"sit on the path: the exact desired path itself overlaps a ball in {min(ticks)}-{max(ticks)} of "
            f"{int(round(cfg['duration'] / cfg['control_dt']))} ticks, so only leaving the path avoids contact. ")
    if ctx["full"]:
        text += res["claim"]["statement"]
    else:
        text += (f"Reduced budget: {len(cfg['seeds'])} seed x {cfg['episodes']} episodes on a coarser skin; the paper's "
                 "budget is `skinsafe experiment tracking` (3 seeds x 10 episodes). It can show the first re-trainings "
                 "taking effect (episode 1 is unmodulated for every method); it cannot show episodes 6-10, where the "
                 "paper's claim (2-step TDM near zero contacts, below the TDM) is measured.")
    return Section("Modulation layer: TDM learning and UR5 tracking (paper Fig. 11)", text,
                   images=[(str(p), p.stem.replace("_", " ")) for p in sorted(out.glob("*.png"))],
                   tables=[(res["summary"], "contacts: control ticks with a taxel over its threshold per episode (mean "
                                            "over seeds); tracking_error_mm: mean end-effector deviation from the path.")])


MEANING = {
    "desk": "min_clearance_mm: closest the arm came to the desk (negative: it pressed into it); desk_force_N: peak force on the desk.",
    "collaboration": "scenario/stack (delivery: the robot strikes a hand; clamp: it presses a fist on the table; person: "
                     "the hand pushed into the still robot); events: contacts with the person; within: every contact "
                     "under its ISO/TS 15066 force and pressure limits; sensed: every contact on skin; peak_N: highest "
                     "force; worst_ratio: highest force or pressure over its limit; task_time_s: the robot's task done.",
}


def stage_scenes(ctx) -> Section:
    sections = []
    skin = Path(__file__).resolve().parents[2] / "results" / "collaboration" / "collaboration_skin.json"
    reduced = {"collaboration": ["--no-sweep", "--stacks", "none", "full+pfl", "--samples", "600", "--steps", "300",
                                 "--workers", "1"] + (["--skin", str(skin)] if skin.is_file() else ["--cover-rounds", "1"])}
    for name in ("desk", "collaboration"):
        out = ctx["out"] / name
        _command(cli.EXPERIMENTS[name][0], ["--out", str(out)] + reduced.get(name, []), name)
        sections.append((name, out))
    images, tables = [], []
    for name, out in sections:
        images += [(str(p), f"{name}: {p.stem.replace('_', ' ')}") for p in sorted(out.glob("*.png"))]
        runs = json.loads((out / f"{name}.json").read_text())["runs"]
        tables.append(([{"run": run, **{k: v for k, v in r.items() if not isinstance(v, (list, dict))}}
                        for run, r in runs.items()], MEANING[name]))
    return Section("Layers together: desk and collaboration scenes (paper Fig. 14, 15)",
                   "A touch on top of the arm triggers retraction toward a desk, modulation stops it before the desk; "
                   "a person reaches into a delivery: each stack's contact forces against the ISO/TS 15066 limits.",
                   images=images, tables=tables)


def stage_hardware(ctx) -> Section:
    from skinsafe.hardware.deploy import deploy
    from skinsafe.hardware.emulator import EmulatorProcess
    from skinsafe.hardware.stream import SkinStream

    design = ctx["design"]
    flash = ctx["out"] / "boards"
    updates = []
    with EmulatorProcess([(b.uid, b.capacity) for b in design.boards], flash) as emu:
        ports = {b.id: emu.ports[b.uid] for b in design.boards}
        reports = deploy(design, ports)
        with SkinStream(design, ports, rate_hz=100) as stream:
            stream.run(updates.append, seconds=2.0)
    last = updates[-1]
    rows = [{"board": r.board.name, "uid": hex(r.board.uid), "status": r.status, "taxels":
             int((design.taxels.board == r.board.id).sum()), "bytes": r.tx_bytes + r.rx_bytes,
             "seconds": round(r.seconds, 3)} for r in reports]
    lit = int(np.count_nonzero(np.nan_to_num(last.peak) > 0))
    if not all(r.ok for r in reports):
        raise RuntimeError("deploy failed: " + "; ".join(r.line() for r in reports if not r.ok))
    return Section("Deploy to the boards and stream back",
                   f"The taxel map pushed to {len(reports)} emulated boards (each its own pseudo-terminal, opened by "
                   f"pyserial like /dev/ttyUSB0), committed, read back and hash-verified; then 2 s of streaming: "
                   f"{sum(u.frames for u in updates)} frames, {last.lost} lost, {last.corrupt} corrupt, "
                   f"{lit} taxels pressed.",
                   tables=[(rows, "status updated/unchanged: the board runs exactly this map (SHA-256 verified).")])


def stage_trade(ctx) -> Section:
    from skinsafe.core.app.trade import run_sweep

    out = ctx["out"] / "trade"
    rows = run_sweep(quick=not ctx["full"], out=out)
    keep = ("knob", "value", "ms", "unit", "speedup_vs_reference", "error", "error_metric", "pareto")
    return Section("Speed vs accuracy (skinsafe trade)",
                   "Each knob swept against its most accurate setting (error 0, speedup 1), one Ray task per point.",
                   images=[(str(out / "trade.png"), "Speed vs error per knob; filled: Pareto-optimal")],
                   tables=[([{k: r.get(k) for k in keep} for r in rows], "error_metric names the accuracy measure.")])


BENCH_ARGS = {
    "jacobians": ["--sizes", "1024,4096", "--repeat", "20"],
    "design": ["--sizes", "2560", "--repeat", "1"],
    "sensing": ["--sizes", "1024,4096", "--sweeps", "taxels", "--steps", "100", "--plot", ""],
    "retraction": ["--active", "1,8,64", "--repeat", "50"],
    "modulation": [],
    "safety": ["--cases", "20", "--nonfinite", "20"],
    "pfl": ["--taxels", "4096", "--repeat", "50"],
    "serial": ["--boards", "1", "4", "--repeat", "1"],
}
BENCH_MEANING = {
    "jacobians": "ms per call for all taxels' (6 x nv) Jacobians; speedup vs one mj_jac per taxel.",
    "design": "place_s: placing modules with frames and Jacobian mapping; regen_ms: re-generating one 256-taxel module.",
    "sensing": "overhead_vs_skinless: what the skin adds to the robot's step; truth_*: lit taxels and forces against "
               "the probes' contact patches over the taxel cells; speedup_vs_tactile: vs MuJoCo's tactile sensor at "
               "equal lit accuracy (tactile_points vertices per cell); speedup_vs_touch: vs per-taxel touch sensors.",
    "retraction": "ms per defensiveness tick with `active` triggered taxels; speedup vs a per-taxel loop.",
    "safety": "audit on random contact sets (20 per count here; `make bench` runs thousands): into_contact_mm_worst, "
              "limit violations and fail_open must be 0 / <= 0.5 mm.",
    "pfl": "ms per ISO/TS 15066 speed-cap tick (all taxels' normal speeds capped); speedup vs a per-taxel loop.",
    "modulation": "ms per modulation tick (potential + gradient + M v) and per full three-layer tick.",
    "serial": "deploy_s: push + commit + read back at 1 Mbaud; decode_x_wire: stream decoding vs the wire rate.",
}


BENCH_KEYS = {  # the columns a reader needs first (the JSON rows carry the rest)
    "sensing": ("n_taxels", "readout", "kernel", "steps_per_s", "read_us", "skinless_step_us", "overhead_vs_skinless",
                "speedup_vs_tactile", "tactile_points", "truth_lit_precision", "truth_lit_recall", "truth_lit_f1",
                "truth_force_err", "speedup_vs_touch"),
}


def stage_bench(ctx) -> Section:
    tables = []
    for name, argv in tqdm(BENCH_ARGS.items(), desc="benchmarks", leave=False):
        module = cli.BENCHES[name][0]
        rows = _command(module, argv, name, bench=True)
        if name in BENCH_KEYS:
            rows = [{k: r[k] for k in BENCH_KEYS[name] if k in r} for r in rows]
        tables.append((rows, f"skinsafe bench {name} {' '.join(argv)} — {BENCH_MEANING[name]}"))
    return Section("Benchmarks (reduced sizes; `make bench` for the full ones)",
                   "Medians of repeated runs in one process; ratios against a simple reference in the same run.",
                   tables=tables)


STAGES = {
    "blender": stage_blender, "export": stage_export, "poke": stage_poke, "maze": stage_maze,
    "tracking": stage_tracking, "scenes": stage_scenes, "hardware": stage_hardware, "trade": stage_trade,
    "bench": stage_bench,
}


def run(args) -> int:
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    skip = {s.strip() for s in args.skip.split(",") if s.strip()}
    unknown = skip - set(STAGES)
    if unknown:
        raise SystemExit(f"skinsafe demo: unknown stage(s) {sorted(unknown)}; stages are {', '.join(STAGES)}")
    ctx = {"out": out, "blend": args.blend, "full": args.full}
    if "blender" in skip:  # the generated sample skin stands in for the Blender scene
        from skinsafe.core.design.sample import make_sample_design
        from skinsafe.core.skin.taxel_map import save

        robot = build_ur5()
        design = make_sample_design("ur5", robot=robot)
        ctx.update(design=design, robot=robot, map=str(save(design, out / "sample_skin.json")))
    sections, failed = [], []
    t0 = time.perf_counter()
    bar = tqdm([s for s in STAGES if s not in skip], desc="demo")
    for name in bar:
        bar.set_postfix(stage=name)
        t = time.perf_counter()
        try:
            sec = STAGES[name](ctx)
            sec.text += f"\n\n(stage '{name}' took {time.perf_counter() - t:.0f} s)"
        except Exception as e:  # noqa: BLE001 — a failed stage is reported, the others still run
            if name == "blender":  # everything after needs the design
                raise
            failed.append(name)
            sec = Section(f"Stage '{name}' failed", f"{type(e).__name__}: {e}\n\n{traceback.format_exc()[-2000:]}")
        sections.append(sec)
    path = write_report(out / "report.html", "skinsafe demo report",
                        f"The sample UR5 skin end to end ({'full' if args.full else 'reduced'} configuration, "
                        f"{time.perf_counter() - t0:.0f} s).", sections)
    print(f"wrote {path}" + (f"; failed stages: {', '.join(failed)}" if failed else ""))
    return 1 if failed else 0
