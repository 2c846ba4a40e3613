"""Headless Chromium for the view's measurements and tests: Debian's `chromium` (never a browser download),
driven by playwright; optionally at the lowest priority (software WebGL on a shared machine otherwise
starves the emulated boards' pseudo-terminals)."""
from __future__ import annotations

import shutil
from pathlib import Path

CHROMIUM_ARGS = ["--headless=new", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync"]


def chromium() -> str | None:
    """Debian's chromium, or None."""
    return shutil.which("chromium") or shutil.which("chromium-browser")


def niced(folder: str | Path, exe: str, nice: int = 19) -> str:
    """A launcher in `folder` that runs chromium `exe` at the normal scheduler and `nice` (playwright's
    executable_path): a browser started from a real-time process would inherit its priority."""
    path = Path(folder) / "chromium"
    path.write_text(f'#!/bin/sh\ncommand -v chrt >/dev/null && exec chrt -o 0 nice -n {nice} "{exe}" "$@"\n'
                    f'exec nice -n {nice} "{exe}" "$@"\n')
    path.chmod(0o755)
    return str(path)
