"""Headless Chromium for the view's measurements and tests: Debian's `chromium` (never a browser download),
driven by playwright; optionally at the lowest priority (software WebGL on a shared machine otherwise
starves the emulated boards' pseudo-terminals)."""
from __future__ import annotations

import os
import shutil
from pathlib import Path

CHROMIUM_ARGS = ["--headless=new", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync"]


def chromium() -> str | None:
    """Debian's chromium, or None."""
    return shutil.which("chromium") or shutil.which("chromium-browser")


def niced(folder: str | Path, exe: str, nice: int = 19, cpus: set[int] | None = None) -> str:
    """A launcher in `folder` that runs chromium `exe` at the normal scheduler and `nice` (playwright's
    executable_path): a browser started from a real-time process would inherit its priority, and one run as root
    raises its display and IO threads to nice -8 (so root's browser runs without CAP_SYS_NICE, `setpriv`). `cpus`:
    the only cores it may use (taskset; e.g. all but a control loop's)."""
    pin = "setpriv --bounding-set -sys_nice " if os.geteuid() == 0 and shutil.which("setpriv") else ""
    if cpus:
        if shutil.which("taskset") is None:
            raise RuntimeError("no taskset to keep the browser on its cores (`apt-get install -y util-linux`)")
        pin += f"taskset -c {','.join(map(str, sorted(cpus)))} "
    path = Path(folder) / "chromium"
    path.write_text(f'#!/bin/sh\ncommand -v chrt >/dev/null && exec {pin}chrt -o 0 nice -n {nice} "{exe}" "$@"\n'
                    f'exec {pin}nice -n {nice} "{exe}" "$@"\n')
    path.chmod(0o755)
    return str(path)
