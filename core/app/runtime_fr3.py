"""The FR3 case end to end, across two processes and two protocols: franky-sim's FR3 (its own process
and environment, `core/sim/franky_world.py`) with a sphere in its world, emulated boards streaming that
world's contacts over serial (pseudo-terminals), and the FR3 driver (`hardware/franka.py`) over
libfranka; plus the `fr3` rows of `skinsafe bench runtime`.

    python -m skinsafe.core.app.runtime_fr3 [--taxels 4096 16384] [--seconds 60] [--json] [--out DIR]

The control is `ContactRetreat` (approach the sphere, retreat on the boards' first contact frame,
pause, repeat) until the runtime's loop (`skinsafe run --robot fr3`) ticks the safety stack here:
`fr3_rows(make_control=...)` takes its tick. What these rows measure is the chain around the
tick: the robot's clock, the boards' frames, the communication constraint and the robot's reaction.
"""
from __future__ import annotations

import argparse
import json
import tempfile
import threading
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from skinsafe.core.sim.franky_world import INITIAL_Q, WorldProcess, obstacle_in_path
from skinsafe.core.skin import taxel_map
from skinsafe.core.skin.files import atomic_write
from skinsafe.hardware.deploy import deploy
from skinsafe.hardware.emulator import EmulatorProcess
from skinsafe.hardware.franka import FrankaDriver
from skinsafe.hardware.stream import SkinStream

APPROACH = np.array([0.3, 0, 0, 0, 0, 0, 0])  # rad/s: the base joint swings the arm into the sphere
LEAD_S = 0.5  # s of that motion before the first contact
RADIUS = 0.05  # m


class BoardReader:
    """Polls the boards in its own thread; `newest()` never waits on I/O (the tick reads it every 1 ms).

    A stand-in for `hardware/skin_source.py` (the runtime's `ReadingsSource`): the largest force of
    the newest frames, its host time, and the frames counted."""

    def __init__(self, stream: SkinStream):
        self.stream = stream
        self.t = 0.0
        self.peak = 0.0
        self.frames = self.lost = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, daemon=True)

    def start(self) -> None:
        self._thread.start()

    def _loop(self) -> None:
        while not self._stop.is_set():
            u = self.stream.poll(0.002)
            if u.frames:
                self.peak = float(np.nanmax(u.peak))  # one float store: readers see old or new, never torn
                self.t = u.t
                self.frames += u.frames
            self.lost = u.lost

    def newest(self) -> tuple[float, float]:
        """(host time of the newest frames, their largest force in N)."""
        return self.t, self.peak

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)


@dataclass
class ContactRetreat:
    """Approach along `qd` until the boards show contact (`threshold` N), retreat until back at the start
    joint angle, pause `pause_s`, repeat; ends in a pause after `seconds` of robot time (or `give_up_s`
    later if the boards never showed a contact). Logs every tick."""

    reader: BoardReader
    qd: np.ndarray
    threshold: float
    seconds: float
    pause_s: float = 0.3
    give_up_s: float = 10.0
    retreats: int = 0
    phase: str = "approach"
    t_phase: float = 0.0
    t_start: float = 0.0
    q_start: np.ndarray | None = None
    log: list = field(default_factory=list)  # (robot t, host t, q0, qd0 measured, command sign, frame age)

    def __call__(self, s):
        now = time.monotonic()
        t_frame, f = self.reader.newest()
        if self.q_start is None:
            self.q_start, self.t_phase, self.t_start = s.q.copy(), s.t, s.t
        elapsed = s.t - self.t_start
        if elapsed > self.seconds and (self.phase == "pause" or elapsed > self.seconds + self.give_up_s):
            return None
        if self.phase == "approach" and f > self.threshold:
            self.phase, self.t_phase = "retreat", s.t
            self.retreats += 1
        elif self.phase == "retreat" and (s.q - self.q_start) @ self.qd <= 0:
            self.phase, self.t_phase = "pause", s.t
        elif self.phase == "pause" and s.t - self.t_phase > self.pause_s:
            self.phase, self.t_phase = "approach", s.t
        sign = {"approach": 1.0, "retreat": -1.0, "pause": 0.0}[self.phase]
        self.log.append((s.t, now, float(s.qd @ self.qd), sign, now - t_frame if f > self.threshold else np.nan))
        return sign * self.qd


@dataclass
class Session:
    design: object
    world: WorldProcess
    driver: FrankaDriver
    reader: BoardReader
    stream: SkinStream


@contextmanager
def fr3_session(map_path: str | Path, workdir: str | Path, obstacle=None, q0=None, rate_hz: int = 1000):
    """franky-sim's world, emulated boards fed from its contacts (the map deployed to them, streaming), and
    the driver connected: a `Session`; everything it started ends with it."""
    workdir = Path(workdir)
    design = taxel_map.load(map_path)
    with WorldProcess(map_path, workdir / "world.json", obstacle, q0) as world, \
            EmulatorProcess([], workdir / "flash", "--map", str(map_path), "--feed", world.feed) as em:
        ports = {b.id: em.ports[b.uid] for b in design.boards}
        failed = [r for r in deploy(design, ports) if not r.ok]
        if failed:
            raise RuntimeError(f"deploy to the emulated boards failed: {failed[0].message}")
        stream = SkinStream(design, ports, rate_hz)
        stream.start()
        reader = BoardReader(stream)
        reader.start()
        driver = FrankaDriver(world.host)
        try:
            yield Session(design, world, driver, reader, stream)
        finally:
            driver.close()
            reader.close()
            stream.stop()
            stream.close()


def contact_run(map_path, workdir, seconds: float, rate_hz: int = 1000, make_control=None) -> dict:
    """One closed-loop run into a sphere placed in the motion's path; the row's figures and the raw logs."""
    sphere = obstacle_in_path(str(map_path), APPROACH, INITIAL_Q, LEAD_S, RADIUS)
    with fr3_session(map_path, workdir, sphere, rate_hz=rate_hz) as s:
        threshold = float(s.design.taxels.thresholds["force"].min())
        control = (make_control or ContactRetreat)(s.reader, APPROACH, threshold, seconds)
        t0 = time.monotonic()
        reason = s.driver.run(control)
        wall = time.monotonic() - t0
        frames, lost = s.reader.frames, s.reader.lost
        stats = dict(s.driver.stats)
        world = s.world.stop()
    return {"reason": reason, "wall_s": wall, "driver": stats, "world": world, "log": np.array(control.log),
            "frames": frames, "frames_lost": lost, "sphere": sphere, "boards": len(s.design.boards),
            "taxels": s.design.n_taxels}


def reaction_ms(onsets, log: np.ndarray) -> np.ndarray:
    """Per contact onset (robot time): ms until the measured joint velocity first follows the retreat."""
    t, follows = log[:, 0], (log[:, 2] < 0) & (log[:, 3] < 0)
    out = []
    for t_on in onsets:
        k = np.flatnonzero((t >= t_on) & follows)
        if len(k):
            out.append(1e3 * (t[k[0]] - t_on))
    return np.array(out)


def row(run: dict) -> dict:
    """A `bench runtime` row (the sim rows' keys; the robot's clock is libfranka's RobotState.time)."""
    log, w, d = run["log"], run["world"], run["driver"]
    dt_robot = np.diff(log[:, 0]) * 1e3
    dt_wall = np.diff(log[:, 1]) * 1e3
    lat = log[:, 4][np.isfinite(log[:, 4])] * 1e3
    react = reaction_ms(w["onsets"], log)
    def pct(a, p):
        return round(float(np.percentile(a, p)), 3) if len(a) else None

    return {"robot": "fr3", "driver": "fr3", "boards": run["boards"], "taxels": run["taxels"], "ticks": d["ticks"],
            "loop_hz_p50": round(1e3 / float(np.median(dt_robot)), 1), "period_ms_p99": pct(dt_robot, 99),
            "latency_ms_p50": pct(lat, 50), "latency_ms_p99": pct(lat, 99),
            "latency_ms_max": round(float(lat.max()), 3) if len(lat) else None,
            "reaction_ms": pct(react, 50), "reaction_ms_worst": round(float(react.max()), 1) if len(react) else None,
            "contacts": len(w["onsets"]), "peak_N": w["peak_N"], "into_contact_mm_worst": w["into_contact_mm_worst"],
            "stale_stops": int("stale" in run["reason"] or "silent" in run["reason"]),
            "frames_lost": run["frames_lost"], "communication_stops": w["communication_stops"],
            "longest_missed_run": w["longest_missed_run"], "states_skipped": d["states_skipped"],
            "robot_s": round(float(log[-1, 0] - log[0, 0]), 1), "wall_s": round(run["wall_s"], 1),
            "realtime_factor": w["realtime_factor"], "loop_hz_wall_p50": round(1e3 / float(np.median(dt_wall)), 1),
            "period_ms_wall_p99": pct(dt_wall, 99), "stop": run["reason"]}


def fr3_rows(maps: dict[int, Path], seconds: float = 60.0, make_control=None, workdir=None) -> list[dict]:
    """One row per taxel count (`maps`: taxels -> taxel map designed on franky-sim's FR3)."""
    rows = []
    for n, path in maps.items():
        with tempfile.TemporaryDirectory(dir=workdir) as tmp:
            rows.append(row(contact_run(path, tmp, seconds, make_control=make_control)))
    return rows


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m skinsafe.core.app.runtime_fr3", description=__doc__.split("\n")[0])
    p.add_argument("maps", nargs="+", help="taxel maps designed on franky-sim's FR3 (see README, The FR3 case)")
    p.add_argument("--seconds", type=float, default=60.0, help="robot time per run, s")
    p.add_argument("--json", action="store_true")
    p.add_argument("--out", help="also write the rows here (JSON)")
    args = p.parse_args(argv)
    maps = {taxel_map.load(m).n_taxels: Path(m) for m in args.maps}
    rows = fr3_rows(maps, args.seconds)
    text = json.dumps(rows, indent=1)
    if args.out:
        atomic_write(args.out, text)
    print(text if args.json else "\n".join(" ".join(f"{k}={v}" for k, v in r.items()) for r in rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
