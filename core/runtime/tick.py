"""One control tick as one typed record: what the loop publishes to the tap (the live views), what the
recorder writes (core/runtime/record.py), what an experiment's episode writes (core/runtime/sim_record.py)
and what a record gives back (core/runtime/recording.py). Built by keyword.

Every array in a tick is one its maker made for that tick and never writes again, so a reader may keep it.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(slots=True, kw_only=True)
class Tick:
    t: float  # the robot's clock, s
    q: np.ndarray  # measured joint positions
    command: np.ndarray  # the joint velocity sent (zero on the stop's tick)
    qd: np.ndarray | None = None  # measured joint velocities (None: not known, recorded as zero)
    dt: float = 0.0  # measured on the robot's clock since the last tick, s
    force: np.ndarray | None = None  # taxel forces the layers saw (N)
    force_new: bool = False  # a new reading arrived this tick: the recorder writes `force` only then
    reading_seq: float = 0.0  # the reading's sequence number
    planned: np.ndarray | None = None  # the command source's velocity
    retracting: bool = False
    pool: int = 0  # retracting taxels
    pool_taxels: np.ndarray | None = None  # the retracting taxels, highest priority first
    flags: tuple = ()  # the layers' flags of this tick
    potential: float = 0.0  # the TDM's danger potential f the modulation saw (0 without --tdm)
    speed_factor: float = 1.0  # |command| / |planned|: how much the layers slowed the plan (1: not at all)
    stop: str = ""  # the stop reason once the robot was stopped, else ""
    ticked: bool = True  # False: the stop's tick (the stack not ticked, zero velocity sent)
    board_age_s: dict | None = None  # per board uid: seconds since its last frame
    frames_lost: int = 0
    command_age: float = 0.0  # seconds since the command source's last update
    command_refused: int = 0  # teleop datagrams refused so far (not from the leader, forged, replayed, ...)
    index: int = 0  # the tick's number in the run
    ns: int = 0  # host wall clock, ns (the record's log time)
    obstacles: np.ndarray | None = None  # (P, 7) poses of moving obstacles (None: they stand still)
