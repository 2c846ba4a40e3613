"""The two interfaces the runtime sees the world through (duck-typed; docs/RUNTIME_CONTRACT in the issue).

`RobotDriver`: `core/sim/robot_driver.py` (MuJoCo) and `hardware/franka.py` (FR3 over libfranka).
The driver owns the clock: every period it calls `control(state)` with the newest measured state
and sends the joint velocities returned. `control` returning None, raising `StopRobot(reason)` (or
any exception: its text is the reason), `stop(reason)` from any thread, or a communication fault
(named) ends the motion: zero velocity, then the robot's own stop; `run` returns the reason.
Every fault the driver meets itself goes to `report(kind, message, onset, during_stop)` (kind a
monitor Kind value, onset host time.monotonic()) before it stops, so the runtime's monitor decides
and names the stop (core/runtime/monitor.py); a failure of the stop itself (its ramp, the robot's
stop, the link lost meanwhile) is reported with `during_stop` True. Every command the stop sends (the
zero, a ramp, the hold until the arm rests) goes to `sent(state, command)` with the state it was sent
on: the record holds what was sent, and the arm's state until it rests. A driver that lost the robot's command link
but still reads its states passes them as `sent(state, None)` (nothing sent) while the robot's own stop brings
the arm to rest.

`ReadingsSource`: `hardware/skin_source.py` (boards over serial). `newest()` never waits on I/O.
"""
from __future__ import annotations

from typing import Callable, Protocol

import numpy as np


class StopRobot(Exception):
    """Raised by the control callback: stop the robot; `str(exc)` names why (one line)."""


class RobotState(Protocol):
    t: float  # the robot's clock, s
    q: np.ndarray  # measured joint positions (n,)
    qd: np.ndarray  # measured joint velocities (n,)
    seq: int  # increments with every new robot state


class RobotDriver(Protocol):
    name: str
    joint_names: list[str]
    period_s: float

    def limits(self):
        """The robot's own q_min, q_max, qd_max, qdd_max (and qddd_max, qd_bounds where it has them), (n,) each: a
        `limiter.JointLimits` or a dict with those keys; the runtime validates it once (`JointLimits.of`)."""

    def run(self, control: Callable[[RobotState], np.ndarray | None], report: Callable | None = None,
            sent: Callable | None = None) -> str:
        """Blocks until the motion ends; returns the stop reason (module docstring: `report`, `sent`)."""

    def stop(self, reason: str) -> None:
        """Thread-safe: end the motion (zero velocity, then the robot's stop)."""

    def close(self) -> None:
        ...


class Readings(Protocol):
    t: float  # host time.monotonic() of the newest complete frame
    force: np.ndarray  # (N,) N after tare, taxel order; NaN where no fresh data or disabled by the health policy
    seq: int  # increments when new data arrived
    board_age_s: dict[int, float]  # per board uid: seconds since its last frame
    faults: list[tuple]  # (kind: a monitor.Kind value, source, text, onset monotonic s or None) since the last call
    frames_lost: int


class ReadingsSource(Protocol):
    n_taxels: int
    frame_period_s: float

    def preflight(self, map_hash: bytes, tare_frames: int) -> dict:
        """Refuses (raises naming the board) a board whose deployed map differs; tares; names unhealthy taxels."""

    def start(self) -> None:
        ...

    def newest(self) -> Readings:
        ...

    def close(self) -> None:
        ...
