"""The faults a run injects (tests and `skinsafe bench runtime --faults`), as one typed plan handed to the parts that can
fail: the seam is an argument of each part, never a function rebound at run time.

`skinsafe run --inject FAULT@S[:BOARD]` builds it (core/app/run.py). Each part asks `due(kind)` where the fault would
arise, from S s after the hand-over (`start`); the first time it is due is its onset (host time.monotonic(), kept in
`onsets`): the layers' command non-finite (`stack-nan`: SafetyStack), the retraction's QP solve failed at the next
retraction tick (`stack-qp-fail`: DefensivenessLayer), a NaN reading on the first taxel not excluded in every frame
read from then on (`reading-nan`: the readings source, onset the frame's read time), the command source's plan
non-finite (`command-nan`: the loop's command source). The boards' links (hardware/link_faults.py), the reader's
process (signals) and the sim's robot (SimFaults, on its own clock) take theirs from the same plan in core/app.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass

IN_PARTS = ("stack-nan", "stack-qp-fail", "reading-nan", "command-nan")  # asked for by the parts themselves


@dataclass(frozen=True)
class Injection:
    kind: str
    at: float  # s after the hand-over (the sim's faults: on its clock)
    board: int | None = None  # a link fault's board id (None: the first)

    def __post_init__(self):
        if not (isinstance(self.at, float | int) and math.isfinite(self.at) and self.at >= 0):
            raise ValueError(f"--inject {self.kind}@{self.at}: give a time >= 0 s")


class FaultPlan:
    """The run's injections (module docstring); `onsets`: kind -> host time it first took effect."""

    def __init__(self, injections: tuple[Injection, ...] = ()):
        self.injections = tuple(injections)
        self._at = {i.kind: float(i.at) for i in self.injections}
        self._t0: float | None = None
        self.onsets: dict[str, float] = {}

    def __contains__(self, kind: str) -> bool:
        return kind in self._at

    def start(self, now: float | None = None) -> None:
        """The robot is handed over: the times count from now."""
        self._t0 = time.monotonic() if now is None else now

    def due(self, kind: str, now: float | None = None) -> bool:
        """Has `kind`'s time come (at `now`, default the host's clock)? The first time it has is its onset."""
        at = self._at.get(kind)
        if at is None or self._t0 is None:
            return False
        now = time.monotonic() if now is None else now
        if now < self._t0 + at:
            return False
        self.onsets.setdefault(kind, now)
        return True
