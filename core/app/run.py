"""`skinsafe run MAP --robot sim|fr3 --boards emulate|PORT... --command SOURCE`: the safety runtime.

Wires the pieces (only `app` may): the robot driver (`sim`: core/sim/robot_driver.py, in-process
MuJoCo whose contacts feed the emulated boards; `fr3`: hardware/franka.py), the boards (`emulate`:
one emulator process per run on pseudo-terminals, fed by the simulation and deployed with MAP
first; or the serial ports of real boards), the pre-flight and readings source
(hardware/skin_source.py), the stack, the command source and the recorder, then hands the loop
(core/runtime/loop.py) to the driver. The safety monitor (core/runtime/monitor.py) decides every stop;
its detection bounds are printed at the start with the distance a taxel can travel blind within each.
Ctrl-C (or SIGTERM) stops the robot first, then reports; every further signal only sets the same flag.

Exit codes: 0 the run ended as planned (--seconds, the trajectory's end) and the robot stopped;
1 a watchdog or the driver stopped the robot (the reason is named); 2 bad input; 3 the pre-flight
refused (the robot never moved); 4 the stop itself failed (its ramp did not bring the arm to rest, the
robot's stop failed, the link was lost while stopping: named, whatever ended the run); 130 Ctrl-C; 143 SIGTERM.
At the start it prints each fault's detection bound and the worst stopping time and distance of any taxel
(the arm at its velocity limits, braking at its acceleration and jerk limits: `monitor.stopping`); at the
end the stop as measured (onset -> every joint at rest, the furthest any taxel travelled meanwhile).
"""
from __future__ import annotations

import contextlib
import gc
import hashlib
import importlib
import json
import math
import os
import signal
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from skinsafe.core.realtime import background, below_host, is_realtime, loop_priority, one_thread, realtime
from skinsafe.core.runtime.commands import CommandError, Trajectory, command_source
from skinsafe.core.runtime.fault_plan import IN_PARTS, FaultPlan, Injection
from skinsafe.core.runtime.layers import build_stack, run_config
from skinsafe.core.runtime.limiter import JointLimits, Limiter
from skinsafe.core.runtime.loop import Runtime, warm_up
from skinsafe.core.runtime.monitor import (
    AFTER_CONTACT,
    OVERRUN_PERIODS,
    OVERRUNS,
    STOP_CATEGORY,
    Kind,
    Monitor,
    Timing,
    fastest_taxel_speed,
    stopping,
    table,
    travel,
)
from skinsafe.core.runtime.run_config import LINK_LATENCY_FREE, LINK_LATENCY_MAX, ROBOTS, RunConfig
from skinsafe.core.runtime.tap import Tap
from skinsafe.core.runtime.teleop import INTRUDER_DATAGRAMS, INTRUDER_WINDOW_S, Teleop, load_key
from skinsafe.core.safety.retraction import RetractionParams
from skinsafe.core.skin.files import atomic_write
from skinsafe.core.skin.model import DesignError
from skinsafe.hardware.client import baud_problem
from skinsafe.hardware.franka import ROBOT_FAULTS  # the FR3 driver's plan (its robot's states)

SWITCH_S = 0.0005  # the interpreter's thread switch interval while the robot moves (default 5 ms)
EXIT_CODES = {0: "ran as planned, robot stopped", 1: "a watchdog or the driver stopped the robot (named)",
              2: "bad input", 3: "pre-flight refused (the robot never moved)",
              4: "the stop itself failed (named: its ramp, the robot's stop, the link lost while stopping)",
              130: "Ctrl-C", 143: "SIGTERM"}
SIM_FAULTS = {"sim-freeze": "freeze_at", "sim-die": "die_at", "sim-clock-freeze": "clock_freeze_at",
              "sim-clock-back": "clock_back_at", "sim-overrun": "overrun_at", "sim-nan": "nan_at"}
SOURCE_FAULTS = IN_PARTS  # at their source (the FaultPlan handed to it), from S s after the hand-over on
READER_FAULTS = ("reader-kill", "reader-stall")  # at S s after the robot is handed over (before the boards settle)


def add_arguments(p) -> None:
    p.add_argument("map", help="taxel map (JSON) of the skin the boards run")
    p.add_argument("--robot", choices=ROBOTS, default=RunConfig.robot, help="sim: MuJoCo in this process (default); "
                   "fr3: a Franka FR3 over libfranka (hardware/franka.py)")
    p.add_argument("--host", help="fr3: the robot's (or franky-sim's) address")
    p.add_argument("--boards", nargs="+", required=True, metavar="emulate|PORT",
                   help="'emulate': emulated boards fed by the simulation; or the serial port of every board")
    p.add_argument("--command", required=True, metavar="SOURCE", help="hold | trajectory:FILE.csv | teleop:[HOST:]PORT "
                   "(default host 127.0.0.1; another only with --teleop-key)")
    p.add_argument("--seconds", type=float, help="stop after this long on the robot's clock (default: a trajectory's "
                   "end plus 1 s; otherwise until Ctrl-C)")
    p.add_argument("--record", metavar="DIR", help="record the run as a rosbag2 folder (ROS 2 messages in MCAP: "
                   "`ros2 bag play DIR`, Foxglove); `skinsafe replay DIR` re-runs it")
    p.add_argument("--rate", type=int, default=RunConfig.rate, help="frames per second per board (default 100: a board is "
                   "silent after 20 ms)")
    p.add_argument("--link-latency", type=float, default=RunConfig.link_latency, metavar="S",
                   help="how late the host's serial input may deliver a board's frames before the board is named silent, "
                        "on top of 2 frame periods (default 0: silent after 2 frame periods); a loaded host's kernel "
                        "holds serial input for tens to hundreds of ms (docs: Run a robot safely); above "
                        f"{LINK_LATENCY_FREE:g} s only with --allow-link-latency")
    p.add_argument("--allow-link-latency", action="store_true",
                   help=f"accept a --link-latency above {LINK_LATENCY_FREE:g} s (up to {LINK_LATENCY_MAX:g} s): a board "
                        "may then be blind that much longer before it is named silent (the start prints each bound and "
                        "the distance a taxel travels blind within it)")
    p.add_argument("--realtime", choices=("auto", "off"), default=RunConfig.realtime,
                   help="auto: run the loop, the skin reader and the emulated boards at real-time priority "
                        "(SCHED_FIFO 10), and keep idle cores out of their sleep states while the robot moves "
                        "(/dev/cpu_dma_latency 0), where the system allows it, as libfranka's hosts do (default)")
    p.add_argument("--allow-non-realtime", action="store_true",
                   help="fr3: move without real-time scheduling (refused otherwise): for a simulated robot such as "
                        "franky-sim, never for a real arm")
    p.add_argument("--baud", type=int, default=RunConfig.baud, help="board link speed (real boards)")
    p.add_argument("--tare-frames", type=int, default=RunConfig.tare_frames, help="frames per board for the tare and health checks")
    p.add_argument("--noise-fraction", type=float, default=RunConfig.noise_fraction,
                   help="a taxel whose reading spreads more than this fraction of its threshold at rest is noisy")
    p.add_argument("--max-excluded", type=float, default=RunConfig.max_excluded,
                   help="refuse to move when more than this fraction of the taxels is dead, stuck or noisy")
    p.add_argument("--command-timeout", type=float, default=RunConfig.command_timeout, help="teleop: stop when no datagram came for this long, s")
    p.add_argument("--teleop-key", metavar="FILE", help="teleop: the shared key file (`skinsafe teleop-key FILE`) the "
                   "leader signs its datagrams with; needed to listen beyond loopback")
    p.add_argument("--teleop-leader", metavar="HOST[:PORT]", help="teleop: the leader's address; datagrams from any other "
                   "are refused and named (default: the first sender whose datagram is valid is pinned)")
    p.add_argument("--tdm", help="a TDM checkpoint (skinsafe's torch format) for the strategy and modulation layers")
    p.add_argument("--alpha", type=float, default=RunConfig.alpha, help="retraction sensitivity, m/N")
    p.add_argument("--after-contact", choices=tuple(AFTER_CONTACT), default=RunConfig.after_contact,
                   help="; ".join(f"{k}: {v}" for k, v in AFTER_CONTACT.items()))
    sim = p.add_argument_group("sim robot")
    sim.add_argument("--period", type=float, default=RunConfig.period, help="the sim's control period, s (default 0.002: 500 Hz)")
    sim.add_argument("--contact", default=RunConfig.contact, metavar="poke|post[:KEY=VALUE,...]|none",
                     help="something in the sim's world to touch: poke (a sprung probe jabs the most upward taxel at "
                          "t=at s) or post (a sprung post in front of the taxel that rotating `joint` sweeps into it); "
                          "keys: at, taxel, joint, gap, depth, speed, stiffness")
    sim.add_argument("--taxel-fault", action="append", default=[], metavar="stuck|noisy:TAXEL",
                     help="a faulty sensor in the sim's skin (the pre-flight must find it); repeatable")
    sim.add_argument("--inject", action="append", default=[], metavar="FAULT@SECONDS[:BOARD]",
                     help="fault injection for tests and `bench runtime --faults`: board-unplug, frame-delay (50 ms, or 3 "
                          "frame periods + --link-latency, the longer), frame-lag, "
                          "frame-replay, foreign-uid, crc-storm, crc-burst (on the emulated boards' links), sim-freeze, sim-die, "
                          "sim-clock-freeze, sim-clock-back, sim-overrun (the state's clock 3 periods a tick), sim-nan "
                          "(the state's first joint position NaN); robot-freeze, robot-clock-back, robot-nan, robot-overrun, "
                          "robot-die (the FR3 driver's view of its robot's states: --robot fr3); "
                          "reader-kill (SIGKILL), reader-stall (SIGSTOP for a silence + 0.1 s) on the boards' reader, "
                          "S s after the robot is handed over (0: before the boards settle); from S s after the "
                          "hand-over: stack-nan (the layers' command non-finite), stack-qp-fail (the retraction's QP "
                          "solve fails at the next retraction tick), reading-nan (a NaN reading on the first taxel not "
                          "excluded), command-nan (the command source's plan non-finite); each handed to the part "
                          "that fails as the run's FaultPlan (core/runtime/fault_plan.py)")
    p.add_argument("--overruns", type=int, default=RunConfig.overruns, metavar="K",
                   help=f"stop after K consecutive overruns: ticks more than {OVERRUN_PERIODS:g} control periods apart "
                        f"on the robot's own clock, its states missed (default {OVERRUNS}; 0: off)")
    p.add_argument("--feed", metavar="NAME", help="with --boards emulate: the emulated boards stream this existing "
                   "shared-memory feed of simulated contacts (e.g. franky-sim's world, `feed NAME`; default: a fresh "
                   "one the sim driver writes)")
    p.add_argument("--view", action="store_true", help="see the run live: publish a view stream (Blender's add-on "
                   "attaches to it) and serve the web page (`skinsafe view`, its own process) at --view-port")
    p.add_argument("--view-port", type=int, default=RunConfig.view_port, help="--view: the web page's port (0: no page, stream only)")
    p.add_argument("--view-stream", default=RunConfig.view_stream, metavar="[HOST:]PORT",
                   help="--view: where the view stream is published (port 0: any free one)")
    p.add_argument("--foxglove", type=int, nargs="?", const=8765, metavar="PORT",
                   help="serve the run live to Foxglove (its WebSocket protocol, the record's ROS 2 topics) at "
                   "ws://127.0.0.1:PORT (default 8765; 0: any free one)")
    p.add_argument("--stats", metavar="FILE.json", help="write the run's figures (loop, latency, world, stop) as JSON")
    p.epilog = "exit codes: " + "; ".join(f"{k} {v}" for k, v in EXIT_CODES.items())


def _contact(text: str):
    from skinsafe.core.sim.robot_driver import Contact

    if text == "none":
        return None
    kind, _, rest = text.partition(":")
    kw = {}
    try:
        for item in filter(None, rest.split(",")):
            k, v = item.split("=")
            kw[k] = int(v) if k in ("taxel", "joint") else float(v)
        return Contact(kind, **kw)
    except (ValueError, TypeError) as e:
        raise DesignError(f"--contact {text!r}: {e}; e.g. poke, post:joint=0,gap=0.01 or poke:at=1.0") from None


def config(args) -> RunConfig:
    """The run's configuration from its command line, validated (a bad option: DesignError naming the fix)."""
    if baud_problem(args.baud):
        raise DesignError(baud_problem(args.baud))
    return RunConfig(map=args.map, boards=tuple(args.boards), command=args.command, robot=args.robot, host=args.host,
                     seconds=args.seconds, record=args.record, rate=args.rate, link_latency=args.link_latency,
                     allow_link_latency=args.allow_link_latency, realtime=args.realtime,
                     allow_non_realtime=args.allow_non_realtime, baud=args.baud, tare_frames=args.tare_frames,
                     noise_fraction=args.noise_fraction, max_excluded=args.max_excluded,
                     command_timeout=args.command_timeout, teleop_key=args.teleop_key,
                     teleop_leader=args.teleop_leader, tdm=args.tdm, alpha=args.alpha, after_contact=args.after_contact,
                     period=args.period, contact=args.contact, taxel_faults=_taxel_faults(args.taxel_fault),
                     inject=_injections(args.inject), overruns=args.overruns, feed=args.feed, view=args.view,
                     view_port=args.view_port, view_stream=args.view_stream, foxglove=args.foxglove,
                     stats=args.stats)


def _taxel_faults(items: list[str]) -> tuple[tuple[int, str], ...]:
    out = []
    for item in items:
        kind, _, i = item.partition(":")
        try:
            out.append((int(i), kind))
        except ValueError:
            raise DesignError(f"--taxel-fault {item!r}: give stuck:TAXEL or noisy:TAXEL (a taxel index)") from None
    return tuple(out)


def _injections(items: list[str]) -> tuple[Injection, ...]:
    """--inject FAULT@SECONDS[:BOARD], each a kind this run can inject."""
    from skinsafe.hardware.link_faults import LINK_FAULTS

    out = []
    kinds = LINK_FAULTS + tuple(SIM_FAULTS) + READER_FAULTS + SOURCE_FAULTS + ROBOT_FAULTS
    for item in items:
        kind, _, rest = item.partition("@")
        at, _, board = rest.partition(":")
        try:
            t = float(at)
            b = int(board) if board else None
        except ValueError:
            raise DesignError(f"--inject {item!r}: give FAULT@SECONDS[:BOARD], e.g. board-unplug@0.5:1") from None
        if kind not in kinds or not (math.isfinite(t) and t >= 0):
            raise DesignError(f"--inject {item!r}: faults are {', '.join(kinds)}, at a time >= 0 s")
        out.append(Injection(kind, t, b))
    return tuple(out)

def _driver(cfg: RunConfig, design, robot, feed, inject):
    if cfg.robot == "fr3":
        try:
            franka = importlib.import_module("skinsafe.hardware.franka")
        except ModuleNotFoundError as e:
            if e.name != "skinsafe.hardware.franka":
                raise
            raise DesignError("--robot fr3: the FR3 driver (skinsafe.hardware.franka) is not in this installation "
                              "yet; use --robot sim") from None
        if not cfg.host:
            raise DesignError("--robot fr3 needs --host IP: the robot's (or franky-sim's) address")
        try:
            return franka.FrankaDriver(cfg.host, rate_limited=False, faults=inject)  # the runtime's limiter does it
        except franka.FrankaError as e:
            raise DesignError(str(e)) from None
    from skinsafe.core.sim.robot_driver import SimDriver, SimFaults

    faults = SimFaults(**{SIM_FAULTS[i.kind]: i.at for i in inject.injections if i.kind in SIM_FAULTS})
    try:
        return SimDriver(design, robot, feed, cfg.period, _contact(cfg.contact), faults=faults,
                         taxel_faults=dict(cfg.taxel_faults))
    except ValueError as e:
        raise DesignError(f"--robot sim: {e}") from None


def _ports(cfg: RunConfig, design, stack: contextlib.ExitStack, feed) -> dict[int, str]:
    """Board id -> port: emulated boards fed by the simulation (the map deployed to them first), or the given ports."""
    from skinsafe.hardware.cli_deploy import find_ports
    from skinsafe.hardware.deploy import deploy
    from skinsafe.hardware.emulator import EmulatorProcess

    if cfg.boards == ("emulate",):
        flash = stack.enter_context(tempfile.TemporaryDirectory(prefix="skinsafe-flash-"))
        em = stack.enter_context(EmulatorProcess([], flash, "--map", str(cfg.map), "--feed", feed.name))
        below_host(em.proc.pid)
        ports = {b.id: em.ports[b.uid] for b in design.boards}
        bad = [r.line() for r in deploy(design, ports) if not r.ok]
        if bad:
            raise DesignError(f"deploying the map to the emulated boards failed: {bad[0]}")
        return ports
    ns = type("Ports", (), {"port": list(cfg.boards), "all": False, "glob": [], "timeout": 0.25, "retries": 4,
                            "baud": cfg.baud, "board": None, "no_system_ports": True})()
    ports, _, _, problems = find_ports(design, ns)
    if problems:
        raise DesignError(problems[0])
    return ports


def _view(cfg: RunConfig, stack: contextlib.ExitStack, design, driver, map_path: Path, map_hash: bytes) -> Tap:
    """The loop's tap for a live view: it shares the newest tick (`SharedTap`); the view stream's publisher and the
    web page (`skinsafe view HOST:PORT`) run in their own processes at a lower priority, ready before the robot
    moves; all end with the run."""
    import subprocess

    from skinsafe.core.runtime.view_share import SharedFrames, SharedTap, start_publisher
    from skinsafe.core.runtime.view_stream import hello

    host, _, port = cfg.view_stream.rpartition(":")
    msg = hello(design.n_taxels, design.taxels.ids, driver.joint_names, {b.uid: b.name for b in design.boards},
                str(map_path.resolve()), map_hash.hex(), driver.period_s, board_period_s=1.0 / cfg.rate)
    frames = SharedFrames.create(design.n_taxels, len(driver.joint_names), [b.uid for b in design.boards])
    stack.callback(frames.close)
    pub, address = start_publisher(frames, msg, host or "127.0.0.1", int(port), preexec=background)
    stack.callback(_end, pub)
    where = f"{address[0]}:{address[1]}"
    print(f"skinsafe run: view stream at {where} (Blender: Skin > Live > Attach)", file=sys.stderr)
    if cfg.view_port:
        page = subprocess.Popen([sys.executable, "-m", "skinsafe.core.app.cli", "view", where, "--port",
                                 str(cfg.view_port), "--until-ended"],
                                stdout=subprocess.PIPE, text=True, preexec_fn=background)
        stack.callback(_end, page)
        line = "-"
        while line and not line.startswith("skinsafe view:"):  # the page says where it is once it serves
            line = page.stdout.readline()
        if not line:
            raise ValueError(f"the view page did not start (exit {page.wait()})")
        print(f"skinsafe run: the view page at {line.split(' at ')[-1].strip()}", file=sys.stderr)
    return SharedTap(frames)


def _foxglove(cfg: RunConfig, stack: contextlib.ExitStack, design, driver, map_path: Path, tap: Tap) -> Tap:
    """The Foxglove server's process (core/app/foxglove_serve.py, at the view's low priority) fed by the loop's shared
    newest tick: the view's (`--view`) or its own; ready before the robot moves, ended with the run."""
    from skinsafe.core.app.foxglove_serve import start
    from skinsafe.core.runtime.view_share import SharedFrames, SharedTap

    if not isinstance(tap, SharedTap):
        frames = SharedFrames.create(design.n_taxels, len(driver.joint_names), [b.uid for b in design.boards])
        stack.callback(frames.close)
        tap = SharedTap(frames)
    proc, port = start(tap.frames, map_path.resolve(), driver.joint_names, cfg.foxglove, preexec=background)
    stack.callback(_end, proc)
    print(f"skinsafe run: Foxglove at ws://127.0.0.1:{port} (Foxglove: Open connection > Foxglove WebSocket; "
          "layout docs/run/skinsafe.foxglove.json)", file=sys.stderr)
    return tap


def _end(proc) -> None:
    proc.terminate()
    try:
        proc.wait(5)
    except Exception:
        proc.kill()
        proc.wait()


def run(args) -> int:
    """The command: its configuration from the command line (a bad option: one line, exit 2), then `execute`."""
    try:
        cfg = config(args)
    except DesignError as e:
        print(f"skinsafe run: {e}", file=sys.stderr)
        return 2
    return execute(cfg)


def execute(cfg: RunConfig, feed=None, ports=None, on_moving=None) -> int:
    """The run `cfg` configures. In-process callers (the fault bench) may pass an existing `feed` and the `ports` of
    boards it feeds (already running this map), and `on_moving(runtime)`, called once the robot is handed over. The
    operator's signal handler, once installed, stays until the report and the record are complete (a second
    Ctrl-C right after a quick stop must not cut them short)."""
    with contextlib.ExitStack() as signals:
        return _run(cfg, feed, ports, on_moving, signals)


class _Refused(Exception):
    """A run refused before the robot moved: its exit code and one line."""

    def __init__(self, code: int, message: str):
        super().__init__(message)
        self.code = code


@dataclass
class _Parts:
    """What one run wired: the robot's driver and arm, the boards' source, the stack's loop and its record."""

    driver: object
    arm: object
    limits: JointLimits
    source: object
    report: dict
    runtime: Runtime
    recorder: object
    links: object
    link_faults: list


def _run(cfg: RunConfig, feed, ports, on_moving, signals: contextlib.ExitStack) -> int:
    """Load, wire, move, report; a refusal is one line and its exit code."""
    try:
        inject, map_path, map_hash, robot, design = _load(cfg)
        rt = _scheduling(cfg)
        with contextlib.ExitStack() as stack:
            p = _wire(cfg, stack, feed, ports, inject, map_path, map_hash, robot, design)
            outcome, injected = _move(cfg, stack, p, design, inject, rt, signals, on_moving)
            p.source.close()  # the robot has stopped: the boards stop, and the reader says what any silence was
            lost, skin = p.source.frames_lost(), p.source.summary
            if p.links is not None:
                injected.update({k: p.links.onsets.get(b if b is not None else min(p.links.ports))
                                 for k, _, b in p.link_faults})
                injected.update({f"{k}-span": p.links.spans.get(b if b is not None else min(p.links.ports))
                                 for k, _, b in p.link_faults if k == "crc-burst"})
            teleop = _teleop(p.runtime.command)
            rec = p.recorder.close({"reason": outcome.reason, "kind": outcome.kind, "watchdog": outcome.watchdog,
                                    "t": outcome.t, "ns": time.time_ns(), "ticks": outcome.ticks,
                                    "dropped": p.recorder.dropped, "frames_lost": lost,
                                    **({"teleop": teleop["line"]} if teleop else {})}) if p.recorder else None
    except _Refused as e:
        print(f"skinsafe run: {e}", file=sys.stderr)
        return e.code
    onsets = [v for k, v in injected.items() if not k.endswith("-span") and isinstance(v, float)]
    if onsets and outcome.stats:  # an injected fault: the stop is measured from its onset (what the bench times)
        outcome.stopping = p.runtime.stopping(min(onsets)) | {"onset": "injected"}
    _report(cfg, p, design, outcome, injected, lost, skin, rec, teleop)
    return outcome.exit_code


def _teleop(command) -> dict | None:
    """Teleop's tally (who led, who was refused and why) with its one line for the operator and the record."""
    if not isinstance(command, Teleop):
        return None
    s = command.summary()
    refused = "; ".join(f"{x['address']} {x['datagrams']} ({x['why']})" for x in s["senders"]) or "none"
    leader = f"{s['leader']} ({'given' if s['pinned'] == 'given' else 'pinned: its first valid datagram'})" \
        if s["leader"] else "none (no valid datagram came)"
    key = f"key id {s['key_id']}" if s["key_id"] else "no key"
    return s | {"line": f"leader {leader}, {key}: {s['accepted']} datagrams accepted, {s['refused']} refused: "
                        f"{refused}"}


def _load(cfg: RunConfig):
    """(injections, map path, its sha256, robot, design), or refused (2)."""
    from skinsafe.core.robot.models import load_robot
    from skinsafe.core.skin.taxel_map import load

    try:
        inject = FaultPlan(cfg.inject)
        map_path = Path(cfg.map)
        map_hash = hashlib.sha256(map_path.read_bytes()).digest()
        robot = load_robot(load(map_path).robot, base_dir=map_path.parent)
        return inject, map_path, map_hash, robot, load(map_path, robot.body_names)
    except (DesignError, OSError) as e:
        raise _Refused(2, str(e)) from None


def _scheduling(cfg: RunConfig) -> str:
    """The real-time scheduling asked for (core/realtime.py); the FR3 without it is refused (2) unless allowed."""
    rt = realtime(cfg.realtime)
    if cfg.robot == "fr3" and not is_realtime():
        if not cfg.allow_non_realtime:
            raise _Refused(2, f"--robot fr3 needs real-time scheduling (SCHED_FIFO), and this process has {rt}: run as "
                           "a user allowed rtprio (/etc/security/limits.conf) with --realtime auto, or pass "
                           "--allow-non-realtime for a simulated robot such as franky-sim")
        print(f"skinsafe run: WARNING: the FR3 without real-time scheduling ({rt}; --allow-non-realtime)",
              file=sys.stderr)
    return rt


def _wire(cfg: RunConfig, stack, feed, ports, inject, map_path, map_hash, robot, design) -> _Parts:
    """Driver, command source, boards (pre-flight), stack, recorder and view, each closed by `stack`; refused with
    2 (bad input) or 3 (the pre-flight)."""
    from skinsafe.core.app.record_writer import start as start_writer
    from skinsafe.core.robot.models import only_joints
    from skinsafe.core.skin.force_feed import FeedError, ForceFeed
    from skinsafe.hardware.client import BoardError
    from skinsafe.hardware.skin_source import PreflightRefused, SkinSource

    try:
        if feed is None:
            feed = stack.enter_context(ForceFeed.attach(cfg.feed) if cfg.feed else
                                       ForceFeed.create(None, design.n_taxels))
            if feed.n != design.n_taxels:
                raise DesignError(f"--feed {cfg.feed} holds {feed.n} taxels, the map {design.n_taxels}")
        driver = _driver(cfg, design, robot, feed, inject)
        stack.callback(driver.close)
        arm = only_joints(robot, driver.joint_names)  # the joints the driver moves (the FR3: not its fingers)
        recorder = None
        if cfg.record:  # its writer starts up beside the pre-flight; the record begins after it
            try:
                recorder = start_writer(Path(cfg.record), map_path.resolve(), driver.joint_names,
                                        [b.uid for b in design.boards], design.n_taxels)
            except OSError as e:
                raise _Refused(2, f"--record {cfg.record}: {e}; choose a folder you can write to") from None
            stack.callback(recorder.close, {"reason": "the run ended before its stop", "kind": "fault"})
        try:
            limits = JointLimits.of(driver.limits())  # validated once, here
        except ValueError as e:
            raise DesignError(f"--robot {cfg.robot}: {e}") from None
        key = load_key(cfg.teleop_key) if cfg.teleop_key else None
        command = command_source(cfg.command, driver.joint_names, limits, cfg.command_timeout, key,
                                 cfg.teleop_leader)
        stack.callback(command.close)
        ports = ports or _ports(cfg, design, stack, feed)
        links = None
        link_faults = [(i.kind, i.at, i.board) for i in inject.injections
                       if i.kind not in (*SIM_FAULTS, *READER_FAULTS, *SOURCE_FAULTS, *ROBOT_FAULTS)]
        if link_faults:
            from skinsafe.hardware.link_faults import DELAY_S, LinkFaults

            links = stack.enter_context(LinkFaults(ports, link_faults, max(DELAY_S, 3.0 / cfg.rate + cfg.link_latency)))
            ports = links.ports
        source = SkinSource(design, ports, cfg.rate, cfg.noise_fraction, cfg.max_excluded,
                            link_latency=cfg.link_latency, baud=cfg.baud, faults=inject)
        stack.callback(source.close)
        report = source.preflight(map_hash, cfg.tare_frames)
    except (DesignError, CommandError, FeedError) as e:
        raise _Refused(2, str(e)) from None
    except (PreflightRefused, BoardError) as e:
        raise _Refused(3, f"pre-flight refused: {e}") from None
    print(f"skinsafe run: pre-flight passed: {len(report['boards'])} boards run this map, tared over "
          f"{cfg.tare_frames} frames; excluded {report['excluded']} taxels (dead {report['dead'][:8]}, stuck "
          f"{report['stuck'][:8]}, noisy {report['noisy'][:8]}, disabled in the map {report['disabled_in_map']})",
          file=sys.stderr)
    params = RetractionParams(alpha=cfg.alpha)
    try:
        layers = build_stack(design, arm.model, limits["qd_max"], limits["qdd_max"], driver.period_s, params, cfg.tdm,
                             faults=inject)
    except (ValueError, OSError) as e:
        raise _Refused(2, f"--tdm: {e}") from None
    warm_up(layers, arm.home, design.taxels.thresholds["force"], driver.period_s)
    seconds = cfg.seconds or (command.duration + 1.0 if isinstance(command, Trajectory) else None)
    if recorder is not None:
        config = run_config(map_path, driver, limits, params, source.excluded, command.spec, cfg.tdm)
        config["run"] = cfg.to_json()  # the run's whole configuration, as given (RunConfig.from_json reads it)
        config["board_period_s"] = 1.0 / cfg.rate  # for the view's board health
        if isinstance(command, Teleop):  # who may drive it, and with which key (its id, never its value)
            config["teleop"] = {"leader": cfg.teleop_leader or "", "key": command.key.path, "key_id": command.key.key_id}
        try:
            recorder.begin(config)
        except OSError as e:
            raise _Refused(2, f"--record {cfg.record}: {e}; choose a folder you can write to") from None
    tap = Tap()
    if cfg.view:
        try:
            tap = _view(cfg, stack, design, driver, map_path, map_hash)
        except (OSError, ValueError) as e:
            raise _Refused(2, f"--view: {e}") from None
    if cfg.foxglove is not None:
        try:
            tap = _foxglove(cfg, stack, design, driver, map_path, tap)
        except OSError as e:
            raise _Refused(2, f"--foxglove: {e}") from None
    runtime = Runtime(driver, source, layers, command, source.excluded, design.taxels.thresholds["force"],
                      recorder, tap, seconds=seconds, monitor=Monitor(cfg.after_contact), limiter=Limiter(limits, driver.period_s),
                      overruns=cfg.overruns, faults=inject)
    return _Parts(driver, arm, limits, source, report, runtime, recorder, links, link_faults)


def _move(cfg: RunConfig, stack, p: _Parts, design, inject, rt: str, signals: contextlib.ExitStack, on_moving):
    """The operator's signals to the monitor, the injected faults started, the loop at its priority with no
    collector pause until the robot stops: (outcome, injected faults' onsets)."""
    runtime, driver, source = p.runtime, p.driver, p.source
    _print_bounds(Timing(driver.period_s, 1.0 / cfg.rate, source.silence_s, runtime.command.stale_s,
                         overruns=cfg.overruns), p.arm, design, p.limits)
    if p.links is not None:
        p.links.arm(source.silence_s)

    def on_signal(signum, _frame):  # only sets the monitor's flag, the first time and every time after
        runtime.stop_by_operator(signum, signal.Signals(signum).name)

    for signum in (signal.SIGINT, signal.SIGTERM):
        signals.callback(signal.signal, signum, signal.signal(signum, on_signal))
    if isinstance(runtime.command, Teleop):
        c = runtime.command
        print(f"skinsafe run: teleop: listening at {c.spec}, " + (f"key id {c.key.key_id}" if c.key.secret else
              "no key (loopback only)") + "; leader " + (f"{c.leader_name} (given)" if c.pinned == "given" else
              "not given: the first sender whose datagram is valid is pinned (--teleop-leader names it)") +
              f"; {INTRUDER_DATAGRAMS} datagrams refused within {INTRUDER_WINDOW_S:g} s stop the robot", file=sys.stderr)
    print(f"skinsafe run: {driver.name} robot moving under '{runtime.command.spec}' ({driver.period_s * 1e3:g} ms "
          f"period, boards at {cfg.rate} Hz, {rt}); Ctrl-C stops it", file=sys.stderr, flush=True)
    inject.start()  # the hand-over: the plan's times count from now (the parts ask it)
    injected = _reader_faults(stack, inject, source, source.silence_s + 0.1)
    if on_moving is not None:
        on_moving(runtime)
    switch = sys.getswitchinterval()
    sys.setswitchinterval(SWITCH_S)
    one_thread()
    gc.freeze()  # no collector pause while the robot moves (what the loop allocates is freed by refcount)
    gc.disable()
    try:
        with loop_priority(rt):
            return runtime.run(), injected | inject.onsets
    finally:
        gc.enable()
        sys.setswitchinterval(switch)


def _report(cfg: RunConfig, p: _Parts, design, outcome, injected: dict, lost: int, skin: dict, rec: dict | None,
            teleop: dict | None = None) -> None:
    """The stop and the run's figures for the operator; with --stats, everything as JSON."""
    t = outcome.stats
    head = {"end": "stopped as planned", "operator": "STOPPED by the operator", "fault": "STOPPED by a watchdog",
            "driver": "STOPPED by the robot"}[outcome.kind]
    head = f"{head}, and THE STOP FAILED" if outcome.during_stop else head
    print(f"skinsafe run: {head}: {outcome.reason}", file=sys.stderr if outcome.exit_code else sys.stdout)
    stop = _stop_figures(outcome, p.arm, design) if t else {}
    if stop.get("stop_time_ms") is not None and stop.get("stop_distance_mm") is not None:
        print(f"skinsafe run: the stop: {stop.get('onset', 'onset' if outcome.onset_mono else 'decision')} -> every "
              f"joint below {stop['rest_qd']:g} rad/s in {stop['stop_time_ms']:.1f} ms; the furthest taxel "
              f"({stop['stop_distance_taxel']}) travelled {stop['stop_distance_mm']:.1f} mm meanwhile", file=sys.stderr)
    elif stop:
        print(f"skinsafe run: the stop: {stop.get('why', 'not measured')}", file=sys.stderr)
    for silence in skin.get("silences", []):
        print(f"skinsafe run: board '{silence['board']}' silent for {silence['silent_ms']} ms: {silence['cause']}",
              file=sys.stderr)
    if teleop:
        print(f"skinsafe run: teleop: {teleop['line']}", file=sys.stderr if teleop["refused"] else sys.stdout)
    if not t:  # stopped before the robot moved: no loop figures
        print("the robot never moved" + (f"; record {rec.get('path', rec.get('error'))}" if rec else ""))
    else:
        print(f"ticks {t['ticks']}, loop {t['loop_hz_p50']:.0f} Hz (period p99 {t['period_ms_p99']:.2f} ms), contact latency "
              f"p50 {t['latency_ms_p50']:.2f} / p99 {t['latency_ms_p99']:.2f} / max {t['latency_ms_max']:.2f} ms over "
              f"{t['latency_samples']} frames, frames lost {lost}"
              + (f"; record {rec.get('path', rec.get('error'))}: {rec['written']} messages, the telemetry of "
                 f"{rec['dropped']} ticks dropped (every tick's joint state and command kept)"
                 if rec else ""))
    if cfg.stats:
        driver = p.driver
        world = getattr(driver, "stats", None)
        world = world if isinstance(world, dict) or world is None else vars(world)
        out = {"reason": outcome.reason, "kind": outcome.kind, "watchdog": outcome.watchdog, "t": outcome.t,
               "detected_mono": outcome.detected_mono, "onset_mono": outcome.onset_mono, "state": outcome.state,
               "exit": outcome.exit_code, "injected": injected, "frames_lost": lost, "preflight": p.report,
               "record": rec, "period_s": driver.period_s, "robot": driver.name, "taxels": design.n_taxels,
               "boards": len(design.boards), **t, "skin": skin, "teleop": teleop, "stopping": stop,
               "during_stop": list(outcome.during_stop),
               "world": {k: v for k, v in world.items() if k != "extra"} if world is not None else {}}
        atomic_write(Path(cfg.stats), json.dumps(out, default=_plain))


def _print_bounds(tm: Timing, arm, design, limits: JointLimits) -> None:
    """The monitor's detection bound of each fault kind, how far the fastest taxel (at home, every joint at its
    limit) travels blind within it, and the worst stopping time and distance of any taxel (`monitor.stopping`)."""
    from skinsafe.core.robot.kinematics import TaxelKinematics

    J = TaxelKinematics(arm.model, design).jacobians_of(np.arange(design.n_taxels), arm.home)[0]
    speed = fastest_taxel_speed(J, limits["qd_max"])
    rows = "; ".join(f"{k} {ms:.0f} ms / {mm:.0f} mm" for k, ms, mm, _ in table(tm, speed))
    print(f"skinsafe run: detection bounds / blind distance at the fastest taxel's {speed:.2f} m/s: {rows}",
          file=sys.stderr)
    kinds = {k for k, *_ in table(tm)}
    stop = {k: v for k, v in stopping(tm, J, limits["qd_max"], limits["qdd_max"], limits.get("qddd_max")).items()
            if k.value in kinds}
    worst = max(stop, key=lambda k: stop[k][1])
    print(f"skinsafe run: worst stopping distance {stop[worst][1] * 1e3:.0f} mm in {stop[worst][0] * 1e3:.0f} ms "
          f"(`{worst.value}`: its detection bound, then every joint braking from its velocity limit at its "
          f"acceleration limit; any taxel, at home)", file=sys.stderr)


def _stop_figures(outcome, arm, design) -> dict:
    """The stop as measured (`Runtime.stopping`): onset -> rest (ms), and the furthest any taxel travelled from where
    it was at the onset, up to the rest (mm, `monitor.travel`)."""
    from skinsafe.core.robot.kinematics import TaxelKinematics

    s = dict(outcome.stopping)
    path = np.asarray(s.pop("q_path", []), float)
    if not len(path):
        return s
    s["states_unknown"] = int((~np.isfinite(path).all(axis=1)).sum())  # a broken encoder's states place no taxel
    far = travel(TaxelKinematics(arm.model, design), path)
    if not np.isfinite(far).any():
        return s | {"stop_distance_mm": None, "why": "no finite joint state after the onset"}
    k = int(np.nanargmax(far))
    return s | {"stop_distance_mm": float(far[k] * 1e3), "stop_distance_taxel": k,
                "stop_category": STOP_CATEGORY[Kind(outcome.watchdog)] if outcome.watchdog else 2}


def _reader_faults(stack: contextlib.ExitStack, inject, source, stall_s: float) -> dict:
    """--inject reader-kill / reader-stall: timers from the hand-over on; fault -> host time it was done (filled
    in when it is)."""
    done = {}

    def later(at: float, call, *args) -> None:
        timer = threading.Timer(at, call, args)
        timer.daemon = True
        timer.start()
        stack.callback(timer.cancel)

    def hit(kind: str) -> None:
        pid = source.pid
        if pid is None:
            return
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGKILL if kind == "reader-kill" else signal.SIGSTOP)
            done[kind] = time.monotonic()
        if kind == "reader-stall":
            later(stall_s, _signal, pid, signal.SIGCONT)

    for kind, at in ((i.kind, i.at) for i in inject.injections if i.kind in READER_FAULTS):
        if at == 0:  # now, and the boards' readings already stale when the loop looks: the boards settle after it
            hit(kind)
            time.sleep(2 * source.frame_period_s)
        else:
            later(at, hit, kind)
    return done


def _signal(pid: int, signum: int) -> None:
    with contextlib.suppress(ProcessLookupError):
        os.kill(pid, signum)


def _plain(x):
    return x.item() if isinstance(x, np.generic) else str(x)
