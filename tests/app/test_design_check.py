"""`skinsafe design` on a robot's own description and `skinsafe check` refusing bad skins."""
import json
import re
from pathlib import Path

import numpy as np
import pytest

from skinsafe.core.app.cli import main
from skinsafe.core.design.placement import PlacementError, place_module
from skinsafe.core.design.sample import make_sample_design
from skinsafe.core.design.surface import body_surface
from skinsafe.core.robot.models import build_ur5
from skinsafe.core.skin.model import Module
from skinsafe.core.skin.taxel_map import save

pytestmark = pytest.mark.xdist_group("franka-map")  # the session's Franka skin (tests/app/conftest.franka_map), made once

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
    assert re.search(r"taxel 0 on 'panda_link4' is [5-7]\d\d\.\d mm off the link's surface", err)  # 0.7 m along x
    assert "outline overhangs" in err


def test_far_anchor_is_refused_not_snapped():
    ur5 = build_ur5()
    surf = body_surface(ur5.model, "forearm_link")
    m = Module(0, "m", "forearm_link", rows=2, cols=2, pitch=0.01)
    with pytest.raises(PlacementError, match="anchor .* is 2\\d\\d mm from the surface of 'forearm_link'") as e:
        place_module(surf, m, np.array([-0.2, 0.0, 0.3]), np.array([1.0, 0, 0]))
    assert e.value.kind == "far_anchor"


def _mating_robot(tmp_path, overlap: float) -> Path:
    """A box base and a cylinder turning about its own axis on the box's top face, sunk `overlap`
    into it: the top face under the cylinder is covered at every joint angle."""
    path = tmp_path / f"mate_{overlap * 1e6:.0f}um.urdf"
    path.write_text(
        '<robot name="mate"><link name="a"><visual><geometry><box size="0.2 0.2 0.1"/></geometry></visual>'
        '<collision><geometry><box size="0.2 0.2 0.1"/></geometry></collision>'
        '<inertial><mass value="1"/><inertia ixx="0.01" iyy="0.01" izz="0.01" ixy="0" ixz="0" iyz="0"/></inertial></link>'
        '<link name="b"><visual><origin xyz="0 0 0.05"/><geometry><cylinder radius="0.05" length="0.1"/></geometry>'
        '</visual><collision><origin xyz="0 0 0.05"/><geometry><cylinder radius="0.05" length="0.1"/></geometry>'
        '</collision><inertial><mass value="1"/><inertia ixx="0.01" iyy="0.01" izz="0.01" ixy="0" ixz="0" iyz="0"/>'
        f'</inertial></link><joint name="j" type="revolute"><parent link="a"/><child link="b"/><origin xyz="0 0 '
        f'{0.05 - overlap}"/><axis xyz="0 0 1"/><limit lower="-3" upper="3" effort="1" velocity="1"/></joint></robot>')
    return path


@pytest.mark.parametrize("overlap,valid", [(0.0002, False), (0.00005, True)])
def test_check_refuses_taxels_buried_more_than_a_tenth_of_a_millimetre(tmp_path, capsys, overlap, valid):
    """A module on the box's top face under the turning cylinder: 0.2 mm deep is refused (the old
    1 mm tolerance let 0.5 mm through), 0.05 mm (within tessellation) passes."""
    from skinsafe.core.app.design import robot_ref
    from skinsafe.core.design.placement import build_design
    from skinsafe.core.robot.models import load_robot

    out = tmp_path / "skin.json"
    ref = robot_ref(str(_mating_robot(tmp_path, overlap)), [], out)
    robot = load_robot(ref, base_dir=tmp_path)
    m = Module(0, "m", "a", rows=2, cols=2, pitch=0.01, taxel_diameter=0.006, margin=0.001, min_bend_radius=0.01)
    placed = place_module(body_surface(robot.model, "a"), m, np.array([0.0, 0.0, 0.05]), np.array([1.0, 0, 0]))
    assert np.allclose(placed.positions[:, 2], 0.05)
    save(build_design(ref, [placed]), out)
    assert main(["check", str(out)]) == (0 if valid else 1)
    captured = capsys.readouterr()
    if valid:
        assert captured.out.rstrip().endswith("valid") and "refused" not in captured.err
    else:
        assert "4 taxels are buried more than 0.1 mm inside another link at all 16 sampled poses" in captured.err


def test_design_leaves_the_mating_face_bare(tmp_path, capsys):
    """`skinsafe design` on the box drops the modules the cylinder buries: what it writes passes check."""
    out = tmp_path / "skin.json"
    assert main(["design", str(_mating_robot(tmp_path, 0.0005)), "--bodies", "a", "--rows", "2", "--cols", "2",
                 "--pitch", "0.01", "--out", str(out)]) == 0
    raw = json.loads(out.read_text())
    pos = np.array(raw["taxels"]["positions"])
    top = pos[:, 2] > 0.0499
    assert top.any() and not (top & (np.hypot(pos[:, 0], pos[:, 1]) < 0.05)).any()  # none under the cylinder
    assert main(["check", str(out)]) == 0


@pytest.mark.parametrize("argv, message", [
    (["check", "{map}", "--tol", "nan"], "--tol nan: give a finite distance >= 0 in m"),  # NaN once passed every taxel
    (["check", "{map}", "--poses", "-1"], "--poses -1: give 1..10000"),  # was a traceback
    (["replay", "{dir}/none.mcap", "--tol", "nan"], "--tol nan: give a finite difference >= 0"),
    (["view", "{dir}/none.mcap", "--port", "-1"], "--port -1: give 1..65535, or 0 for any free port"),  # hung
    (["view", "{dir}/none.mcap", "--fps", "nan"], "--fps nan: give page updates per second in (0, 1000]"),
])
def test_bad_numbers_are_refused_in_one_line(tmp_path, capsys, argv, message):
    save(make_sample_design("ur5"), tmp_path / "skin.json")
    assert main([a.format(map=tmp_path / "skin.json", dir=tmp_path) for a in argv]) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err, err
