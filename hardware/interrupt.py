"""Ctrl-C and SIGTERM for operator commands: the signal handler only sets a plain attribute.

A handler runs in the main thread between two bytecodes, possibly while that thread holds a lock
(`threading.Event.set` inside a handler can deadlock on the event's own condition lock), so it
takes none. Worker threads poll `requested` between requests; the command then reports every
board and exits with `exit_code` (130 for SIGINT, 143 for SIGTERM).
"""
from __future__ import annotations

import signal
import sys
import threading
from pathlib import Path

SIGNALS = (signal.SIGINT, signal.SIGTERM)


class Interrupt:
    """Catches SIGINT and SIGTERM while entered (main thread only); `requested` once one arrived.

    With `restore=False` the handlers stay until the process ends, so a signal arriving after the
    report was printed (while the interpreter shuts down) cannot end in a traceback either.
    """

    def __init__(self, restore: bool = True):
        self.signum: int | None = None
        self.restore = restore
        self._old: dict = {}

    @property
    def requested(self) -> bool:
        return self.signum is not None

    @property
    def exit_code(self) -> int:
        return 128 + int(self.signum or 0)

    @property
    def name(self) -> str:
        return signal.Signals(self.signum).name if self.signum else ""

    def _handler(self, signum, _frame) -> None:
        if self.signum is None:
            self.signum = signum

    def __enter__(self) -> "Interrupt":
        if threading.current_thread() is threading.main_thread():
            self._old = {s: signal.signal(s, self._handler) for s in SIGNALS}
        return self

    def __exit__(self, *exc) -> None:
        for s, h in self._old.items() if self.restore else ():
            signal.signal(s, h)
        self._old = {}


def for_command() -> Interrupt:
    """The Interrupt of an operator command: kept to the end when this process is the `skinsafe` command,
    restored when the command runs inside another program (tests, the demo)."""
    return Interrupt(restore=Path(sys.argv[0]).name != "skinsafe")
