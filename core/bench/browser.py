"""Headless Chromium for the view's measurements and tests: Debian's `chromium` (never a browser download),
driven by playwright; optionally at the lowest priority (software WebGL on a shared machine otherwise
starves the emulated boards' pseudo-terminals)."""
from __future__ import annotations

import importlib.util
import os
import shutil
from pathlib import Path

from skinsafe.core.system import MissingPart, program

CHROMIUM_ARGS = ["--headless=new", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync"]
ENV = "SKINSAFE_CHROMIUM"  # a Chromium elsewhere than on PATH (set to a missing path: none)


def chromium() -> str | None:
    """$SKINSAFE_CHROMIUM where set (None if nothing runs there), else Debian's chromium on PATH, or None."""
    if ENV in os.environ:
        exe = os.environ[ENV]
        return exe if os.path.isfile(exe) and os.access(exe, os.X_OK) else None
    return shutil.which("chromium") or shutil.which("chromium-browser")


def require_chromium(what: str) -> str:
    """chromium() and playwright to drive it, for `what` (a command), or MissingPart naming the one that is not here."""
    exe = chromium()
    if exe is None:
        where = f"${ENV}={os.environ[ENV]} is not an executable" if ENV in os.environ else "not on PATH"
        raise MissingPart(f"chromium for {what} ({where})", "install it: `apt-get install -y chromium`")
    if importlib.util.find_spec("playwright") is None:
        raise MissingPart(f"playwright for {what}", "install it: `pip install playwright==1.65.2` (skinsafe[test])")
    return exe


def niced(folder: str | Path, exe: str, nice: int = 19, cpus: set[int] | None = None) -> str:
    """A launcher in `folder` that runs chromium `exe` at the normal scheduler and `nice` (playwright's
    executable_path): a browser started from a real-time process would inherit its priority, and one run as root
    raises its display and IO threads to nice -8 (so root's browser runs without CAP_SYS_NICE, `setpriv`). `cpus`:
    the only cores it may use (taskset; e.g. all but a control loop's)."""
    pin = "setpriv --bounding-set -sys_nice " if os.geteuid() == 0 and shutil.which("setpriv") else ""
    if cpus:
        pin += f"{program('taskset', 'util-linux')} -c {','.join(map(str, sorted(cpus)))} "
    path = Path(folder) / "chromium"
    path.write_text(f'#!/bin/sh\ncommand -v chrt >/dev/null && exec {pin}chrt -o 0 nice -n {nice} "{exe}" "$@"\n'
                    f'exec {pin}nice -n {nice} "{exe}" "$@"\n')
    path.chmod(0o755)
    return str(path)
