"""`make robots`: the public robot descriptions that are not shipped in this folder, from PyPI.

CI and developers' machines reach only package registries, so descriptions come from a PyPI
package that ships them: `example-robot-data` (BSD-3-Clause, a 131 MB wheel of many robots).
Only the packages named in `PACKAGES` are extracted (about 2 MB) into `example-robot-data/`
beside this file (git-ignored); pip's own cache keeps the wheel, so a second fetch on the same
machine downloads nothing, and a folder already extracted from the same wheel is left as it is.
"""
from __future__ import annotations

import json
import shutil
import subprocess
import sys
import tempfile
import zipfile
from pathlib import Path

WHEEL = "example-robot-data==6.0.0"
PREFIX = "cmeel.prefix/share/example-robot-data/"
PACKAGES = ("robots/xarm_description/",)  # xArm7 (UFactory, xarm_ros2, BSD-3-Clause): 7 DoF, STL mesh links
HERE = Path(__file__).resolve().parent
DEST = HERE / "example-robot-data"
STAMP = DEST / "FETCHED.json"


def fetch(dest: Path = DEST) -> Path:
    """Extract `PACKAGES` of `WHEEL` into `dest` (staged, then renamed: never half-written)."""
    stamp = dest / STAMP.name
    want = {"wheel": WHEEL, "packages": list(PACKAGES)}
    if stamp.is_file() and json.loads(stamp.read_text()) == want:
        return dest
    with tempfile.TemporaryDirectory(dir=dest.parent) as tmp:
        subprocess.run([sys.executable, "-m", "pip", "download", "-q", "--no-deps", "-d", tmp, WHEEL], check=True)
        wheel = next(Path(tmp).glob("*.whl"))
        stage = Path(tmp) / "stage"
        with zipfile.ZipFile(wheel) as z:
            for name in z.namelist():
                rel = name[len(PREFIX):] if name.startswith(PREFIX) else None
                if rel == "package.xml" or (rel and rel.startswith(PACKAGES)):
                    (stage / rel).parent.mkdir(parents=True, exist_ok=True)
                    (stage / rel).write_bytes(z.read(name))
                elif name.endswith(".dist-info/licenses/LICENSE"):
                    stage.mkdir(parents=True, exist_ok=True)
                    (stage / "LICENSE").write_bytes(z.read(name))
        (stage / stamp.name).write_text(json.dumps(want))
        if dest.exists():
            shutil.rmtree(dest)
        stage.rename(dest)
    return dest


if __name__ == "__main__":
    print(f"robots: {fetch()}")
