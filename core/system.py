"""Parts of the machine some commands need that pip does not install (a browser, a serial port, franky-sim's
environment). A command that lacks one raises `MissingPart`: `skinsafe` prints its message as one line, exit code 2,
never a traceback. The line always holds `MARKER` (tests/app/test_readme_commands.py skips a documented command on
it). Standard library only: a leaf every layer and `hardware` may import (import-linter: the lowest layer)."""
from __future__ import annotations

import shutil
import sys
from pathlib import Path

MARKER = "missing system part"
SKINSAFE = str(Path(sys.executable).with_name("skinsafe"))  # this environment's `skinsafe` command: benches run the
# product through it as a user does (a black box), never by the name of an app module


class MissingPart(FileNotFoundError):
    """A part of the machine a command needs is not there; the message names it and how to get it."""

    def __init__(self, part: str, how: str):
        super().__init__(f"{MARKER}: {part}; {how}")
        self.part, self.how = part, how


def program(name: str, package: str) -> str:
    """The path of program `name` on PATH, or MissingPart naming the Debian `package` that holds it."""
    path = shutil.which(name)
    if path is None:
        raise MissingPart(f"the program `{name}`", f"install it: `apt-get install -y {package}`")
    return path
