"""A skin designed on the bundled Franka description (3x3 modules on link 4), made once per session."""
import json
from pathlib import Path

import pytest

from skinsafe.core.app.cli import main

ASSET = Path(__file__).resolve().parents[2] / "blend_assets" / "franka_description"


@pytest.fixture(scope="session")
def franka_map(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("franka") / "skin.json"
    spec = out.parent / "layout.json"
    spec.write_text(json.dumps({"module": {"rows": 3, "cols": 3, "pitch": 0.012}, "bodies": ["panda_link4"]}))
    rc = main(["design", str(ASSET / "robots/panda/panda.urdf.xacro"), "--package-dir", str(ASSET),
               "--layout", str(spec), "--out", str(out)])
    assert rc == 0
    return out.resolve()
