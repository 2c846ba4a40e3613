"""The newest tick for a live viewer (issue 30's web view): the loop publishes one reference per tick,
a reader takes it whenever it likes; nothing blocks and nothing is copied for a reader that is not there.

Every array in a frame is one the loop made for that tick and never writes again, so a reader may
keep it.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np


class Frame(NamedTuple):
    t: float  # the robot's clock, s
    q: np.ndarray  # measured joint positions
    force: np.ndarray  # taxel forces the layers saw (N)
    command: np.ndarray  # joint velocity sent
    retracting: bool
    pool: int  # retracting taxels
    flags: tuple  # the layers' flags of this tick
    stop: str  # the stop reason once the robot was stopped, else ""
    planned: np.ndarray | None = None  # the command source's velocity
    pool_taxels: np.ndarray | None = None  # the retracting taxels, highest priority first
    potential: float = 0.0  # the TDM's danger potential f the modulation saw (0 without --tdm)
    speed_factor: float = 1.0  # |command| / |planned|: how much the layers slowed the plan (1: not at all)
    board_age_s: dict | None = None  # per board uid: seconds since its last frame
    frames_lost: int = 0


class Tap:
    frame: Frame | None = None

    def publish(self, frame: Frame) -> None:
        self.frame = frame  # one reference store: atomic for any reader thread

    def latest(self) -> Frame | None:
        return self.frame
