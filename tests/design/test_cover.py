"""Coverage fill (`cover_design`): every arm link of the UR5 and the Panda covered at >= 60% of its
open surface, no two modules overlapping (on one link or across links), no taxel buried or
enclosed, and the skin passes `skinsafe check`; links that coincide share one skin."""
import json

import mujoco
import numpy as np
import pytest
from scipy.spatial import cKDTree

from skinsafe.core.app.cli import main
from skinsafe.core.design.audit import audit, buried_taxels, enclosed_taxels, module_strains
from skinsafe.core.design.cover import COVER_MODULE, cover_design, cover_report, trimmed
from skinsafe.core.design.coverage import body_area
from skinsafe.core.design.surface import surface_bodies
from skinsafe.core.robot.models import build_panda, build_ur5, load_robot
from skinsafe.core.skin.model import RobotRef


def _world(design, model, home):
    data = mujoco.MjData(model)
    data.qpos[:] = home
    mujoco.mj_kinematics(model, data)
    bid = np.array([model.body(b).id for b in design.bodies])[design.taxels.body]
    R = data.xmat[bid].reshape(-1, 3, 3)
    return (np.einsum("nij,nj->ni", R, design.taxels.positions) + data.xpos[bid],
            np.einsum("nij,nj->ni", R, design.taxels.frames[:, :, 2]))


def _overlapping_pairs(design, pos, nrm, limit):
    """Pairs of taxels of different modules, facing the same way (within 60 degrees), closer than `limit`."""
    pairs = cKDTree(pos).query_pairs(limit, output_type="ndarray")
    a, b = pairs[:, 0], pairs[:, 1]
    return pairs[(design.taxels.module[a] != design.taxels.module[b]) & (np.sum(nrm[a] * nrm[b], axis=1) > 0.5)]


@pytest.mark.parametrize("name,build", [("ur5", build_ur5), ("panda", build_panda)])
def test_every_arm_link_covered_without_overlap_or_buried_taxels(name, build):
    robot = build()
    design, refused = cover_design(robot, RobotRef("builtin", name))
    arm = surface_bodies(robot.model, moving=True)
    assert design.bodies == arm  # every arm link carries skin
    report = cover_report(design, robot.model, robot.home)
    t = design.taxels
    for i, link in enumerate(arm):
        r = report[link]
        assert r["covered"] >= 0.6, (link, r)
        assert r["overlaps"] == 0 and r["buried"] == 0
        # the covered share is the cells' union (never more than pitch^2 per taxel) over the link's open area
        n = int((t.body == i).sum())
        assert r["covered_of_link"] <= 1.03 * n * 0.01 ** 2 / body_area(robot.model, link)
        assert r["covered"] <= min(1.0, 1.03 * r["covered_of_link"] / r["exposed"])  # of the exposed part only
    # checked here directly: no two modules' cells overlap (3/4 pitch), on one link or across links at home
    pos, nrm = _world(design, robot.model, robot.home)
    assert len(_overlapping_pairs(design, pos, nrm, 0.75 * 0.01 - 1e-9)) == 0
    assert len(_overlapping_pairs(design, pos, nrm, 1.01 * 0.01)) > design.n_taxels / 4  # yet modules do abut
    # whole modules first, then trimmed ones only
    sizes = [(m.rows, m.cols) for m in design.modules]
    assert set(sizes) <= {(m.rows, m.cols) for m in trimmed(COVER_MODULE)}
    assert sizes.count((3, 3)) > len(sizes) / 2
    assert not buried_taxels(design, robot.model, robot.home, poses=1).any()
    assert not enclosed_taxels(design, robot.model, robot.home).any()
    assert audit(design, robot.model, robot.home, poses=4) == []
    strains = module_strains(design)  # every module buildable: within its FPC's 1% in-plane strain
    assert all(v is not None for v in strains.values()) and max(v[0] for v in strains.values()) <= 0.01
    assert sum(r["strain"] for r in refused.values()) > 0  # the doubly curved ends refused stretched grids


def test_coincident_links_share_one_skin(tmp_path):
    """Two identical boxes at the same place (the second on a joint at its origin): the fill skins
    the first and leaves the second bare instead of laying a second skin over the first."""
    box = '<geometry><box size="0.1 0.1 0.1"/></geometry>'
    inertial = '<inertial><mass value="1"/><inertia ixx="0.01" iyy="0.01" izz="0.01" ixy="0" ixz="0" iyz="0"/></inertial>'
    path = tmp_path / "twin.urdf"
    path.write_text(
        f'<robot name="twin"><link name="base"/><link name="a"><visual>{box}</visual><collision>{box}</collision>'
        f'{inertial}</link><link name="b"><visual>{box}</visual>{inertial}</link>'
        '<joint name="ja" type="revolute"><parent link="base"/><child link="a"/><axis xyz="0 0 1"/>'
        '<limit lower="-1" upper="1" effort="1" velocity="1"/></joint>'
        '<joint name="jb" type="revolute"><parent link="a"/><child link="b"/><axis xyz="0 0 1"/>'
        '<limit lower="-1" upper="1" effort="1" velocity="1"/></joint></robot>')
    ref = RobotRef("urdf", "twin", str(path))
    robot = load_robot(ref)
    alone, _ = cover_design(robot, ref, ["a"])
    both, refused = cover_design(robot, ref, ["a", "b"])
    assert both.bodies == ["a"] and both.n_taxels == alone.n_taxels
    assert refused["b"]["overlap"] > 0  # b was tried and every try met a's skin
    report = cover_report(both, robot.model, robot.home)["a"]
    assert report["covered"] >= 0.6 and report["overlaps"] == 0
    # each face of the box: 10 cm square; 3x3 modules of 1 cm cells fill it with at most the border
    faces = np.round(both.taxels.frames[:, :, 2]).astype(int)
    per_face = np.unique(faces, axis=0, return_counts=True)[1]
    assert len(per_face) == 6 and per_face.min() >= 49


def test_cover_from_the_command_line_and_the_layout_spec(tmp_path, capsys):
    out = tmp_path / "skin.json"
    assert main(["design", "ur5", "--cover", "wrist_3_link", "--module", "2x2", "--pitch", "0.008",
                 "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "wrist_3_link" in printed and "overlaps" in printed and "buried" in printed
    raw = json.loads(out.read_text())
    assert raw["bodies"] == ["wrist_3_link"]
    assert {(m["rows"], m["cols"]) for m in raw["modules"]} <= {(2, 2), (1, 2)}
    assert {m["pitch"] for m in raw["modules"]} == {0.008}
    assert main(["check", str(out)]) == 0
    spec = tmp_path / "layout.json"
    spec.write_text(json.dumps({"module": {"rows": 2, "cols": 2, "pitch": 0.008}, "cover": ["wrist_3_link"]}))
    again = tmp_path / "again.json"
    assert main(["design", "ur5", "--layout", str(spec), "--out", str(again)]) == 0
    assert json.loads(again.read_text())["taxels"] == raw["taxels"]
    capsys.readouterr()
    assert main(["design", "ur5", "--cover", "wrist_3_link", "--module", "3by3", "--out", str(out)]) == 2
    assert "--module '3by3' is not RxC (e.g. 3x3), rect or strip" in capsys.readouterr().err
    assert main(["design", "ur5", "--cover", "elbow", "--out", str(out)]) == 2
    assert "body 'elbow' is not in robot ur5" in capsys.readouterr().err
