"""`skinsafe design` on a robot's own description and `skinsafe check` refusing bad skins."""
import json
from pathlib import Path

import numpy as np
import pytest

from skinsafe.core.app.cli import main
from skinsafe.core.design.placement import PlacementError, place_module
from skinsafe.core.design.surface import body_surface
from skinsafe.core.robot.models import build_ur5
from skinsafe.core.skin.model import Module

ASSET = Path(__file__).resolve().parents[2] / "blend_assets" / "franka_description"


def test_design_on_a_urdf_and_check_passes(franka_map, capsys):
    raw = json.loads(franka_map.read_text())
    assert raw["robot"]["kind"] == "urdf" and raw["bodies"] == ["panda_link4"]
    assert len(raw["modules"]) >= 3 and all(m["rows"] == 3 for m in raw["modules"])
    assert main(["check", str(franka_map)]) == 0
    assert "valid" in capsys.readouterr().out


def test_check_refuses_a_taxel_off_its_link_and_an_overhang(franka_map, tmp_path, capsys):
    raw = json.loads(franka_map.read_text())
    raw["robot"]["path"] = str((franka_map.parent / raw["robot"]["path"]).resolve())
    raw["robot"]["package_dirs"] = [str(ASSET)]
    raw["taxels"]["positions"][0][0] += 0.7  # 0.7 m off the link
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(raw))
    assert main(["check", str(bad)]) == 1
    err = capsys.readouterr().err
    assert "taxel 0 on 'panda_link4' is 6" in err and "mm off the link's surface" in err
    assert "outline overhangs" in err


def test_far_anchor_is_refused_not_snapped():
    ur5 = build_ur5()
    surf = body_surface(ur5.model, "forearm_link")
    m = Module(0, "m", "forearm_link", rows=2, cols=2, pitch=0.01)
    with pytest.raises(PlacementError, match="anchor .* is 2\\d\\d mm from the surface of 'forearm_link'") as e:
        place_module(surf, m, np.array([-0.2, 0.0, 0.3]), np.array([1.0, 0, 0]))
    assert e.value.kind == "far_anchor"
