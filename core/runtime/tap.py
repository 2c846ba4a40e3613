"""The newest tick for a live viewer (issue 30's web view): the loop publishes one reference per tick,
a reader takes it whenever it likes; nothing blocks and nothing is copied for a reader that is not there.

Every array in a frame is one the loop made for that tick and never writes again, so a reader may
keep it.
"""
from __future__ import annotations

from skinsafe.core.runtime.tick import Tick


class Tap:
    frame: Tick | None = None

    def publish(self, frame: Tick) -> None:
        self.frame = frame  # one reference store: atomic for any reader thread

    def latest(self) -> Tick | None:
        return self.frame
