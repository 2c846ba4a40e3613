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
from skinsafe.core.app import report_figures as figs
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
    p.add_argument("--timing", help="also write the wall time, each stage's seconds and the machine's load to this "
                                    "JSON file (results/demo/demo_timing.json feeds the README)")


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
        images=[(info["pictures"][0], f"Retractability |J_p^T z| of each of the {info['taxels']:,} taxels at the scene's "
                                      "pose, rendered headless by the add-on (bright: the robot can pull this taxel "
                                      "back fast; dark: a dead spot)."),
                (info["pictures"][1], f"The {info['modules']} FPC modules coloured by interface board, "
                                      f"{info['boards']} boards (the key counts each board's taxels).")],
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
    budget = f"{len(fs['force'])} pokes" + ("" if ctx["full"] else " at the demo's reduced depths")
    rows = [{"merge": r["merge"], "epsilon": r["epsilon"], "contacts": r["contacts"],
             "dominant_fraction": r["dominant_fraction"], "others_fraction": ", ".join(f"{x:.3g}" for x in
                                                                                          r["others_fraction"]),
             "into_contact_mm": r["into_contact_mm"]} for r in res["multicontact"]]
    forms = [{"form": k, **{c: v[c] for c in ("achieved_median", "achieved_p10", "within_5pct", "drift_median")}}
             for k, v in res["forms"].items()]
    return Section(
        "Tactile defensiveness: pokes and retraction (paper Fig. 7, 8, 12)",
        f"Pokes of increasing force on taxel {fs['taxel']} ({fs['body']}) in MuJoCo: retraction distance = "
        f"{fs['slope'] * 100:.4f} cm/N x force (alpha/12 = {res['params']['alpha'] / 12 * 100:.4f}), R² = {fs['r2']:.5f}: "
        "heavier touch, further retraction, linearly, as the paper shows qualitatively.",
        images=[(str(figs.save(figs.poke_force(res), out / "report_force.png")),
                 f"Retraction distance against the peak force of each poke ({budget}) with the least-squares line "
                 "and eq. 10's alpha/12: heavier touch, further retraction."),
                (str(out / "poke_displacement.png"), f"The poked taxel's displacement along -z over time for each poke "
                                                      f"({budget}), solid, against eq. 10's quartic profile, dotted."),
                (str(figs.save(figs.poke_multicontact(res), out / "report_fig7.png")),
                 "Fig. 7: with 2 and 3 taxels touched at once, the share of its own eq. 10 distance each achieves "
                 "(1 = as if alone), for the prioritised QP and the closed-form merges (one retraction each).")],
        tables=[(rows, "Multi-contact merge: fraction of each taxel's own eq. 10 distance achieved; the dominant "
                       "(highest-priority) taxel first."),
                (forms, "6-D (paper, zero rotation) vs 3-D (position only) task: achieved/commanded -z distance.")])


DEMO_MAZE_METHODS = "SAC,SAC-TDM,AC,AC-TDM"


def stage_maze(ctx) -> Section:
    from skinsafe.core.experiments.maze import PRESETS
    from skinsafe.core.experiments.maze_claims import LAST, LEARNED_AT
    from skinsafe.core.experiments.maze_report import claim_statement

    out = ctx["out"] / "maze"
    argv = ["--out", str(out), "--no-progress"] + ([] if ctx["full"] else ["--demo", "--methods", DEMO_MAZE_METHODS])
    _command("skinsafe.core.app.experiment_maze", argv, "maze")
    results = json.loads((out / "maze_results.json").read_text())
    res = results["replicates"][0]["summary"]
    full = PRESETS["full"]
    grid_file = REPO / "results" / "maze" / "maze_results.json"
    grid = json.loads(grid_file.read_text()) if grid_file.is_file() else None
    rows = [{"method": m, **{k: v[k] for k in ("total_contacts_mean", "total_contacts_std", "goal_rate_mean",
                                                 "goal_rate_last_mean", "mean_steps")}} for m, v in res["methods"].items()]
    cfg = {**results["evaluation_conditions"], "seeds": len(results["eval_seeds"])}
    text = claim_statement(res["claim"])
    if not ctx["full"]:
        text = (f"Reduced budget: {cfg['seeds']} seeds x {cfg['episodes']} episodes (at most {cfg['max_steps']} "
                f"macro-actions) of {len(rows)} of the {len(full.methods)} methods; the paper's budget is "
                f"`skinsafe experiment maze` ({len(full.eval_seeds)} seeds x {full.episodes} episodes, all nine). "
                "What this run can show: the -TDM variants' contact events stopping within the first episodes (cost "
                "curves) and whether each method finds the goal at this budget. What it cannot show: the nine-way "
                f"ranking of Fig. 9b over {len(full.eval_seeds)} held-out seeds (the full grid's result is in the README and "
                "results/maze/). ")
        slow = [m for m, v in res["methods"].items() if v["goal_rate_last_mean"] < LEARNED_AT]
        text += (f"Here {', '.join(slow)} reached the goal in fewer than {LEARNED_AT:.0%} of the last "
                 f"{min(LAST, cfg['episodes'])} episodes, so their totals are not yet those of a trained policy.\n\n"
                 if slow else f"Every method shown reached the goal in at least {LEARNED_AT:.0%} of the last "
                 f"{min(LAST, cfg['episodes'])} episodes.\n\n") + claim_statement(res["claim"])
    budget = (f"{figs.plural(cfg['seeds'], 'seed')} x {figs.plural(cfg['episodes'], 'episode')} of at most "
              f"{cfg['max_steps']} macro-actions")
    third = ("the -TDM variants against the safe-RL baselines of this run" if grid is None or
             any(b in res["methods"] for b in figs.BASELINES) else
             "the -TDM variants against the safe-RL baselines at the paper's budget, from the committed full grid "
             "(results/maze, which this demo does not re-run; online contacts: RRL's and SQRL's offline phase is in their "
             "totals, not drawn)")
    return Section("Strategy layer: the maze (paper Fig. 9)", text,
                   images=[(str(figs.save(figs.maze(results, grid), out / "report_maze.png")),
                            f"Left and middle: each method's episode return and contact events per episode in this run "
                            f"({budget}; moving average over 5 episodes). Right: contact events so far, {third}.")],
                   tables=[(rows, "total_contacts: contact events over all training episodes (lower is safer); "
                                  "goal_rate_last: share of the last 20 episodes that reached the goal.")])


def stage_tracking(ctx) -> Section:
    out = ctx["out"] / "tracking"
    from skinsafe.core.experiments.tracking_report import label_set_statement

    _command("skinsafe.core.app.experiment_tracking", ["--out", str(out), "--no-progress"] + ([] if ctx["full"] else ["--quick"]),
             "tracking")
    res = json.loads((out / "tracking.json").read_text())
    cfg = {**res["config"], "seeds": res["experiment"]["seeds"]}
    ticks = sorted(res["path_contact_ticks"].values())
    span = str(ticks[0]) if ticks[0] == ticks[-1] else f"{ticks[0]}-{ticks[-1]}"
    text = (f"Vanilla velocity tracking vs TDM modulation vs 2-step TDM modulation, the TDM re-trained on all "
            f"experience after each episode; contacts from the skin readout of {res['n_taxels']} taxels. The balls "
            f"sit on the path: the exact desired path itself overlaps a ball in {span} of "
            f"{int(round(cfg['duration'] / cfg['control_dt']))} ticks, so only leaving the path avoids contact. ")
    if ctx["full"]:
        text += label_set_statement(res["labels"][res["headline"]])
    else:
        text += (f"Reduced budget: {len(cfg['seeds'])} seed x {cfg['episodes']} episodes on a coarser skin; the paper's "
                 "budget is `skinsafe experiment tracking` (10 held-out seeds x 10 episodes). It can show the first re-trainings "
                 "taking effect (episode 1 is unmodulated for every method); it cannot show episodes 6-10, where the "
                 "paper's claim (2-step TDM near zero contacts, below the TDM) is measured.")
    budget = f"{figs.plural(len(cfg['seeds']), 'seed')} x {figs.plural(cfg['episodes'], 'episode')}, {res['n_taxels']:,} taxels"
    return Section("Modulation layer: TDM learning and UR5 tracking (paper Fig. 11)", text,
                   images=[(str(figs.save(figs.tracking_contacts(res), out / "report_contacts.png")),
                            f"Control ticks in contact per episode for each method ({budget}); the TDM is re-trained "
                            "on all experience after each episode, episode 1 is unmodulated for every method."),
                           (str(figs.save(figs.tracking_paths(res), out / "report_paths.png")),
                            f"The last episode's end-effector path per method ({budget}): desired path dashed, the balls "
                            "orange, where the skin touched them green.")],
                   tables=[(tracking_rows(res), "contacts: control ticks with a taxel over its threshold per episode "
                                                "(mean over seeds); tracking_error_mm: mean end-effector deviation "
                                                "from the path; first_zero_episode: the first episode without "
                                                "contact, per seed.")])


def tracking_rows(res: dict) -> list[dict]:
    """The summary rows with only the columns this run measured: episodes 6-10 (the paper's
    window) only when the run had 10 episodes."""
    n = res["config"]["episodes"]
    rows = []
    for r in res["labels"][res["headline"]]["replicates"][0]["summary"]:
        row = {"method": r["method"], "contacts_first": r["contacts_first"], f"contacts_last (episode {n})":
               r["contacts_last"], f"contacts_mean (episodes 1-{n})": r["contacts_mean"]}
        if n >= 10:
            row |= {"contacts_ep6_10": r["contacts_ep6_10"], "contacts_ep6_10_std": r["contacts_ep6_10_std"]}
        row["tracking_error_mm"] = r["tracking_error_mm"]
        row["first_zero_episode"] = ", ".join("never" if e is None else str(e) for e in r["first_zero_episode"])
        rows.append(row)
    return rows


MEANING = {
    "desk": "min_clearance_mm: closest the arm came to the desk (negative: it pressed into it); desk_force_N: peak force on the desk.",
    "collaboration": "scenario/stack (delivery: the robot strikes a hand; clamp: it presses a fist on the table; person: "
                     "the hand pushed into the still robot); events: contacts with the person; within: every contact "
                     "under its ISO/TS 15066 force and pressure limits; sensed: every contact on skin; peak_N: highest "
                     "force; worst_ratio: highest force or pressure over its limit; task_time_s: the robot's task done.",
}


def stage_scenes(ctx) -> Section:
    images, tables = [], []
    skin = Path(__file__).resolve().parents[2] / "results" / "collaboration" / "collaboration_skin.json"
    reduced = {"collaboration": ["--no-sweep", "--stacks", "none", "full+pfl", "--samples", "600", "--steps", "300",
                                 "--workers", "1"] + (["--skin", str(skin)] if skin.is_file() else ["--cover-rounds", "1"])}
    for name in ("desk", "collaboration"):
        out = ctx["out"] / name
        _command(cli.EXPERIMENTS[name][0], ["--out", str(out)] + reduced.get(name, []), name)
        res = json.loads((out / f"{name}.json").read_text())
        if name == "desk":
            images.append((str(figs.save(figs.desk(res), out / "report_desk.png")),
                           "Fig. 14: the arm's clearance to the desk over time after a touch on top of the forearm "
                           "(0.1-0.2 s) triggers a retraction toward the desk, without modulation and with the TDM and "
                           "2-step TDM modulation (one run each, the sample skin)."))
        else:
            images.append((str(figs.save(figs.collaboration(res), out / "report_collaboration.png")),
                           "Fig. 15 as an ISO/TS 15066 test: the force on the person per scenario (delivery: the robot "
                           "strikes a hand; clamp: it presses a fist on the table; person: the hand pushed into the "
                           "still robot) and stack, and each contact's worst ratio to its force and pressure limits "
                           "(the nominal cell only, reduced TDM; the sweep is left out)."))
        tables.append(([{"run": run, **{k: v for k, v in r.items() if not isinstance(v, (list, dict))}}
                        for run, r in res["runs"].items()], MEANING[name]))
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
                   images=[(str(out / "trade.png"), f"Each knob's settings as speed-up against error, both relative to "
                                                     f"the knob's most accurate setting; filled: Pareto-optimal "
                                                     f"({'full' if ctx['full'] else 'quick'} sweep, {len(rows)} points).")],
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


def safety_row(r: dict) -> dict:
    """An audit row with its missing ratio said in words: the dominant ratio is measured only on
    ticks where nothing binds the dominant contact, and with many contacts a few cases have none."""
    if r.get("dominant_ratio_min") is None:
        r = {**r, "dominant_ratio_min": f"not measured: no tick left the dominant contact free in {r['cases']} cases"}
    return r


def stage_bench(ctx) -> Section:
    tables = []
    for name, argv in tqdm(BENCH_ARGS.items(), desc="benchmarks", leave=False):
        module = cli.BENCHES[name][0]
        rows = _command(module, argv, name, bench=True)
        if name in BENCH_KEYS:
            rows = [{k: r[k] for k in BENCH_KEYS[name] if k in r} for r in rows]
        if name == "safety":
            rows = [safety_row(r) for r in rows]
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
    sections, failed, seconds = [], [], {}
    t0 = time.perf_counter()
    bar = tqdm([s for s in STAGES if s not in skip], desc="demo")
    for name in bar:
        bar.set_postfix(stage=name)
        t = time.perf_counter()
        try:
            sec = STAGES[name](ctx)
            seconds[name] = round(time.perf_counter() - t, 1)
            sec.text += f"\n\n(stage '{name}' took {seconds[name]:.0f} s)"
        except Exception as e:  # noqa: BLE001 — a failed stage is reported, the others still run
            if name == "blender":  # everything after needs the design
                raise
            failed.append(name)
            sec = Section(f"Stage '{name}' failed", f"{type(e).__name__}: {e}\n\n{traceback.format_exc()[-2000:]}")
        sections.append(sec)
    path = write_report(out / "report.html", "skinsafe demo report",
                        f"The sample UR5 skin end to end ({'full' if args.full else 'reduced'} configuration, "
                        f"{time.perf_counter() - t0:.0f} s).", sections)
    if args.timing:
        write_timing(args.timing, time.perf_counter() - t0, seconds, failed, args)
    print(f"wrote {path}" + (f"; failed stages: {', '.join(failed)}" if failed else ""))
    return 1 if failed else 0


def write_timing(path: str, wall: float, seconds: dict, failed: list[str], args) -> None:
    """The run's wall time and each stage's, with the machine's size and load (its 1, 5 and 15
    minute load averages at the end: the demo shares the machine with whatever else runs)."""
    import os
    import platform

    from skinsafe.core.skin.files import atomic_write

    atomic_write(path, json.dumps({
        "wall_s": round(wall, 1), "stages": seconds, "failed": failed, "skipped": args.skip, "full": args.full,
        "cpus": os.cpu_count(), "load_average": [round(x, 1) for x in os.getloadavg()], "machine": platform.machine(),
        "date": time.strftime("%Y-%m-%d")}, indent=1))
