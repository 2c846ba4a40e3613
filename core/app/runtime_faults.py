"""`skinsafe faults`: the fault storm behind `skinsafe bench runtime --faults`: many short `skinsafe run`s,
each with one fault.

Its own command (`skinsafe faults --runs N --json`; the bench starts it as a user would, so the bench never
imports the application): one emulator process (boards fed by the run's simulation through one shared-memory feed, the
map deployed once) serves every run; each run is the real command (`core.app.run.execute` on the RunConfig of its command line: pre-flight,
sim driver, readings source, stack, recorder, signal handling) with one fault, at a random time
0.3-0.9 s after the robot starts moving, each of `KINDS` in turn, injected at its source at a known
time.monotonic() (the onset): a board's link closed (the host's side of its pseudo-terminal), its
frames held 50 ms, ever later (frame-lag), replayed, foreign or corrupt (on the link proxy), the
simulation failed, its state frozen, its clock gone back or missing states (overruns), the boards' reader killed
(SIGKILL), a NaN reading from the readings source, the layers' command non-finite, the retraction's QP solve failed
(that run has a contact: a retraction), the teleop leader silent, a second sender beside the teleop leader (its shoulder
target +0.4 rad at 100 Hz: unsigned with stamps 2^30 us ahead, signed with another key, the leader's datagram
replayed; the onset its first datagram), SIGINT to this process (once, or twice 10 ms apart:
one stop). Per run: the fault kind the monitor named (is it the
one injected: `EXPECT`, no text matched), onset -> the time the driver sent zero velocity (not the
detection), any traceback, is the record readable (every message decodes with mcap-ros2-support and
the last one is the stop's diagnostics), was the stop latched (the monitor's protective stop)?
Every run sweeps the first joint at a speed (`--speeds`, fractions of its velocity limit; franky-sim's arm
from where the last run left it, toward the further end of its range), so the stop is measured as a safety engineer
states it: from the onset to every joint at rest (`Runtime.stopping`, on the arm's measured state), and the furthest
any taxel travelled meanwhile (`monitor.travel`), beside the printed bounds' model at the top speed measured.
The contact kinds (stack-qp-fail, after-contact under --after-contact hold) sweep it into something: the sim's arm
into a sprung post SIM_POST_GAP_M in front of the taxel the first joint sweeps fastest into (`--contact post`); the
FR3's (given on their own with `--kinds`: their world has an obstacle) into a sphere in franky-sim's world 0.4 rad
along it from the start pose (`franky_world.obstacle_in_path`: its first contact on skin), the arm first brought back
to that pose.
A frame-lag is a ramp: its onset is when the newest frame the link proxy had passed to the host became older
than the run's silence since the board sent it (hardware/link_faults.py, measured on the frames), not its
first late byte.
"""
from __future__ import annotations

import contextlib
import io
import json
import os
import signal
import socket
import sys
import tempfile
import threading
import time
import traceback
from pathlib import Path

import numpy as np
from tqdm import tqdm

from skinsafe.core.runtime.limiter import MARGIN
from skinsafe.core.runtime.monitor import STOP_CATEGORY, Kind
from skinsafe.core.runtime.teleop import INTRUDER_DATAGRAMS, NO_KEY, datagram, make_key, now_us

EXPECT = {"board-unplug": "link-lost", "frame-delay": "board-silent", "frame-lag": "board-late",
          "frame-replay": "counter-back", "foreign-uid": "foreign-uid", "crc-storm": "crc-storm",
          "crc-burst": "crc-storm", "sim-die": "driver", "sim-freeze": "robot-frozen",
          "sim-clock-back": "robot-clock-back", "sim-nan": "robot-nonfinite", "sim-overrun": "overrun",
          "reader-kill": "reader-died", "reader-stall": "reader-stalled", "command-silent": "command-stale",
          "command-nan": "command-bad", "ctrl-c": "operator", "ctrl-c-twice": "operator",
          "reading-nan": "reading-nonfinite", "stack-nan": "stack-nonfinite", "stack-qp-fail": "stack-latch",
          "after-contact": "after-contact", "teleop-intruder": "command-intruder", "robot-freeze": "robot-frozen",
          "robot-clock-back": "robot-clock-back", "robot-nan": "robot-nonfinite", "robot-overrun": "overrun",
          "robot-die": "driver"}  # injected -> the monitor's kind
# a contact at speed stops by its own retraction's latch (stack-latch: pushed further into the contact than braking
# allows, ticks flagged infeasible, or the solve failed) at or before the retraction's end, where after-contact's
# hold would latch: the earlier cause, named right; the row says so (`named_earlier`) beside named_as_injected
EARLIER = {"after-contact": "stack-latch"}
INTRUDER_HZ = 100.0  # the intruder's datagrams per second (the hijack)
CONTACT = ("stack-qp-fail", "after-contact")  # a contact (a retraction): the arm swept into a post / an obstacle
SIM_POST_GAP_M = 0.1  # the sim's post: this far in front of its taxel at home (0.16 rad of the first joint: the arm
# at speed before it, the arc still through the post)
CONTACT_LEAD_RAD = 0.4  # the FR3's obstacle: this far along its first joint from the start pose
CONTACT_SWEEP_RAD = 0.8  # the FR3's contact sweep: this far along it, through the obstacle
RETURN_S = 1.0  # s the FR3's contact run takes back to the start pose before its sweep
SPEEDS = (0.25, 0.5, 1.0)  # the swept joint's speed, a fraction of its velocity limit, for every other kind
SWEEP_S = 1.2  # s the swept joint moves at its speed from the start (then the arm holds)
# per driver: the robot's own faults as sim-* (the sim's SimFaults) or robot-* (the FR3 driver's view of franky-sim's
# states, its FaultPlan). The FR3's contact kinds come from an obstacle in franky-sim's world (`--kinds` with only
# them: the other kinds' runs have none, so nothing is retracted); the sim's from a post (`--contact`, per run)
KINDS = {"sim": tuple(k for k in EXPECT if not k.startswith("robot-")),
         "fr3": tuple(k for k in EXPECT if not k.startswith("sim-") and k not in CONTACT)}
SIGNALS = {"ctrl-c": (0.0,), "ctrl-c-twice": (0.0, 0.01)}  # SIGINTs to this process, s after the fault's time


def _readable(record: Path) -> bool:
    """Every message of the record (its rosbag2 folder's MCAP) decodes, the last the stop's diagnostics."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    from skinsafe.core.runtime.rosbag2 import record_file

    try:
        last = None
        with open(record_file(record), "rb") as f:
            for _, channel, _, msg in make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages(
                    log_time_order=False):
                last = (channel.topic, msg)
        return last is not None and last[0] == "/diagnostics" and last[1].status[0].name == "skinsafe/watchdog"
    except Exception:
        return False


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class _Intruder:
    """A second sender beside the leader: the hijack of issue 54 (module docstring), from `run()` until `stop`;
    `done["onset"]`: its first datagram's send."""

    def __init__(self, to, home, key, other_path: Path, stop: threading.Event, done: dict):
        self.to, self.stop, self.done = to, stop, done
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.name = f"127.0.0.1:{self.sock.getsockname()[1]}"
        self.bad = np.asarray(home, float) + np.eye(len(home))[0] * 0.4
        self.other, self.captured = make_key(other_path, force=True), datagram(home, key, now_us())
        self.sent: list[float] = []  # the first INTRUDER_DATAGRAMS sends, host time.monotonic()

    def run(self) -> None:
        k = 0
        while not self.stop.is_set():
            data = (datagram(self.bad, NO_KEY, now_us() + 2**30), datagram(self.bad, self.other, now_us()),
                    self.captured)[k % 3]
            self.done.setdefault("onset", time.monotonic())
            if len(self.sent) < INTRUDER_DATAGRAMS:
                self.sent.append(time.monotonic())
            with contextlib.suppress(OSError):
                self.sock.sendto(data, self.to)
            k += 1
            self.stop.wait(1.0 / INTRUDER_HZ)

    def row(self, teleop: dict) -> dict:
        """followed_intruder: the run took a datagram of the intruder's (it became the leader); intruder_named: the
        run's tally names it; the bound's extra: the time the intruder took to send the datagrams that stop (the
        monitor's bound runs from the last of them)."""
        named = {x["address"]: x["datagrams"] for x in teleop.get("senders", [])}
        return {"followed_intruder": int(teleop.get("leader") == self.name), "intruder": self.name,
                "intruder_named": self.name in named, "intruder_refused": named.get(self.name, 0),
                "leader_accepted": teleop.get("accepted", 0),
                "bound_extra_ms": (self.sent[-1] - self.sent[0]) * 1e3 if len(self.sent) == INTRUDER_DATAGRAMS else
                (INTRUDER_DATAGRAMS - 1) / INTRUDER_HZ * 1e3}

    def close(self) -> None:
        self.sock.close()


def _stop_boards(ports: dict[int, str]) -> None:
    """Leave every board idle for the next run (a run whose link was cut could not stop its board)."""
    from skinsafe.hardware.client import BoardClient, BoardError

    for port in ports.values():
        try:
            with BoardClient(port, timeout=1.0, retries=4) as c:  # behind a backlog of frames a loaded host passes slowly
                c.identify()  # the frame size first: a streaming board's frames are longer than a short answer
                c.stop_stream()
        except BoardError:
            pass


class _Stopping:
    """The arm of a storm's world (its joints, limits and taxels' Jacobians at home) and the printed bounds' model
    (core/runtime/monitor.py `stopping`) for the swept joint at a measured speed."""

    def __init__(self, joints, limits: dict, J: np.ndarray, timing):
        self.joints, self.J, self.timing = list(joints), J, timing
        self.qd_max, self.qdd_max, self.qddd_max = limits["qd_max"], limits["qdd_max"], limits.get("qddd_max")
        self.q_min, self.q_max = limits["q_min"], limits["q_max"]
        self.kin = None

    def travel(self, q_path) -> np.ndarray:
        """Each taxel's stopping distance along the measured path (m; `monitor.travel`)."""
        from skinsafe.core.runtime.monitor import travel

        return travel(self.kin, q_path)

    def model(self, kind: str, qd, extra_s: float = 0.0, q=None) -> tuple[float, float]:
        """(stop time ms, distance mm): the kind's detection bound (+ `extra_s`, the time the fault takes to become
        the kind: a CRC burst's 5 frames, an intruder's 3 datagrams), then braking from the joints' speeds `qd` (each
        joint's top speed measured from the onset to the rest), the taxels' Jacobians at the arm's pose `q` (default
        home)."""
        from skinsafe.core.runtime.monitor import Kind, fastest_taxel_speed, stopping

        J = self.J if q is None or not np.isfinite(q).all() else self.kin.jacobians_of(np.arange(self.kin.n), q)[0]
        qd = np.nan_to_num(np.asarray(qd, float))
        t, d = stopping(self.timing, J, qd, self.qdd_max, self.qddd_max)[Kind(kind)]
        d += fastest_taxel_speed(J, qd) * extra_s
        return round((t + extra_s) * 1e3, 2), round(d * 1e3, 2)


def one_run(k: int, kind: str, at: float, map_path: Path, feed, ports, home, out: Path, rate: int,
            link_latency: float = 0.0, robot: tuple = ("--robot", "sim"), speed: float = 0.0,
            the: _Stopping | None = None) -> dict:
    """One `skinsafe run` (`robot`: its --robot and the driver's options) with the fault `kind` at `at` s after the
    robot starts moving, the first joint swept at `speed` x its velocity limit for SWEEP_S s from the start (0: the
    arm holds); `the`: the arm's joints, limits and the model of the printed stopping bounds."""
    from skinsafe.core.app import run as run_cmd
    from skinsafe.core.app.cli import module_args
    from skinsafe.core.bench.runtime import write_waypoints
    from skinsafe.core.runtime.leader import stream

    record, stats = out / f"run{k}.mcap", out / f"run{k}.json"
    extra, stop = [], threading.Event()
    timers, done, intruder = [], {}, None
    # the fastest the limiter allows at speed 1 (its margin inside the limit); from the arm's pose (`home`: where the
    # last run left franky-sim's arm), toward the further end of the joint's range, within it
    v = speed * the.qd_max[0] * (1 - MARGIN) if the is not None else 0.0
    if v:
        up, down = the.q_max[0] - home[0], home[0] - the.q_min[0]
        v = v if up >= down else -v
        sweep = min(SWEEP_S, 0.8 * max(up, down) / abs(v))
    else:
        sweep = SWEEP_S
    end = home + np.eye(len(home))[0] * v * sweep
    times, targets = np.array([0.0, sweep, sweep + 1.0]), np.stack([home, end, end])
    command = f"trajectory:{write_waypoints(out / 'sweep.csv', the.joints, times, targets)}" if v else "hold"

    def at_once(call, *args):  # the harness's own injections: the onset is when it first acts
        done.setdefault("onset", time.monotonic())
        call(*args)
    if kind == "command-silent":
        port = _free_port()
        command = f"teleop:{port}"
        threading.Thread(target=stream, args=(("127.0.0.1", port), times, targets, stop), daemon=True).start()
    elif kind == "teleop-intruder":
        port = _free_port()
        key = make_key(out / "leader.key", force=True)
        command, extra = f"teleop:{port}", ["--teleop-key", key.path]
        intruder = _Intruder(("127.0.0.1", port), home, key, out / "other.key", stop, done)
        threading.Thread(target=stream, args=(("127.0.0.1", port), times, targets, stop, 100.0, key),
                         daemon=True).start()
    elif kind in CONTACT:  # the sim: the sweep into a post; the FR3: back to its start pose, then the sweep into the
        sim = robot[1] == "sim"  # world's obstacle (the sim's QP fails from the post's first retraction tick on)
        if not sim:
            command = f"trajectory:{_into_obstacle(out / 'contact.csv', the, home, abs(v))}"
        post = ["--contact", f"post:joint=0,gap={SIM_POST_GAP_M}"] if sim else []
        # after-contact: the retraction's end latches under --after-contact hold
        extra = ["--after-contact", "hold", *post] if kind == "after-contact" else ["--inject", f"{kind}@{0 if sim else at:.3f}", *post]
    elif kind not in SIGNALS:
        extra = ["--inject", f"{kind}@{at:.3f}"]

    def moving(runtime):
        done["runtime"] = runtime
        if kind == "command-silent":
            timers.append(threading.Timer(at, at_once, (stop.set,)))
        if intruder is not None:
            timers.append(threading.Timer(at, intruder.run))
        for later in SIGNALS.get(kind, ()):
            timers.append(threading.Timer(at + later, at_once, (os.kill, os.getpid(), signal.SIGINT)))
        for t in timers:
            t.start()

    cfg = run_cmd.config(module_args(run_cmd, "skinsafe run", "", [  # the operator's command line, as typed
        str(map_path), *robot, "--boards", "emulate", "--command", command, "--rate", str(rate), "--link-latency",
        str(link_latency), "--allow-link-latency", "--tare-frames", "10", "--seconds", "3", "--record", str(record),
        "--stats", str(stats), *extra], "run"))
    err, tb = io.StringIO(), ""
    t0 = time.monotonic()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        try:
            code = run_cmd.execute(cfg, feed=feed, ports=dict(ports), on_moving=moving)
        except BaseException:
            code, tb = None, traceback.format_exc()
    stop.set()
    for t in timers:
        t.cancel()
    if intruder is not None:
        intruder.close()
    _stop_boards(ports)
    s = json.loads(stats.read_text()) if stats.exists() else {}
    reason = s.get("reason", "")
    world = s.get("world", {})
    onset = done.get("onset") or s.get("injected", {}).get(kind) or world.get("fault_mono")
    if kind == "after-contact":  # the fault is the retraction's end: the monitor's own decision
        onset = s.get("detected_mono")
    zero = world.get("zero_mono")
    runtime = done.get("runtime")
    st = runtime.stopping(onset) if onset and runtime is not None and runtime.ticks else {}
    if the is not None and st.get("q_path"):
        far = the.travel(st["q_path"])
        st["stop_distance_mm"] = float(np.nanmax(far) * 1e3) if np.isfinite(far).any() and \
            st.get("stop_time_ms") is not None else None  # not at rest by the record's end: unknown
        done["travel"] = (far, np.asarray(st["q_path"][0], float))  # for the picture (`--picture`)
    st["stop_category"] = STOP_CATEGORY[Kind(EXPECT[kind])]
    span = s.get("injected", {}).get(f"{kind}-span")  # crc-burst: its first corrupt frame -> its 5th (the storm)
    bound_extra = {"bound_extra_ms": span * 1e3} if span is not None else {}
    if intruder is not None:
        bound_extra = {"bound_extra_ms": intruder.row(s.get("teleop") or {})["bound_extra_ms"]}
    # the printed bounds' model at each joint's top speed measured from the onset to the rest (the arm may still
    # speed up while the fault is being detected)
    model = (the.model(EXPECT[kind], st.get("qd_peak") or np.zeros(len(home)), bound_extra.get("bound_extra_ms", 0.0) / 1e3,
                       np.asarray(st["q_path"][0], float) if st.get("q_path") else None)
             if the is not None else (None, None))
    if runtime is not None and runtime.last_q is not None and np.isfinite(runtime.last_q).all():
        done["pose"] = runtime.last_q.tolist()  # where the arm was left (franky-sim's persists)
    return {"run": k, "fault": kind, "driver": robot[1], "period_s": s.get("period_s"), "at_s": round(at, 3),
            "speed": speed, "speed_rad_s": round(abs(v), 3), "speed_at_onset": st.get("speed_at_onset"),
            "speed_max": st.get("speed_max"),
            "stop_time_ms": st.get("stop_time_ms"), "stop_distance_mm": st.get("stop_distance_mm"),
            "stop_category": st.get("stop_category"), "stop_why": st.get("why", ""),
            "model_stop_ms": model[0], "model_distance_mm": model[1], **bound_extra, "pose": done.get("pose"),
            "travel": done.get("travel"),
            "exit": code, "reason": reason,
            "named_kind": s.get("watchdog", ""), "expected_kind": EXPECT[kind], "stopped": bool(s) and s.get("kind") != "end",
            "named": bool(reason) and s.get("kind") != "end", "named_as_injected": s.get("watchdog") == EXPECT[kind],
            "named_earlier": kind in EARLIER and s.get("watchdog") == EARLIER[kind],
            "onset_to_zero_ms": (zero - onset) * 1e3 if onset and zero else None,
            "latched": s.get("state") == "protective_stop",
            "traceback": bool(tb) or "Traceback" in err.getvalue(), "record_readable": _readable(record),
            "seconds": time.monotonic() - t0, "detail": tb.strip().splitlines()[-1] if tb else ""} | \
        (intruder.row(s.get("teleop") or {}) if intruder is not None else {})


def _into_obstacle(path: Path, the: _Stopping, home, v: float) -> Path:
    """The FR3's contact run as a trajectory: from `home` back to franky-sim's start pose (RETURN_S, then held 0.5 s),
    then the first joint swept at `v` rad/s CONTACT_SWEEP_RAD along it, through the world's obstacle (held at the
    start pose when `v` is 0)."""
    from skinsafe.core.bench.runtime import write_waypoints
    from skinsafe.core.sim.franky_world import INITIAL_Q

    start = np.asarray(INITIAL_Q, float)
    end = start + np.eye(len(start))[0] * (CONTACT_SWEEP_RAD if v else 0.0)
    t = [0.0, RETURN_S, RETURN_S + 0.5, RETURN_S + 0.5 + (CONTACT_SWEEP_RAD / v if v else 1.0)]
    return write_waypoints(path, the.joints, t, [np.asarray(home, float), start, start, end])


@contextlib.contextmanager
def _setup(driver: str, tmp: Path, obstacle: bool = False):
    """(map, feed, ports, home, the run's robot options) of `driver`'s world: the UR5 sample skin in the sim, or
    a skin on franky-sim's FR3 (its own process; with `obstacle`, a sphere its first joint sweeps the skin into,
    CONTACT_LEAD_RAD from the start pose: `franky_world.obstacle_in_path`); one emulator serves every run."""
    from skinsafe.core.skin.force_feed import ForceFeed
    from skinsafe.core.skin.taxel_map import load, save
    from skinsafe.hardware.deploy import deploy
    from skinsafe.hardware.emulator import EmulatorProcess

    with contextlib.ExitStack() as stack:
        if driver == "sim":
            from skinsafe.core.design.sample import make_sample_design
            from skinsafe.core.robot.models import build_ur5

            robot = build_ur5()
            save(make_sample_design("ur5", robot=robot), tmp / "skin.json")
            home, options = robot.home, ("--robot", "sim")
            feed = stack.enter_context(ForceFeed.create(None, load(tmp / "skin.json").n_taxels))
        else:
            import subprocess

            from skinsafe.core.app.cli import main as skinsafe
            from skinsafe.core.sim.franky_world import INITIAL_Q, WorldProcess, obstacle_in_path, require_franky_python

            subprocess.run([str(require_franky_python()), "-m", "skinsafe.core.sim.franky_world", "mjcf",
                            str(tmp / "fr3.xml")], check=True, capture_output=True)
            with contextlib.redirect_stdout(io.StringIO()):
                if skinsafe(["design", str(tmp / "fr3.xml"), "--bodies", "fr3_link5,fr3_link6", "--out",
                             str(tmp / "skin.json")]):
                    raise SystemExit("runtime faults: designing the FR3 skin failed")
            sphere = obstacle_in_path(str(tmp / "skin.json"), np.eye(7)[0], INITIAL_Q, CONTACT_LEAD_RAD) if obstacle else None
            world = stack.enter_context(WorldProcess(tmp / "skin.json", tmp / "world.json", obstacle=sphere,
                                                     realtime=True))
            feed = stack.enter_context(ForceFeed.attach(world.feed))
            home, options = np.array(INITIAL_Q), ("--robot", "fr3", "--host", world.host, "--feed", world.feed,
                                                   "--allow-non-realtime")
        design = load(tmp / "skin.json")
        em = stack.enter_context(EmulatorProcess([], tmp / "flash", "--map", str(tmp / "skin.json"), "--feed",
                                                 feed.name))
        ports = {b.id: em.ports[b.uid] for b in design.boards}
        if not all(r.ok for r in deploy(design, ports)):
            raise SystemExit(f"runtime faults: deploying the {driver} map to the emulated boards failed")
        yield tmp / "skin.json", feed, ports, home, options


def picture(path: Path, the: _Stopping, row: dict, far: np.ndarray, q0: np.ndarray) -> Path:
    """Each taxel's stopping distance (mm, colour) at its place on the arm when the fault began, the arm's links as
    lines between its bodies (two views)."""
    from skinsafe.core.app.report_figures import _plt, save

    plt = _plt()
    pos = the.kin.poses(q0)[0].copy()
    m, d = the.kin.model, the.kin.data
    bones = [(d.xpos[b].copy(), d.xpos[m.body_parentid[b]].copy()) for b in range(1, m.nbody)]
    mm = far * 1e3
    fig = plt.figure(figsize=(11, 5))
    top = float(np.nanmax(mm))
    for i, (elev, azim) in enumerate(((25, -50), (25, 40))):
        ax = fig.add_subplot(1, 2, i + 1, projection="3d")
        for a, b in bones:
            ax.plot(*np.stack([a, b]).T, color="0.55", lw=2)
        sc = ax.scatter(*pos.T, c=mm, cmap="viridis", s=4, vmin=0, vmax=top)
        ax.view_init(elev, azim)
        lo, hi = np.minimum(pos.min(0), np.min([x for bone in bones for x in bone], 0)), \
            np.maximum(pos.max(0), np.max([x for bone in bones for x in bone], 0))
        ax.set_box_aspect(hi - lo + 1e-3)
        for axis, name in zip((ax.set_xlabel, ax.set_ylabel, ax.set_zlabel), "xyz"):
            axis(f"{name} (m)")
    fig.colorbar(sc, ax=fig.axes, shrink=0.7, label="stopping distance (mm): the onset -> the arm at rest")
    fig.suptitle(f"{row['driver']}, {row['fault']} (named {row['named_kind']}), swept at {row['speed']:g} x its "
                 f"limit: stop {row['stop_time_ms']:.0f} ms, the furthest taxel {row['stop_distance_mm']:.1f} mm "
                 f"({len(mm)} taxels)", fontsize=10)
    return save(fig, path)


def _arm(driver: str, map_path: Path, timing) -> _Stopping:
    """The storm's arm: its joints (the driver's), limits and its taxels' Jacobians at home."""
    from skinsafe.core.robot.kinematics import TaxelKinematics
    from skinsafe.core.robot.models import load_robot, only_joints
    from skinsafe.core.skin.taxel_map import load

    robot = load_robot(load(map_path).robot, base_dir=map_path.parent)
    if driver == "fr3":
        from skinsafe.hardware import franka

        robot = only_joints(robot, franka.JOINT_NAMES)
        joints = franka.JOINT_NAMES
        limits = {"qd_max": franka.QD_MAX, "qdd_max": franka.QDD_MAX, "qddd_max": franka.QDDD_MAX,
                  "q_min": franka.Q_MIN, "q_max": franka.Q_MAX}
    else:
        joints = [robot.model.joint(j).name for j in range(robot.model.njnt)][:robot.model.nv]
        limits = {"qd_max": np.asarray(robot.vel_limits, float), "qdd_max": np.asarray(robot.acc_limits, float),
                  "q_min": robot.model.jnt_range[:robot.model.nv, 0], "q_max": robot.model.jnt_range[:robot.model.nv, 1]}
    design = load(map_path, robot.body_names)
    kin = TaxelKinematics(robot.model, design)
    the = _Stopping(joints, limits, kin.jacobians_of(np.arange(design.n_taxels), robot.home)[0].copy(), timing)
    the.kin = kin
    return the


def add_arguments(p) -> None:
    p.add_argument("--runs", type=int, default=204)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--rate", type=int, default=50,
                   help="board frames per second (50: a board is silent after 40 ms; a 50 ms delay still trips it)")
    p.add_argument("--link-latency", type=float, default=0.0, metavar="S", help="`skinsafe run --link-latency` (a frame "
                   "delay is then 3 frame periods + this)")
    p.add_argument("--driver", choices=tuple(KINDS), default="sim", help="sim (default) or fr3 (franky-sim's FR3 in "
                   "its own process: `make franky-sim`); fr3 has no sim-* faults")
    p.add_argument("--kinds", nargs="+", metavar="FAULT", help="only these fault kinds, in turn (default: every kind "
                   "of the driver; fr3's contact kinds stack-qp-fail after-contact only on their own: their world has an obstacle)")
    p.add_argument("--speeds", type=float, nargs="+", default=list(SPEEDS), metavar="FRACTION",
                   help="the swept joint's speeds, fractions of its velocity limit; every kind runs at each in turn "
                        f"(the contact kinds {', '.join(CONTACT)} swept into something; default {' '.join(map(str, SPEEDS))})")
    p.add_argument("--picture", metavar="FILE.png", help="draw each taxel's stopping distance of the run whose furthest "
                   "taxel travelled furthest, on the arm's pose at its onset")
    p.add_argument("--json", action="store_true", help="print the per-run rows as one JSON list")


def run(args) -> int:
    from skinsafe.core.realtime import realtime

    rng = np.random.default_rng(args.seed)
    realtime("auto")  # before the emulator starts: it inherits the priority, as under `skinsafe run`
    signal.signal(signal.SIGINT, lambda *_: None)  # a run's own handler takes Ctrl-C; a late one lands here
    rows = []
    kinds = KINDS[args.driver]
    if args.kinds:
        known = kinds + (CONTACT if args.driver == "fr3" else ())
        unknown = [k for k in args.kinds if k not in known]
        if unknown:
            print(f"skinsafe faults: --kinds {' '.join(unknown)}: the {args.driver} driver's kinds are "
                  f"{', '.join(known)}", file=sys.stderr)
            return 2
        contact = [k in CONTACT for k in args.kinds] if args.driver == "fr3" else [False]
        if any(contact) and not all(contact):
            print(f"skinsafe faults: --kinds: the FR3's contact kinds ({', '.join(CONTACT)}) need an obstacle in its "
                  "world, the others none: give them on their own", file=sys.stderr)
            return 2
        kinds = tuple(args.kinds)
    obstacle = args.driver == "fr3" and set(kinds) <= set(CONTACT)
    with tempfile.TemporaryDirectory(prefix="skinsafe-faults-") as tmp, _setup(args.driver, Path(tmp), obstacle) as world:
        map_path, feed, ports, home, options = world
        from skinsafe.core.runtime.monitor import Timing

        period = 0.001 if args.driver == "fr3" else 0.002  # the drivers' periods (skinsafe run's sim default)
        frame = 1.0 / args.rate
        the = _arm(args.driver, map_path, Timing(period, frame, 2 * frame + args.link_latency, 0.1))
        plan = [(kind, v) for v in args.speeds for kind in kinds]
        pose, worst = home, None
        for k in tqdm(range(args.runs), desc=f"fault runs ({args.driver})", file=sys.stderr):
            kind, speed = plan[k % len(plan)]
            rows.append(one_run(k, kind, float(rng.uniform(0.3, 0.9)), map_path, feed, ports, pose,
                                Path(tmp), args.rate, args.link_latency, options, speed, the))
            # franky-sim's arm stays where a run left it: the next run sweeps from there (the sim starts at home)
            left = rows[-1].pop("pose")
            pose = np.asarray(left, float) if args.driver == "fr3" and left is not None else home
            travel = rows[-1].pop("travel")
            if travel is not None and (worst is None or (rows[-1]["stop_distance_mm"] or 0.0) >
                                       (worst[0]["stop_distance_mm"] or 0.0)):
                worst = (rows[-1], travel)
        if args.picture and worst is not None:
            picture(Path(args.picture), the, worst[0], *worst[1])
    print(json.dumps(rows) if args.json else "\n".join(map(str, rows)))
    return 0
