"""The clean-Blender test's environments: per tested Blender, a venv holding that bpy and its own dependencies only,
kept under `$SKINSAFE_CACHE` (default `~/.cache/skinsafe`) keyed by the bpy and Python versions. The Blenders are
4.5 LTS and this project's bpy (Python 3.11) and the newest release (Python 3.13, found on PATH or in pyenv).
`make test` builds them beside its other installs (`python tests/addon/bpy_only.py`: two at a time, about a
minute each with the 300-400 MB wheel downloaded, at once when there; prints each one's python)."""
import fcntl
import glob
import os
import shutil
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from importlib.metadata import version
from pathlib import Path

HERE = f"{sys.version_info.major}.{sys.version_info.minor}"


@dataclass(frozen=True)
class Blender:
    bpy: str  # the bpy module's version: the Blender release it is built from
    python: str  # that Blender's Python, "3.11"

    @property
    def name(self) -> str:
        return f"bpy-{self.bpy}-py{self.python.replace('.', '')}"


BLENDERS = (Blender("4.5.15", "3.11"), Blender(version("bpy"), HERE), Blender("5.3.0", "3.13"))


class NoPython(RuntimeError):
    """The Python a Blender needs is not on this machine."""


def base_python(python: str) -> str:
    """An interpreter of that Python version: the running one's base, else `pythonX.Y` on PATH or in pyenv."""
    if python == HERE:
        return getattr(sys, "_base_executable", sys.executable)
    root = os.environ.get("PYENV_ROOT", str(Path.home() / ".pyenv"))
    for exe in [shutil.which(f"python{python}")] + sorted(glob.glob(f"{root}/versions/{python}.*/bin/python{python}")):
        if exe and subprocess.run([exe, "-c", "pass"], capture_output=True).returncode == 0:  # a pyenv shim may refuse
            return exe
    raise NoPython(f"no Python {python} on this machine for the clean-install test's Blender: install one "
                   f"(`pyenv install {python}` or the distribution's python{python} with venv), then `make bpy-only`")


def bpy_only_python(blender: Blender) -> Path:
    """The python of a venv holding that Blender's bpy and its own dependencies only (built when missing)."""
    cache = Path(os.environ.get("SKINSAFE_CACHE", Path.home() / ".cache" / "skinsafe"))
    venv = cache / f"venv-{blender.name}"
    python, ready = venv / "bin" / "python", venv / ".ready"
    cache.mkdir(parents=True, exist_ok=True)
    with open(cache / f"{venv.name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # one builder at a time
        if not (ready.exists() and python.exists()):
            subprocess.run([base_python(blender.python), "-m", "venv", "--clear", str(venv)], check=True)
            subprocess.run([str(python), "-m", "pip", "install", "-q", "--disable-pip-version-check",
                            f"bpy=={blender.bpy}"], check=True)
            ready.write_text(blender.bpy)
    return python


if __name__ == "__main__":
    try:
        with ThreadPoolExecutor(2) as pool:
            print("\n".join(str(p) for p in pool.map(bpy_only_python, BLENDERS)))
    except NoPython as e:
        sys.exit(f"bpy_only: {e}")
