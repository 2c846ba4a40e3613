"""The fault storm behind `skinsafe bench runtime --faults`: many short `skinsafe run`s, each with one fault.

Run as its own process (`python -m skinsafe.core.app.runtime_faults --runs N --json`; the bench starts
it): one emulator process (boards fed by the run's simulation through one shared-memory feed, the
map deployed once) serves every run; each run is the real command (`core.app.run.run`: pre-flight,
sim driver, readings source, stack, recorder, signal handling) with one fault, at a random time
0.1-0.8 s after the robot starts moving, in turn:
- board-unplug: a board's link closes (the host's side of its pseudo-terminal);
- frame-delay: a board's frames arrive 50 ms late;
- frame-replay / foreign-uid (alternating): a frame sent again, or one with another board's uid;
- sim-die / sim-freeze (alternating): the simulation fails, or its state stops updating;
- command-silent: the teleop leader stops sending;
- ctrl-c: SIGINT to this process.
Per run: was it stopped, by the watchdog that names this fault, within 2 periods of the detection
(zero velocity sent), any traceback, is the record readable (every message decodes with
mcap-ros2-support and the last one is the stop's diagnostics)?
"""
from __future__ import annotations

import argparse
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

KINDS = ("board-unplug", "frame-delay", ("frame-replay", "foreign-uid"), ("sim-die", "sim-freeze"), "command-silent",
         "ctrl-c")
NAMED_BY = {"board-unplug": "link lost", "frame-delay": "silent for", "frame-replay": "frame counter went back",
            "foreign-uid": "frames from another uid", "sim-die": "the simulation failed",
            "sim-freeze": "state not updating", "command-silent": "command: teleop", "ctrl-c": "interrupted by the operator"}


def _kind(k: int) -> str:
    kind = KINDS[k % len(KINDS)]
    return kind if isinstance(kind, str) else kind[(k // len(KINDS)) % 2]


def _readable(record: Path) -> bool:
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    try:
        last = None
        with open(record, "rb") as f:
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


def one_run(k: int, kind: str, at: float, map_path: Path, feed, ports, home, out: Path, rate: int,
            link_latency: float = 0.0) -> dict:
    """One `skinsafe run` with the fault `kind` at `at` s after the robot starts moving."""
    from skinsafe.core.app import run as run_cmd
    from skinsafe.core.app.cli import module_args
    from skinsafe.core.runtime.leader import stream

    record, stats = out / f"run{k}.mcap", out / f"run{k}.json"
    command, extra, stop = "hold", [], threading.Event()
    timers = []
    if kind == "command-silent":
        port = _free_port()
        command = f"teleop:{port}"
        threading.Thread(target=stream, args=(("127.0.0.1", port), np.array([0.0, 1.0]), np.stack([home, home]), stop),
                         daemon=True).start()
    elif kind != "ctrl-c":
        extra = ["--inject", f"{kind}@{at:.3f}"]

    def moving(runtime):
        if kind == "command-silent":
            timers.append(threading.Timer(at, stop.set))
        elif kind == "ctrl-c":
            timers.append(threading.Timer(at, os.kill, (os.getpid(), signal.SIGINT)))
        for t in timers:
            t.start()

    args = module_args(run_cmd, "skinsafe run", "", [str(map_path), "--boards", "emulate", "--command", command,
                                                     "--rate", str(rate), "--link-latency", str(link_latency),
                                                     "--tare-frames", "10", "--seconds", "3",
                                                     "--record", str(record), "--stats", str(stats), *extra], "run")
    err, tb = io.StringIO(), ""
    t0 = time.monotonic()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        try:
            code = run_cmd.run(args, feed=feed, ports=dict(ports), on_moving=moving)
        except BaseException:
            code, tb = None, traceback.format_exc()
    stop.set()
    for t in timers:
        t.cancel()
    _stop_boards(ports)
    s = json.loads(stats.read_text()) if stats.exists() else {}
    reason = s.get("reason", "")
    world = s.get("world", {})
    stop_periods = ((world.get("zero_mono", np.inf) - s.get("detected_mono", 0.0)) / s.get("period_s", 1.0)
                    if s else np.inf)
    return {"run": k, "fault": kind, "at_s": round(at, 3), "exit": code, "reason": reason,
            "stopped": bool(s) and s.get("kind") != "end", "named": bool(reason) and s.get("kind") != "end",
            "named_as_injected": NAMED_BY[kind] in reason, "stop_periods": float(stop_periods),
            "traceback": bool(tb) or "Traceback" in err.getvalue(), "record_readable": _readable(record),
            "seconds": time.monotonic() - t0, "detail": tb.strip().splitlines()[-1] if tb else ""}


def main(argv: list[str] | None = None) -> int:
    from skinsafe.core.design.sample import make_sample_design
    from skinsafe.core.robot.models import build_ur5
    from skinsafe.core.skin.force_feed import ForceFeed
    from skinsafe.core.skin.taxel_map import save
    from skinsafe.hardware.deploy import deploy
    from skinsafe.hardware.emulator import EmulatorProcess

    p = argparse.ArgumentParser(prog="python -m skinsafe.core.app.runtime_faults", description=__doc__.split("\n\n")[0])
    p.add_argument("--runs", type=int, default=204)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--rate", type=int, default=50,
                   help="board frames per second (50: a board is silent after 40 ms; a 50 ms delay still trips it)")
    p.add_argument("--link-latency", type=float, default=0.0, metavar="S", help="`skinsafe run --link-latency` (a frame "
                   "delay is then 3 frame periods + this)")
    p.add_argument("--json", action="store_true", help="print the per-run rows as one JSON list")
    args = p.parse_args(argv)
    from skinsafe.core.app.run import _realtime

    rng = np.random.default_rng(args.seed)
    _realtime("auto")  # before the emulator starts: it inherits the priority, as under `skinsafe run`
    signal.signal(signal.SIGINT, lambda *_: None)  # a run's own handler takes Ctrl-C; a late one lands here
    rows = []
    with tempfile.TemporaryDirectory(prefix="skinsafe-faults-") as tmp:
        tmp = Path(tmp)
        robot = build_ur5()
        design = make_sample_design("ur5", robot=robot)
        save(design, tmp / "skin.json")
        with ForceFeed.create(None, design.n_taxels) as feed, \
                EmulatorProcess([], tmp / "flash", "--map", str(tmp / "skin.json"), "--feed", feed.name) as em:
            ports = {b.id: em.ports[b.uid] for b in design.boards}
            if not all(r.ok for r in deploy(design, ports)):
                raise SystemExit("runtime faults: deploying the sample map to the emulated boards failed")
            for k in tqdm(range(args.runs), desc="fault runs", file=sys.stderr):
                rows.append(one_run(k, _kind(k), float(rng.uniform(0.1, 0.8)), tmp / "skin.json", feed, ports,
                                    robot.home, tmp, args.rate, args.link_latency))
                for f in tmp.glob(f"run{k}.*"):
                    f.unlink()
    print(json.dumps(rows) if args.json else "\n".join(map(str, rows)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
