"""`skinsafe emulate`: run board emulators on pseudo-terminals and print their ports (until Ctrl-C)."""
from __future__ import annotations

from skinsafe.hardware.emulator import add_arguments, serve

__all__ = ["add_arguments", "run"]


def run(args) -> int:
    return serve(args)
