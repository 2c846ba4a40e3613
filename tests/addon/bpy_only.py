"""The clean-Blender test's environment: a venv holding bpy (this project's pinned version) and its own
dependencies only, kept under `$SKINSAFE_CACHE` (default `~/.cache/skinsafe`) keyed by the bpy version.
`make test` builds it beside its other installs (`python tests/addon/bpy_only.py` prints its python)."""
import fcntl
import os
import subprocess
import sys
from importlib.metadata import version
from pathlib import Path


def bpy_only_python() -> Path:
    """The python of a venv holding bpy (this project's pinned version) and its own dependencies only."""
    bpy_version = version("bpy")
    cache = Path(os.environ.get("SKINSAFE_CACHE", Path.home() / ".cache" / "skinsafe"))
    venv = cache / f"venv-bpy-{bpy_version}-py{sys.version_info.major}{sys.version_info.minor}"
    python, ready = venv / "bin" / "python", venv / ".ready"
    cache.mkdir(parents=True, exist_ok=True)
    with open(cache / f"{venv.name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # one builder at a time
        if not (ready.exists() and python.exists()):
            base = getattr(sys, "_base_executable", sys.executable)
            subprocess.run([base, "-m", "venv", "--clear", str(venv)], check=True)
            subprocess.run([str(python), "-m", "pip", "install", "-q", "--disable-pip-version-check",
                            f"bpy=={bpy_version}"], check=True)
            ready.write_text(bpy_version)
    return python


if __name__ == "__main__":
    print(bpy_only_python())
