"""`skinsafe bench runtime [--faults]`: the safety runtime closed-loop, the real `skinsafe run` in its own process.

Rows (default): the UR5 sample skin cut to `--taxels` (4,096 and 16,384: whole 64-taxel modules on
boards of 1,024 channels), the `sim` driver at 500 Hz, emulated boards at `--rate`, the arm driven by a
trajectory (shoulder pan at 0.2 rad/s) into a sprung post 1 cm in front of the taxel the pan sweeps
into it. Per row, over `--repeats` runs (worst case where it says so):
- loop_hz_p50 (median of the runs' medians), period_ms_p99 (worst): the loop's rate and jitter;
- latency_ms_p50 / p99 / max (worst): a frame holding a contact complete on the host -> its command
  leaves for the robot;
- reaction_ms (worst): contact onset in the sim -> the touched taxel's measured motion points out of
  the contact (MuJoCo's clock);
- peak_N, into_contact_mm_worst (worst): the post's largest contact force, and how far the taxel went
  into the post after the onset; `peak_N_in_process` is the same contact with the stack fed straight
  from the sim's readout (no boards, no serial; same code, `SimDriver(realtime=False)`);
- stale_stops: runs a staleness watchdog (silent board, robot state, command) stopped with nothing
  injected (the shared machine's stalls), or a board was silent before the robot moved; such a run is run
  again (up to RETRIES times) and the row's figures are those of the runs that went to the end;
  frames_lost: frames sent that never arrived.
`--view off page browser`: a row per mode (key `view`), the modes' runs alternating so they share the
machine's load: without the live view, with `run --view` (its stream and page process), and with a headless
Chromium on the page too; per_run_* list each run's loop figures (the spread).
`--faults`: the fault storm (core/app/runtime_faults.py) in its own process, one row: runs, faults
(runs the fault stopped), stopped_within_2_periods (fraction: zero velocity sent within 2 control
periods of the detection), unnamed, tracebacks, records_readable (fraction), and named_as_injected.
"""
from __future__ import annotations

import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from skinsafe.core.design.sample import make_sample_design
from skinsafe.core.robot.models import build_ur5
from skinsafe.core.skin.boards import assign_boards, number_channels
from skinsafe.core.skin.model import Module, SkinDesign

PITCHES = (0.01, 0.0072, 0.005, 0.0036, 0.0025)  # the sample skin gets denser until it holds enough taxels
PAN_SPEED = 0.2  # rad/s of the shoulder pan in the trajectory
CONTACT = "post:joint=0,gap=0.01"
SECONDS = 3.0
STALE = ("skin-silent", "robot-state", "command-stale")
RETRIES = 5
VIEW_PORT = 8480


def add_arguments(p) -> None:
    p.add_argument("--taxels", type=int, nargs="+", default=[4096, 16384])
    p.add_argument("--capacity", type=int, default=1024, help="channels per board")
    p.add_argument("--rate", type=int, default=100, help="board frames per second")
    p.add_argument("--repeats", type=int, default=2, help="runs per row")
    p.add_argument("--period", type=float, default=0.002, help="the sim's control period, s (0.002: the UR e-series' 500 Hz)")
    p.add_argument("--faults", action="store_true", help="the fault storm instead (one row)")
    p.add_argument("--runs", type=int, default=204, help="--faults: runs (one fault each)")
    p.add_argument("--fault-rate", type=int, default=50, help="--faults: board frames per second (a board is silent "
                   "after 2 frame periods: 40 ms, so a 50 ms delay trips it and the machine's stalls mostly do not)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--view", nargs="+", default=["off"], choices=("off", "page", "browser"),
                   help="rows without the live view (off), with `run --view` (page: the stream and its page process), "
                   "and also with a headless Chromium showing the page (browser); the runs alternate between them")


def sample_skin(n: int, capacity: int, robot=None) -> SkinDesign:
    """The UR5 sample skin with exactly the first whole modules holding `n` taxels (or as close below as
    whole modules allow), on boards of `capacity` channels."""
    robot = robot or build_ur5()
    for pitch in PITCHES:
        d = make_sample_design("ur5", pitch=pitch, board_capacity=capacity, robot=robot)
        if d.n_taxels >= n:
            break
    else:
        raise ValueError(f"the sample skin holds at most {d.n_taxels} taxels; ask for fewer")
    sizes = np.bincount(d.taxels.module)
    keep = [m for m, total in zip(d.modules, np.cumsum([sizes[m.id] for m in d.modules])) if total <= n]
    ids = {m.id for m in keep}
    t = d.taxels.subset(np.flatnonzero(np.isin(d.taxels.module, list(ids))))
    boards, of = assign_boards(t.module, {m.id: int(sizes[m.id]) for m in keep}, capacity)
    t.board = np.array([of[int(m)] for m in t.module], dtype=np.int32)
    t.channel = number_channels(t.module, t.board)
    modules = [Module(**{**m.__dict__, "board": of[m.id]}) for m in keep]
    design = SkinDesign(d.robot, d.bodies, modules, boards, t)
    design.validate("runtime bench skin", robot.body_names)
    return design


def write_trajectory(path: Path, robot, seconds: float = SECONDS) -> Path:
    """The shoulder pan turning positive at PAN_SPEED from home (into the post), the other joints still."""
    names = [robot.model.joint(j).name for j in range(robot.model.nv)]
    t = np.linspace(0.0, seconds, int(seconds * 10) + 1)
    q = np.repeat(robot.home[None], len(t), 0)
    q[:, 0] += PAN_SPEED * t
    path.write_text("t," + ",".join(names) + "\n" + "\n".join(",".join(f"{x:.9g}" for x in (a, *b)) for a, b in zip(t, q)))
    return path


def _contact():
    from skinsafe.core.sim.robot_driver import Contact

    return Contact("post", joint=0, gap=0.01)


def reference(design, robot, traj: Path, period: float = 0.002) -> dict:
    """The same contact with the stack fed straight from the sim's readout (no boards): its world stats."""
    from skinsafe.core.runtime.commands import Trajectory
    from skinsafe.core.runtime.layers import build_stack
    from skinsafe.core.runtime.loop import warm_up
    from skinsafe.core.sim.robot_driver import SimDriver

    drv = SimDriver(design, robot, None, period, _contact(), realtime=False)
    lim = drv.limits()
    stack = build_stack(design, robot.model, lim["qd_max"], lim["qdd_max"], period)
    warm_up(stack, robot.home, design.taxels.thresholds["force"], period)
    src = Trajectory(traj, drv.joint_names, lim)

    def control(s):
        if s.t >= SECONDS:
            return None
        return stack.tick(s.t, s.q, {"force": drv.forces}, src(s.t, s.q), period, qdot=s.qd)
    drv.run(control)
    return vars(drv.stats)


def _run(map_path: Path, traj: Path, stats: Path, rate: int, period: float, view: str = "off") -> dict:
    """One `skinsafe run`; `view`: "page" with `--view` (the stream and its page process), "browser" also with a
    headless Chromium (nice 19) showing the page while the robot moves."""
    cmd = [sys.executable, "-m", "skinsafe.core.app.cli", "run", str(map_path), "--robot", "sim", "--boards", "emulate",
           "--command", f"trajectory:{traj}", "--contact", CONTACT, "--seconds", str(SECONDS), "--rate", str(rate),
           "--period", str(period), "--stats", str(stats)]
    if view != "off":
        cmd += ["--view", "--view-port", str(VIEW_PORT), "--view-stream", "127.0.0.1:0"]
    if view == "browser":
        p = _with_browser(cmd)
    else:
        p = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    if not stats.exists():
        raise RuntimeError(f"bench runtime: `skinsafe run` exited {p.returncode} without figures: {p.stderr[-800:]}")
    return json.loads(stats.read_text())


def _with_browser(cmd: list[str]) -> subprocess.CompletedProcess:
    """`cmd` (a `run --view`) with a headless Chromium (Debian's, nice 19) on its page from before the robot moves."""
    from playwright.sync_api import Error as PlaywrightError
    from playwright.sync_api import sync_playwright

    from skinsafe.core.bench.browser import CHROMIUM_ARGS, chromium, niced

    exe = chromium()
    if exe is None:
        raise RuntimeError("bench runtime --view browser: no chromium (`apt-get install -y chromium`)")
    with tempfile.TemporaryDirectory() as tmp, sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=niced(tmp, exe), args=CHROMIUM_ARGS)
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        err = []
        for line in proc.stderr:
            err.append(line)
            if "the view page at" in line:
                try:
                    browser.new_page().goto(line.rsplit(" at ", 1)[1].strip())
                except PlaywrightError:  # the run already stopped (a false staleness stop) and its page with it
                    pass
                break
        out, rest = proc.communicate(timeout=600)
        browser.close()
    return subprocess.CompletedProcess(cmd, proc.returncode, out, "".join(err) + rest)


def _ms(world: dict, key: str) -> float:
    return float("nan") if world.get(key) is None or world.get("onset_t") is None else (world[key] - world["onset_t"]) * 1e3


def rows(args) -> list[dict]:
    if args.faults:
        return [fault_row(args)]
    from skinsafe.core.skin.taxel_map import save

    robot = build_ur5()
    out = []
    with tempfile.TemporaryDirectory(prefix="skinsafe-bench-runtime-") as tmp:
        tmp = Path(tmp)
        traj = write_trajectory(tmp / "pan.csv", robot)
        for n in args.taxels:
            design = sample_skin(n, args.capacity, robot)
            save(design, tmp / f"skin{n}.json")
            ref = reference(design, robot, traj, args.period)
            runs, stale = {v: [] for v in args.view}, {v: 0 for v in args.view}
            for k in range(args.repeats):  # a run a false staleness stop cut short is counted, then run again
                for v in args.view:  # alternating: the modes share the machine's load
                    for attempt in range(RETRIES):
                        r = _run(tmp / f"skin{n}.json", traj, tmp / f"stats{n}_{v}_{k}_{attempt}.json", args.rate,
                                 args.period, v)
                        stale[v] += r["watchdog"] in STALE or not r.get("ticks")  # silent before moving too
                        if r["watchdog"] not in STALE and r.get("ticks"):
                            break
                    runs[v].append(r)
            for v in args.view:
                out.append(_row(design, runs[v], stale[v], ref, args) | ({"view": v} if args.view != ["off"] else {}))
    return out


def _row(design, runs: list[dict], stale: int, ref: dict, args) -> dict:
    w = [r["world"] for r in runs]
    worst = lambda key: float(np.nanmax([r[key] for r in runs]))  # noqa: E731
    return {
        "robot": "ur5", "driver": "sim", "boards": len(design.boards), "taxels": design.n_taxels,
        "ticks": int(sum(r["ticks"] for r in runs)), "rate_hz": args.rate, "period_ms": args.period * 1e3,
        "runs": len(runs),
        "loop_hz_p50": float(np.median([r["loop_hz_p50"] for r in runs])), "period_ms_p99": worst("period_ms_p99"),
        "latency_ms_p50": float(np.nanmedian([r["latency_ms_p50"] for r in runs])),
        "latency_ms_p99": worst("latency_ms_p99"), "latency_ms_max": worst("latency_ms_max"),
        "reaction_ms": float(np.nanmax([_ms(x, "reaction_t") for x in w])),
        "peak_N": float(max(x["peak_N"] for x in w)),
        "into_contact_mm_worst": float(max(x["into_contact_m"] for x in w)) * 1e3,
        "stale_stops": stale,
        "frames_lost": int(sum(r["frames_lost"] for r in runs)),
        "peak_N_in_process": float(ref["peak_N"]), "reaction_ms_in_process": _ms(ref, "reaction_t"),
        "into_contact_mm_in_process": float(ref["into_contact_m"]) * 1e3,
        "peak_vs_in_process": float(max(x["peak_N"] for x in w) / ref["peak_N"]) if ref["peak_N"] else float("nan"),
        "work_ms_p99": worst("work_ms_p99"), "work_ms_max": worst("work_ms_max"),
        "latency_samples": int(sum(r["latency_samples"] for r in runs)),
        "stops": ";".join(sorted({r["kind"] + (":" + r["watchdog"] if r["watchdog"] else "") for r in runs})),
        "per_run_loop_hz_p50": [round(r["loop_hz_p50"], 3) for r in runs],
        "per_run_period_ms_p99": [round(r["period_ms_p99"], 4) for r in runs],
        "per_run_latency_ms_p99": [round(r["latency_ms_p99"], 4) for r in runs]}


def fault_row(args) -> dict:
    cmd = [sys.executable, "-m", "skinsafe.core.app.runtime_faults", "--runs", str(args.runs), "--seed", str(args.seed),
           "--rate", str(args.fault_rate), "--json"]
    p = subprocess.run(cmd, stdout=subprocess.PIPE, text=True, timeout=7200)
    if p.returncode:
        raise RuntimeError(f"bench runtime --faults: the fault storm exited {p.returncode}")
    runs = json.loads(p.stdout)
    stopped = [r for r in runs if r["stopped"]]
    kinds = sorted({r["fault"] for r in runs})
    return {"runs": len(runs), "faults": len(stopped),
            "stopped_within_2_periods": float(np.mean([r["stop_periods"] <= 2 for r in stopped])) if stopped else 0.0,
            "unnamed": sum(not r["named"] for r in runs), "tracebacks": sum(r["traceback"] for r in runs),
            "records_readable": float(np.mean([r["record_readable"] for r in runs])),
            "named_as_injected": float(np.mean([r["named_as_injected"] for r in runs])),
            "stop_periods_max": float(max((r["stop_periods"] for r in stopped), default=float("nan"))),
            "rate_hz": args.fault_rate, "seconds": float(sum(r["seconds"] for r in runs)),
            **{f"runs_{k.replace('-', '_')}": sum(r["fault"] == k for r in runs) for k in kinds},
            **{f"other_first_{k.replace('-', '_')}": sum(r["fault"] == k and not r["named_as_injected"] for r in runs)
               for k in kinds}}
