"""`skinsafe bench runtime [--faults]`: the safety runtime closed-loop, the real `skinsafe run` in its own process.

Rows (default): the UR5 sample skin cut to `--taxels` (4,096 and 16,384: whole 64-taxel modules on
boards of 1,024 channels), the `sim` driver at 500 Hz, emulated boards at `--rate`, the arm driven by a
trajectory (shoulder pan at 0.2 rad/s) into a sprung post 1 cm in front of the taxel the pan sweeps
into it. Per row, over `--repeats` runs (worst case where it says so):
- loop_hz_p50 (median of the runs' medians), period_ms_p99 (worst): the loop's rate and jitter;
- latency_ms_p50 / p99 (over every contact frame of every run, pooled) / max (worst): a frame holding a
  contact complete on the host -> its command leaves for the robot (per_run_latency_ms_p99: each run's own);
  split into latency_wait_ms (the frame complete -> the tick that uses it begins: the reader's decoding and
  publication, `publish_ms_p99` (worst run), then the wait for the robot's next period) and latency_tick_ms
  (that tick's work up to the command);
- reaction_ms (worst): contact onset in the sim -> the touched taxel's measured motion points out of
  the contact (MuJoCo's clock);
- peak_N, into_contact_mm_worst (worst): the first contact's largest force (from the onset until the
  post lets go: the contact `reaction_ms` is of), and how far the taxel went into the post after the
  onset; `peak_N_in_process` is the same contact with the stack fed straight from the sim's readout (no
  boards, no serial; same code, `SimDriver(realtime=False)`); `peak_N_run` (and `_in_process`): the
  largest force of the whole run, the arm's later approaches included (after each retraction the
  trajectory catches up and sweeps the arm into the post again, at a speed that depends on how the
  retraction went: these are not the same contact in the two runs);
- stale_stops: runs a staleness watchdog (silent board, robot state, command) stopped with nothing
  injected (the shared machine's stalls), or a board was silent before the robot moved; such a run is run
  again (up to RETRIES times) and the row's figures are those of the runs that went to the end;
  frames_lost: frames sent that never arrived;
- the loop's stalls beside the host's own: work_ms_max and off_cpu_ms_max / slowest_tick_off_cpu_ms (a tick's
  wall time less its thread's CPU time), host_stall_ms_max (the longest a thread at the loop's priority on the
  loop's core lost while it spun for PROBE_S just before each run, with host_switched_out, its involuntary
  switches: core/realtime.py `host_stalls`) and steal_ms_max (the time the hypervisor took from the loop's core
  during one run, /proc/stat). The `fr3` rows carry the same.
`--view off page browser browser-shared`: a row per mode (key `view`), the modes' runs alternating (each repeat
in an order turned by one) so they share the machine's load: without the live view, with `run --view` (its
stream and page process), and with a headless Chromium on the page too, off the loop's core or on any;
per_run_* list each run's loop figures (the spread); period_ms_p99_pooled and latency_ms_p99_pooled over every
tick / contact frame of the mode's runs (latency_tick_ms_p99_pooled: the frames' tick part), `*_p99_vs_off`
their change against the runs without the view, `within_5pct` (all within 5%), `not_slower_5pct` (none more
than 5% above), `*_p99_vs_off_ci95` (the change's 95% interval, the repeats resampled as pairs of runs made
next to each other) with `shown_within_5pct` / `shown_not_slower_5pct` (the whole intervals), and the noise
floor: `off_spread`, how far the runs without the view differ from themselves (even runs against odd),
`resolvable` when that is within 5%.
`--view foxglove record`: the same rows for `run --foxglove` with a Foxglove WebSocket client subscribed to every
topic (`client_messages`: what it got) and for `run --record` (the rosbag2 folder and its ROS 2 topics).
`--view alternating alternating-pinned alternating-remote` (core/bench/view_pause.py): the comparison inside each
run instead (a local Chromium on any core, off the loop's core, or the page open on another computer), the view
attached throughout and its processes paused and resumed every `--block` s: `*_p50_vs_paused`, `*_p99_vs_paused`
(and `_ci95`, the pairs of neighbouring blocks resampled), `view_cpu_per_working_s`, `shown_within_5pct`,
`shown_not_slower_5pct` (and `_p50`); with `--sweep S` (the arm into the post and back every S s) and `--block S`,
each block holds one whole sweep: the same contacts.
`--tap`: the live view's cost inside the loop (core/bench/view_tap.py).
`--faults`: the fault storm (`skinsafe faults`) in its own process, one row per fault kind and
driver (`--robot`: sim, or fr3 against franky-sim): runs, detect_bound_ms (the monitor's bound for the kind that names it), onset_to_zero_ms_p50 /
_max (the injection's time -> the zero command the driver sent), over_bound (runs over the bound),
named_as_injected (fraction named by that kind), named_earlier (fraction named by the earlier cause the kind allows:
after-contact at speed by its contact's own stack-latch, core/app/runtime_faults.py EARLIER), unnamed, tracebacks, records_readable (fraction),
latched (fraction left in the monitor's protective stop); `--fault-kinds` picks kinds. One row per fault kind, driver and
speed (`--fault-speeds`: the swept joint's speed, a fraction of its velocity limit; the contact kinds swept into something): the
stop as a safety engineer states it, from the arm's measured state (core/runtime/loop.py `Runtime.stopping`):
stop_time_ms_p50 / _max (the onset -> every joint below 0.02 rad/s, on the robot's clock), stop_distance_mm_max (the
furthest any taxel travelled from where it was at the onset, up to the rest), stop_missing (runs whose arm was not at
rest by the end of the record: a dead simulation has none), stop_category (IEC 60204-1; None: the robot's own stop),
speed_at_onset_max and speed_max (the fastest joint's speed at the onset, and its top until the rest), and the printed
bounds' braking model at that top speed and the arm's pose (model_stop_ms_max, model_distance_mm_max, monitor.stopping)
with over_model (runs over it); over_bound counts a missing or negative onset -> zero time as a failed run. The `teleop-intruder` row's
onset is the intruder's first datagram and each run's bound adds the time the intruder took to send the 3 that
stop (about 20 ms at its 100 Hz; detect_bound_ms: the longest); followed_intruder (runs whose leader became the intruder), intruder_named (fraction of runs whose tally
names it), intruder_refused_min, leader_accepted_min.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import os
import subprocess
import sys
import tempfile
import threading
from pathlib import Path

import numpy as np

from skinsafe.core.design.sample import make_sample_design
from skinsafe.core.realtime import host_stalls, loop_cores, steal_s
from skinsafe.core.robot.models import build_ur5
from skinsafe.core.runtime.monitor import Kind
from skinsafe.core.skin.boards import assign_boards, number_channels
from skinsafe.core.skin.model import Module, SkinDesign
from skinsafe.core.system import SKINSAFE
from skinsafe.core.timing import pct, pooled_change_ci95

PITCHES = (0.01, 0.0072, 0.005, 0.0036, 0.0025)  # the sample skin gets denser until it holds enough taxels
PAN_SPEED = 0.2  # rad/s of the shoulder pan in the trajectory
CONTACT = "post:joint=0,gap=0.01"
SECONDS = 3.0
# the staleness stops a loaded host makes with nothing injected (monitor kinds; a run they cut short is run again)
STALE = tuple(k.value for k in (Kind.BOARD_SILENT, Kind.BOARD_LATE, Kind.ROBOT_FROZEN, Kind.COMMAND_STALE))
RETRIES = 5
FR3_SECONDS = 60.0
PROBE_S = 2.0  # s of the host's own stalls measured before each run (core/realtime.py `host_stalls`)
VIEW_PORT = 8480
LOCAL_BROWSER = {"browser", "browser-shared", "alternating", "alternating-pinned"}  # --view modes with a Chromium here


def add_arguments(p) -> None:
    p.add_argument("--taxels", type=int, nargs="+", default=[4096, 16384])
    p.add_argument("--capacity", type=int, default=1024, help="channels per board")
    p.add_argument("--rate", type=int, default=100, help="board frames per second")
    p.add_argument("--repeats", type=int, default=2, help="runs per row")
    p.add_argument("--period", type=float, default=0.001, help="the sim's control period, s (default 0.001: a frame "
                   "waits at most 1 ms for the tick that uses it)")
    p.add_argument("--robot", choices=("sim", "fr3"), default="sim", help="sim (default): the UR5 sample skin on the "
                   "sim driver; fr3: franky-sim's FR3 over libfranka, a hand reaching into the arm (`make franky-sim`; "
                   "give --maps)")
    p.add_argument("--maps", nargs="+", metavar="MAP", help="--robot fr3: taxel maps designed on franky-sim's FR3 "
                   "(README, 'The FR3 case'); one row each")
    p.add_argument("--seconds", type=float, help=f"robot time per run (default {SECONDS:g} s; fr3 {FR3_SECONDS:g} s)")
    p.add_argument("--link-latency", type=float, default=0.0, metavar="S",
                   help="`skinsafe run --link-latency`: how late the host's serial input may be before a board counts "
                        "as silent, on top of 2 frame periods (default 0)")
    p.add_argument("--realtime", action=argparse.BooleanOptionalAction, default=True,
                   help="--robot fr3: franky-sim's world at real-time priority where allowed (default)")
    p.add_argument("--faults", action="store_true", help="the fault storm instead (one row)")
    p.add_argument("--links", action="store_true", help="instead: how late the host's serial input arrives through "
                   "pseudo-terminals and pipes, waiting with poll and epoll (core/bench/links.py; --seconds each, "
                   "default 30)")
    p.add_argument("--tap", action="store_true", help="instead: the live view's cost inside the loop per shared tick, "
                   "the tick's arrays copied against the stream message encoded (core/bench/view_tap.py; --seconds "
                   "each, default 2)")
    p.add_argument("--runs", type=int, default=204, help="--faults: runs (one fault each)")
    p.add_argument("--fault-kinds", nargs="+", metavar="FAULT", help="--faults: only these kinds (`skinsafe faults "
                   "--kinds`), e.g. teleop-intruder")
    p.add_argument("--fault-speeds", type=float, nargs="+", metavar="FRACTION", help="--faults: the swept joint's "
                   "speeds, fractions of its velocity limit (`skinsafe faults --speeds`; default 0.25 0.5 1)")
    p.add_argument("--fault-rate", type=int, default=50, help="--faults: board frames per second (a board is silent "
                   "after 2 frame periods: 40 ms, so a 50 ms delay trips it and the machine's stalls mostly do not)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--view", nargs="+", default=["off"],
                   choices=("off", "page", "browser", "browser-shared", "alternating", "alternating-pinned",
                            "alternating-remote", "foxglove", "record"),
                   help="rows without the live view (off), with `run --view` (page: the stream and its page process), "
                   "and also with a headless Chromium showing the page, kept off the loop's core (browser) or free to "
                   "use it (browser-shared); the runs alternate between them. alternating (-pinned): browser-shared "
                   "(browser) with the view's processes paused and resumed every --block s, the ticks compared inside "
                   "each run (core/bench/view_pause.py); alternating-remote: so, the page open on another computer "
                   "(core/bench/remote_viewer.py) instead of a local browser; foxglove: `run --foxglove` with a Foxglove "
                   "WebSocket client subscribed to every topic (core/bench/foxglove_client.py); record: `run --record` "
                   "(the rosbag2 folder with its ROS 2 topics, written by the run's writer thread)")
    p.add_argument("--sweep", type=float, metavar="S", help="the arm into the post and back every S seconds (contacts "
                   "all run long) instead of the pan on into it")
    p.add_argument("--block", type=float, default=0.5, help="--view alternating: seconds the view works, then is paused")


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


def write_trajectory(path: Path, robot, seconds: float = SECONDS, sweep: float | None = None) -> Path:
    """The shoulder pan turning positive at PAN_SPEED from home (into the post), the other joints still; with
    `sweep` (s), into the post and back every `sweep` seconds instead (a cosine, PAN_SPEED at its fastest)."""
    names = [robot.model.joint(j).name for j in range(robot.model.nv)]
    t = np.linspace(0.0, seconds, int(seconds * (100 if sweep else 10)) + 1)
    q = np.repeat(robot.home[None], len(t), 0)
    q[:, 0] += PAN_SPEED * t if sweep is None else PAN_SPEED * sweep / np.pi * (1 - np.cos(2 * np.pi * t / sweep)) / 2
    return write_waypoints(path, names, t, q)


def _contact():
    from skinsafe.core.sim.robot_driver import Contact

    return Contact("post", joint=0, gap=0.01)


def reference(design, robot, traj: Path, period: float = 0.002, seconds: float = SECONDS) -> dict:
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
        if s.t >= seconds:
            return None
        return stack.tick(s.t, s.q, {"force": drv.forces}, src(s.t, s.q), period, qdot=s.qd)
    drv.run(control)
    return vars(drv.stats)


def _run(args, map_path: Path, command: str, stats: Path, seconds: float, *extra: str, view: str = "off") -> dict:
    """One `skinsafe run` in its own process: its figures. `view`: "page" with `--view` (the stream and its page
    process), "browser" also with a headless Chromium (nice 19) showing the page while the robot moves, off the
    loop's core ("browser-shared": on any core); "alternating" ("-pinned"): as "browser-shared" ("browser"), the
    view's processes paused and resumed every `args.block` s; "alternating-remote": so, with the page open on
    another computer instead of a browser here."""
    cmd = [SKINSAFE, "run", str(map_path), "--boards", "emulate", "--command", command,
           "--seconds", str(seconds), "--rate", str(args.rate), "--link-latency", str(args.link_latency), "--allow-link-latency",
           "--after-contact", "always-resume",  # the rows measure every contact of a sweep, flagged or not
           "--stats", str(stats), *extra]
    if view == "foxglove":
        cmd += ["--foxglove", "0"]
    elif view == "record":
        cmd += ["--record", str(stats.with_suffix(".record"))]
    elif view != "off":
        cmd += ["--view", "--view-port", str(VIEW_PORT), "--view-stream", "127.0.0.1:0"]
    stats.unlink(missing_ok=True)
    pause = {}
    if view == "foxglove":
        p = _with_foxglove(cmd, pause)
    elif view not in ("off", "page", "record"):
        alternating = view.startswith("alternating")
        p = _with_browser(cmd, shared=view in ("browser-shared", "alternating"), block=args.block if alternating else None,
                          pause=pause, remote=view == "alternating-remote")
    else:
        host = host_stalls(PROBE_S)  # the host's own stalls of a thread at the loop's priority, just before
        core = min(loop_cores(os.sched_getaffinity(0))[0])
        steal = steal_s(core)
        p = subprocess.run(cmd, capture_output=True, text=True, timeout=600 + 20 * seconds)
        after = steal_s(core)
        pause = {"host_stall_ms_max": host["stall_ms_max"], "host_switched_out": host["switched_out"],
                 "steal_ms": (after - steal) * 1e3 if steal is not None and after is not None else None}
    if not stats.exists():
        raise RuntimeError(f"bench runtime: `skinsafe run` exited {p.returncode} without figures: {p.stderr[-800:]}")
    return json.loads(stats.read_text()) | pause


def _cut_short(r: dict) -> bool:
    """A staleness stop with nothing injected (the machine's stalls), or a board silent before the robot moved."""
    return r["watchdog"] in STALE or not r.get("ticks")


def _retried(run) -> tuple[dict, int]:
    """`run()` again while a false staleness stop cuts it short (RETRIES in all): the last run, and how many were cut."""
    for attempt in range(RETRIES):
        r = run()
        if not _cut_short(r):
            return r, attempt
    return r, RETRIES


def _with_browser(cmd: list[str], shared: bool = False, block: float | None = None,
                  pause: dict | None = None, remote: bool = False) -> subprocess.CompletedProcess:
    """`cmd` (a `run --view`) with a headless Chromium (Debian's, nice 19) on its page from before the robot moves;
    on the cores `run` leaves to what it starts (all but the first, its loop's: as an operator keeps a browser
    off a robot PC's control core, README 'The loop with the view attached'), or with `shared` on any; `remote`:
    the page open on another computer instead (core/bench/remote_viewer.py, nice 19, off the loop's core). `block`:
    the view's processes paused and resumed every `block` s once the page is open, its `switches` and the view's
    `view_cpu_s` put in `pause` (core/bench/view_pause.py)."""
    from playwright.sync_api import Error as PlaywrightError
    from playwright.sync_api import sync_playwright

    from skinsafe.core.bench.browser import CHROMIUM_ARGS, niced, require_chromium
    from skinsafe.core.bench.view_pause import REMOTE_VIEWER, Pauser
    from skinsafe.core.realtime import loop_cores

    exe = None if remote else require_chromium("bench runtime --view")
    cpus = os.sched_getaffinity(0)
    others = None if shared or len(cpus) < 2 else loop_cores(cpus)[1]
    with tempfile.TemporaryDirectory() as tmp, contextlib.ExitStack() as stack:
        if remote:
            def open_page(url):
                viewer = subprocess.Popen(["taskset", "-c", ",".join(map(str, sorted(others or cpus))), "nice", "-n",
                                           "19", sys.executable, "-m", REMOTE_VIEWER, url], stderr=subprocess.DEVNULL)
                stack.callback(viewer.wait)  # after the SIGTERM below (an exit stack runs last-in first)
                stack.callback(viewer.terminate)
        else:
            browser = stack.enter_context(sync_playwright()).chromium.launch(
                executable_path=niced(tmp, exe, cpus=others), args=CHROMIUM_ARGS)
            stack.callback(browser.close)

            def open_page(url):
                try:
                    browser.new_page().goto(url)
                except PlaywrightError:  # the run already stopped (a false staleness stop) and its page with it
                    pass
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        err, pauser = [], None
        for line in proc.stderr:
            err.append(line)
            if "the view page at" in line:
                open_page(line.rsplit(" at ", 1)[1].strip())
                if block:
                    pauser = Pauser(os.getpid(), exe, block)
                    pauser.start()
                break
        out, rest = proc.communicate(timeout=600)
        if pauser is not None:
            pauser.stop()
            pause |= {"switches": pauser.switches, "view_cpu_s": pauser.cpu_s}
    return subprocess.CompletedProcess(cmd, proc.returncode, out, "".join(err) + rest)


def _with_foxglove(cmd: list[str], got: dict) -> subprocess.CompletedProcess:
    """`cmd` (a `run --foxglove 0`) with a Foxglove client subscribed to every topic from before the robot moves to
    the run's end, as the Foxglove app would be (a thread of this process); the messages it got in `got`."""
    from skinsafe.core.bench.foxglove_client import watch

    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    err, live, client = [], {}, None
    for line in proc.stderr:
        err.append(line)
        if "Foxglove at ws://" in line:
            url = line.split(" at ")[1].split()[0]
            client = threading.Thread(target=lambda: live.update(watch(url, None, seconds=600)), daemon=True)
            client.start()
            break
    out, rest = proc.communicate(timeout=600)
    if client is not None:
        client.join(30)
    got["client_messages"] = sum(len(m) for m in live.get("messages", {}).values())
    return subprocess.CompletedProcess(cmd, proc.returncode, out, "".join(err) + rest)


def _ms(world: dict, key: str) -> float:
    return float("nan") if world.get(key) is None or world.get("onset_t") is None else (world[key] - world["onset_t"]) * 1e3


def rows(args) -> list[dict]:
    if args.faults:
        return fault_rows(args)
    if args.links:
        from skinsafe.core.bench.links import rows as link_rows

        return link_rows(args.seconds or 30.0)
    if args.tap:
        from skinsafe.core.bench.view_tap import rows as tap_rows

        return tap_rows(args.taxels, args.seconds or 2.0)
    if args.robot == "fr3":
        return fr3_rows(args)
    if set(args.view) & LOCAL_BROWSER:  # before any run: a missing browser ends the bench, not its third run
        from skinsafe.core.bench.browser import require_chromium

        require_chromium(f"bench runtime --view {' '.join(sorted(set(args.view) & LOCAL_BROWSER))}")
    from tqdm import tqdm

    from skinsafe.core.skin.taxel_map import save

    seconds = args.seconds or SECONDS
    robot = build_ur5()
    out = []
    bar = tqdm(total=len(args.taxels) * args.repeats * len(args.view), desc="bench runtime", unit="run", file=sys.stderr)
    with bar, tempfile.TemporaryDirectory(prefix="skinsafe-bench-runtime-") as tmp:
        tmp = Path(tmp)
        traj = write_trajectory(tmp / "pan.csv", robot, seconds, args.sweep)
        for n in args.taxels:
            design = sample_skin(n, args.capacity, robot)
            save(design, tmp / f"skin{n}.json")
            ref = reference(design, robot, traj, args.period, seconds)
            runs, stale = {v: [] for v in args.view}, {v: 0 for v in args.view}
            for k in range(args.repeats):  # a run a false staleness stop cut short is counted, then run again
                m = k % len(args.view)  # alternating, each repeat starting one mode later: the modes share the
                for v in args.view[m:] + args.view[:m]:  # machine's load, and none always follows another
                    r, cut = _retried(lambda: _run(args, tmp / f"skin{n}.json", f"trajectory:{traj}",
                                                   tmp / f"stats{n}_{v}_{k}.json", seconds, "--robot", "sim", "--contact",
                                                   CONTACT, "--period", str(args.period), view=v))
                    runs[v].append(r)
                    stale[v] += cut
                    bar.set_postfix_str(f"{design.n_taxels:,} taxels, view {v}")
                    bar.update()
            rows_n = {v: _row(design, runs[v], stale[v], ref, args) for v in args.view}
            for v in args.view:
                out.append(rows_n[v] | (_vs_off(runs, v) if args.view != ["off"] else {}) |
                           (_vs_paused(runs[v], args.block) if v.startswith("alternating") else {}))
    return out


def _row(design, runs: list[dict], stale: int, ref: dict, args) -> dict:
    w = [r["world"] for r in runs]
    worst = lambda key: float(np.nanmax([r[key] for r in runs]))  # noqa: E731
    return {
        "robot": "ur5", "driver": "sim", "boards": len(design.boards), "taxels": design.n_taxels,
        "ticks": int(sum(r["ticks"] for r in runs)), "rate_hz": args.rate, "period_ms": args.period * 1e3,
        "link_latency_ms": args.link_latency * 1e3, "runs": len(runs),
        "loop_hz_p50": float(np.median([r["loop_hz_p50"] for r in runs])), "period_ms_p99": worst("period_ms_p99"),
        "latency_ms_p50": _pooled(runs, "latency", 50), "latency_ms_p99": _pooled(runs, "latency"),
        "latency_ms_max": worst("latency_ms_max"),
        "reaction_ms": float(np.nanmax([_ms(x, "reaction_t") for x in w])),
        "peak_N": float(max(x["first_peak_N"] for x in w)),
        "into_contact_mm_worst": float(max(x["into_contact_m"] for x in w)) * 1e3,
        "stale_stops": stale,
        "frames_lost": int(sum(r["frames_lost"] for r in runs)),
        "peak_N_in_process": float(ref["first_peak_N"]), "reaction_ms_in_process": _ms(ref, "reaction_t"),
        "into_contact_mm_in_process": float(ref["into_contact_m"]) * 1e3,
        "peak_vs_in_process": float(max(x["first_peak_N"] for x in w) / ref["first_peak_N"]) if ref["first_peak_N"] else
        float("nan"),
        "peak_N_run": float(max(x["peak_N"] for x in w)), "peak_N_run_in_process": float(ref["peak_N"]),
        "work_ms_p99": worst("work_ms_p99"), "work_ms_max": worst("work_ms_max"),
        "off_cpu_ms_max": worst("off_cpu_ms_max"), "slowest_tick_off_cpu_ms": worst("slowest_tick_off_cpu_ms"),
        **_host(runs),
        "latency_wait_ms_p50": _pooled(runs, "latency_wait", 50), "latency_wait_ms_p99": _pooled(runs, "latency_wait"),
        "latency_tick_ms_p50": _pooled(runs, "latency_tick", 50), "latency_tick_ms_p99": _pooled(runs, "latency_tick"),
        "publish_ms_p99": float(max(r["skin"].get("publish_ms_p99") or 0.0 for r in runs)),
        "latency_samples": int(sum(r["latency_samples"] for r in runs)),
        "frame_delay_ms_max": float(max(r["skin"].get("frame_delay_ms_max") or 0.0 for r in runs)),
        "stops": ";".join(sorted({r["kind"] + (":" + r["watchdog"] if r["watchdog"] else "") for r in runs})),
        "per_run_loop_hz_p50": [round(r["loop_hz_p50"], 3) for r in runs],
        "per_run_period_ms_p99": [round(r["period_ms_p99"], 4) for r in runs],
        "per_run_latency_ms_p99": [round(r["latency_ms_p99"], 4) for r in runs],
        "per_run_peak_N": [round(x["first_peak_N"], 2) for x in w]}


def _host(runs: list[dict]) -> dict:
    """The host beside the loop's figures: the longest its own stall of a thread at the loop's priority just before a
    run (`host_stall_ms_max`, with `host_switched_out`: that thread's involuntary switches, all runs), and the time
    the hypervisor stole from the loop's core during the runs (`steal_ms_max`, the most in one run)."""
    steal = [r["steal_ms"] for r in runs if r.get("steal_ms") is not None]
    return {"host_stall_ms_max": max((r.get("host_stall_ms_max", np.nan) for r in runs), default=np.nan),
            "host_switched_out": int(sum(r.get("host_switched_out", 0) for r in runs)),
            "steal_ms_max": max(steal) if steal else None}


SAMPLES = {  # a run's samples of each pooled figure (ms): every tick's period, every contact frame's latency
    "period": lambda r: np.asarray(r["period_ms_all"], float),
    "latency": lambda r: np.asarray(r["latency_ms_all"], float),
    "latency_wait": lambda r: np.asarray(r["latency_wait_ms_all"], float),
    # the latency less its wait for the tick: the part the phase of the boards' frames to the ticks does not set
    "latency_tick": lambda r: SAMPLES["latency"](r) - SAMPLES["latency_wait"](r),
}


def _pooled(runs: list[dict], name: str, p: float = 99) -> float:
    """Percentile `p` of the runs' samples of `name` (SAMPLES) together."""
    return pct(np.concatenate([SAMPLES[name](r) for r in runs]) if runs else np.zeros(0), p)


VIEW_KEYS = ("period", "latency", "latency_tick")
VIEW_TOLERANCE = 0.05
BOOTSTRAP = 2000  # resamples of the repeats for the confidence interval of each view-vs-off change


def _vs_off(runs: dict[str, list[dict]], view: str, seed: int = 0) -> dict:
    """A view mode's loop tails against the runs without the view: each pooled over every tick (period) and every
    contact frame (latency, and its tick's part) of the mode's runs, as a ratio to off's; and the same ratio between
    off's own two halves (its even and odd runs: the same code, so what the machine alone makes of it).
    `*_p99_vs_off_ci95`: the change's 95% interval over the repeats resampled as pairs (repeat k's run of the mode
    with repeat k's run without the view, run next to it: a pair shares the machine's load of its minute).
    `within_5pct`: every change within 5%; `not_slower_5pct`: none more than 5% above off's; `shown_within_5pct` /
    `shown_not_slower_5pct`: the same of the whole intervals; `resolvable`: off's halves within 5% of each other."""
    out = {"view": view}
    if view == "foxglove":
        out["client_messages"] = int(sum(r["client_messages"] for r in runs[view]))
    if "off" not in runs:
        return out
    off = runs["off"]
    halves = (off[0::2], off[1::2])
    spread = []
    pairs = min(len(off), len(runs[view]))
    draws = np.random.default_rng(seed).integers(0, pairs, (BOOTSTRAP, pairs)) if pairs >= 2 else None
    for name in VIEW_KEYS:
        out[f"{name}_ms_p99_pooled"] = _pooled(runs[view], name)
        if len(off) >= 2:
            a, b = (_pooled(h, name) for h in halves)
            spread.append(abs(a / b - 1))
            out[f"off_halves_{name}_p99"] = [round(a, 4), round(b, 4)]
        if view != "off":
            out[f"{name}_p99_vs_off"] = out[f"{name}_ms_p99_pooled"] / _pooled(off, name) - 1
            if draws is not None:
                out[f"{name}_p99_vs_off_ci95"] = pooled_change_ci95(
                    [SAMPLES[name](r) for r in runs[view][:pairs]], [SAMPLES[name](r) for r in off[:pairs]], draws)
    if view != "off":
        change = [out[f"{name}_p99_vs_off"] for name in VIEW_KEYS]
        out["within_5pct"] = all(abs(c) <= VIEW_TOLERANCE for c in change)
        out["not_slower_5pct"] = all(c <= VIEW_TOLERANCE for c in change)
        if draws is not None:
            out |= _shown([out[f"{name}_p99_vs_off_ci95"] for name in VIEW_KEYS])
    if spread:
        out["off_spread"] = max(spread)
        out["resolvable"] = max(spread) <= VIEW_TOLERANCE
    return out


def _vs_paused(runs: list[dict], block: float) -> dict:
    """--view alternating: the ticks while the view worked against those of the same runs while it was paused
    (core/bench/view_pause.py), with `shown_within_5pct` / `shown_not_slower_5pct` of the whole intervals."""
    from skinsafe.core.bench.view_pause import compare, pair_blocks

    pairs = pair_blocks([(r, r["switches"]) for r in runs if r.get("switches")])
    if len(pairs) < 2:
        return {"blocks": 2 * len(pairs)}
    working = sum((b - a) for r in runs for (a, p), (b, _) in zip(r["switches"], r["switches"][1:]) if not p)
    out = compare(pairs, VIEW_KEYS) | {"block_s": block,
                                       "view_cpu_per_working_s": sum(r["view_cpu_s"] for r in runs) / working}
    return out | _shown([out[f"{name}_p99_vs_paused_ci95"] for name in VIEW_KEYS]) | \
        _shown([out[f"{name}_p50_vs_paused_ci95"] for name in VIEW_KEYS], "_p50")


def _shown(ci: list[list[float]], suffix: str = "") -> dict:
    """What the whole 95% intervals of the view's changes show: all within 5%, none more than 5% slower."""
    return {f"shown_within_5pct{suffix}": all(-VIEW_TOLERANCE <= lo and hi <= VIEW_TOLERANCE for lo, hi in ci),
            f"shown_not_slower_5pct{suffix}": all(hi <= VIEW_TOLERANCE for _, hi in ci)}


def write_waypoints(path: Path, joints: list[str], t, q) -> Path:
    """A `--command trajectory:` CSV: joint positions q (one row per time in t, s) of `joints`."""
    path.write_text("t," + ",".join(joints) + "\n" + "\n".join(",".join(f"{x:.9g}" for x in (a, *b)) for a, b in zip(t, q)))
    return path


def write_still(path: Path, joints: list[str], q) -> Path:
    """A trajectory that holds pose q: the arm goes back to it after every retraction."""
    return write_waypoints(path, joints, (0.0, 1.0), (q, q))


def fr3_rows(args) -> list[dict]:
    """One row per map: `skinsafe run --robot fr3` against franky-sim's FR3 (its own process, at real-time priority
    where allowed, as the robot's controller is) with a hand reaching into the arm every `Hand.period` s; the
    command holds franky-sim's start pose (the arm goes back after each retraction), for `--seconds` of robot
    time. The robot's clock is libfranka's (franky-sim's 1 ms steps)."""
    from skinsafe.core.robot.models import load_robot
    from skinsafe.core.sim.franky_world import INITIAL_Q, WorldProcess, hand_in_reach, require_franky_python
    from skinsafe.core.skin.taxel_map import load

    if not args.maps:
        raise ValueError("bench runtime --robot fr3: give --maps (taxel maps designed on franky-sim's FR3; README, "
                         "'The FR3 case')")
    require_franky_python()  # before the maps load
    seconds = args.seconds or FR3_SECONDS
    out = []
    with tempfile.TemporaryDirectory(prefix="skinsafe-bench-fr3-") as tmp:
        tmp = Path(tmp)
        for path in map(Path, args.maps):
            design = load(path)
            robot = load_robot(design.robot, base_dir=path.parent)
            still = write_still(tmp / "still.csv", [robot.model.joint(j).name for j in range(7)], INITIAL_Q)
            hand = hand_in_reach(str(path), INITIAL_Q)
            with WorldProcess(path, tmp / "world.json", hand=hand, realtime=args.realtime) as world:
                r, stale = _retried(lambda: _run(args, path, f"trajectory:{still}", tmp / "stats.json", seconds,
                                                 "--robot", "fr3", "--host", world.host, "--feed", world.feed,
                                                 "--allow-non-realtime"))
                w = world.stop()
            out.append(fr3_row(r, w, stale, args))
    return out


def fr3_row(r: dict, w: dict, stale: int, args) -> dict:
    """A row of the sim rows' keys on the robot's clock, plus the robot's own counters."""
    react = np.array([(b - a) * 1e3 for a, b in zip(w["onsets"], w["reactions"]) if b is not None])
    d = r["world"]  # the driver's counters

    def rnd(x, n=3):
        return None if x is None or not np.isfinite(x) else round(float(x), n)
    return {"robot": "fr3", "driver": "fr3", "boards": r["boards"], "taxels": r["taxels"], "ticks": r["ticks"],
            "rate_hz": args.rate, "link_latency_ms": args.link_latency * 1e3,
            "loop_hz_p50": rnd(r["loop_hz_robot_p50"], 1), "period_ms_p99": rnd(r["period_ms_robot_p99"]),
            "latency_ms_p50": rnd(r["latency_ms_p50"]), "latency_ms_p99": rnd(r["latency_ms_p99"]),
            "latency_ms_max": rnd(r["latency_ms_max"]),
            "reaction_ms": rnd(np.median(react), 1) if len(react) else None,
            "reaction_ms_worst": rnd(react.max(), 1) if len(react) else None,
            "contacts": len(w["onsets"]), "contacts_reacted": len(react), "peak_N": w["peak_N"],
            "into_contact_mm_worst": w["into_contact_mm_worst"], "stale_stops": stale, "frames_lost": r["frames_lost"],
            "communication_stops": w["communication_stops"], "longest_missed_run": w["longest_missed_run"],
            "states_skipped": d.get("states_skipped"), "success_rate_min": rnd(d.get("success_rate_min")),
            "robot_s": rnd(r["robot_s"], 1), "realtime_factor": w["realtime_factor"],
            "loop_hz_wall_p50": rnd(r["loop_hz_p50"], 1), "period_ms_wall_p99": rnd(r["period_ms_p99"]),
            "frame_delay_ms_p99": r["skin"].get("frame_delay_ms_p99"), "frame_delay_ms_max": r["skin"].get("frame_delay_ms_max"),
            "work_ms_p99": rnd(r["work_ms_p99"]), "work_ms_max": rnd(r["work_ms_max"]),
            "off_cpu_ms_max": rnd(r["off_cpu_ms_max"]), "slowest_tick_off_cpu_ms": rnd(r["slowest_tick_off_cpu_ms"]),
            **_host([r]), "stop": r["reason"]}


def fault_rows(args) -> list[dict]:
    from skinsafe.core.runtime.monitor import Timing, bounds

    cmd = [SKINSAFE, "faults", "--runs", str(args.runs), "--seed", str(args.seed),
           "--rate", str(args.fault_rate), "--link-latency", str(args.link_latency), "--driver", args.robot, "--json",
           *(["--kinds", *args.fault_kinds] if args.fault_kinds else []),
           *(["--speeds", *map(str, args.fault_speeds)] if args.fault_speeds else [])]
    p = subprocess.run(cmd, stdout=subprocess.PIPE, text=True, timeout=7200)
    if p.returncode:
        raise RuntimeError(f"bench runtime --faults: the fault storm exited {p.returncode}")
    runs = json.loads(p.stdout)
    frame = 1.0 / args.fault_rate
    period = next(r["period_s"] for r in runs if r["period_s"])  # the driver's (sim 2 ms, fr3 1 ms)
    bound = bounds(Timing(period, frame, 2 * frame + args.link_latency, 0.1))
    rows = []
    for (fault, driver, speed) in sorted({(r["fault"], r["driver"], r.get("speed", 0.0)) for r in runs}):
        these = [r for r in runs if r["fault"] == fault and r["driver"] == driver and r.get("speed", 0.0) == speed]
        b = bound[Kind(these[0]["expected_kind"])] * 1e3
        timed = [r for r in these if r["onset_to_zero_ms"] is not None]
        z = np.array([r["onset_to_zero_ms"] for r in timed])
        each = np.array([b + r.get("bound_extra_ms", 0.0) for r in timed])  # a run's own bound
        b += max((r.get("bound_extra_ms", 0.0) for r in these), default=0.0)
        stopped = [r for r in these if r.get("stop_time_ms") is not None]
        st = np.array([r["stop_time_ms"] for r in stopped])
        dist = np.array([r["stop_distance_mm"] for r in stopped if r.get("stop_distance_mm") is not None])
        over_model = sum(r["stop_time_ms"] > r["model_stop_ms"] or (r.get("stop_distance_mm") or 0.0) >
                         r["model_distance_mm"] for r in stopped if r.get("model_stop_ms") is not None)
        rows.append({"fault": fault, "driver": driver, "speed": speed, "runs": len(these), "detect_bound_ms": round(b, 2),
                     "onset_to_zero_ms_p50": round(float(np.median(z)), 2) if len(z) else None,
                     "onset_to_zero_ms_max": round(float(z.max()), 2) if len(z) else None,
                     # a missing or negative onset -> zero time is a failed run, as one over its bound
                     "over_bound": int((z > each).sum() + (z < 0).sum()) + len(these) - len(z),
                     "speed_rad_s": these[0].get("speed_rad_s", 0.0),
                     "speed_at_onset_max": round(max((r.get("speed_at_onset") or 0.0) for r in these), 3),
                     "speed_max": round(max((r.get("speed_max") or 0.0) for r in these), 3),
                     "stop_time_ms_p50": round(float(np.median(st)), 2) if len(st) else None,
                     "stop_time_ms_max": round(float(st.max()), 2) if len(st) else None,
                     "stop_distance_mm_max": round(float(dist.max()), 2) if len(dist) else None,
                     "stop_missing": len(these) - len(stopped) + int((st < 0).sum()),
                     "stop_category": next((r["stop_category"] for r in these if r.get("stop_category") is not None),
                                           None) if fault != "sim-die" else None,
                     "model_stop_ms_max": max((r.get("model_stop_ms") or 0.0 for r in these), default=None),
                     "model_distance_mm_max": max((r.get("model_distance_mm") or 0.0 for r in these), default=None),
                     "over_model": over_model,
                     "named_as_injected": float(np.mean([r["named_as_injected"] for r in these])),
                     "named_earlier": float(np.mean([r.get("named_earlier", False) for r in these])),
                     "unnamed": sum(not r["named"] for r in these), "tracebacks": sum(r["traceback"] for r in these),
                     "records_readable": float(np.mean([r["record_readable"] for r in these])),
                     "latched": float(np.mean([r["latched"] for r in these])),
                     "rate_hz": args.fault_rate, "link_latency_ms": args.link_latency * 1e3}
                    | ({"followed_intruder": sum(r["followed_intruder"] for r in these),
                        "intruder_named": float(np.mean([r["intruder_named"] for r in these])),
                        "intruder_refused_min": min(r["intruder_refused"] for r in these),
                        "leader_accepted_min": min(r["leader_accepted"] for r in these)}
                       if "followed_intruder" in these[0] else {}))
    return rows
