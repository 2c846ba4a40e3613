"""URDF export: reloaded by MuJoCo, taxel links sit where TaxelKinematics puts the taxels; tactile sensors; errors."""
import dataclasses
import xml.etree.ElementTree as ET

import mujoco
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from skinsafe.core.app.cli import main
from skinsafe.core.design.sample import make_sample_design
from skinsafe.core.robot.kinematics import TaxelKinematics
from skinsafe.core.robot.models import build_ur5
from skinsafe.core.skin import taxel_map
from skinsafe.exporters.urdf import URDF_FILE, export_urdf, rpy_from_matrices


@pytest.fixture(scope="module")
def ur5():
    robot = build_ur5()
    design = make_sample_design("ur5", robot=robot)
    return robot, design


@pytest.fixture(scope="module")
def urdf_path(ur5, tmp_path_factory):
    robot, design = ur5
    return export_urdf(design, robot, tmp_path_factory.mktemp("urdf") / URDF_FILE)


def test_rpy_round_trips_also_at_gimbal_lock():
    R = Rotation.random(200, random_state=1).as_matrix()
    R[:2] = Rotation.from_euler("xyz", [[0.3, np.pi / 2, -1.2], [2.0, -np.pi / 2, 0.7]]).as_matrix()
    back = Rotation.from_euler("xyz", rpy_from_matrices(R)).as_matrix()  # scipy "xyz" = URDF Rz Ry Rx
    np.testing.assert_allclose(back, R, atol=1e-14)


def test_taxel_links_in_mujoco_match_taxel_kinematics(ur5, urdf_path):
    robot, design = ur5
    model = mujoco.MjModel.from_xml_path(str(urdf_path))
    data = mujoco.MjData(model)
    t = design.taxels
    bodies = np.array([mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, f"taxel_{int(i)}") for i in t.ids])
    assert (bodies > 0).all()
    assert [model.body(model.body_parentid[b]).name for b in bodies] == [design.body_of(i) for i in range(len(t))]
    assert model.njnt == robot.model.njnt
    # joints by name: the URDF model may order them differently
    qadr = [(robot.model.jnt_qposadr[j], model.joint(robot.model.joint(j).name).qposadr[0])
            for j in range(robot.model.njnt)]
    kin = TaxelKinematics(robot.model, design)
    rng = np.random.default_rng(7)
    for _ in range(3):
        q = rng.uniform(-np.pi, np.pi, robot.model.nq)
        for src, dst in qadr:
            data.qpos[dst] = q[src]
        mujoco.mj_kinematics(model, data)
        pos, frames = kin.poses(q)
        np.testing.assert_allclose(data.xpos[bodies], pos, rtol=0, atol=1e-9)
        np.testing.assert_allclose(data.xmat[bodies].reshape(-1, 3, 3), frames, rtol=0, atol=1e-9)


def test_tactile_sensors_list_every_taxel_once(ur5, urdf_path):
    robot, design = ur5
    t = design.taxels
    board_name = {b.id: b.name for b in design.boards}
    by_channel = {(board_name[int(t.board[i])], int(t.channel[i])): i for i in range(len(t))}
    sensors = ET.parse(urdf_path).getroot().findall("sensor")
    assert len(sensors) == len(design.modules)
    seen = []
    for s in sensors:
        assert float(s.get("update_rate")) > 0
        parent = s.find("parent").get("link")
        for tactile in s.findall("tactile"):
            for tx in tactile.findall("taxel"):
                i = by_channel[(tactile.get("channel"), int(tx.get("idx")))]
                seen.append(int(t.ids[i]))
                assert design.body_of(i) == parent
                np.testing.assert_allclose([float(v) for v in tx.get("xyz").split()], t.positions[i], rtol=0, atol=0)
                R = Rotation.from_euler("xyz", [float(v) for v in tx.get("rpy").split()]).as_matrix()
                np.testing.assert_allclose(R, t.frames[i], atol=1e-12)
                assert tx.find("geometry/box") is not None
    assert len(seen) == len(t)
    assert sorted(seen) == sorted(t.ids.tolist())


def test_body_missing_from_robot_is_named_and_nothing_written(ur5, tmp_path):
    robot, design = ur5
    bad = dataclasses.replace(design, bodies=["no_such_link"] + design.bodies[1:])
    with pytest.raises(ValueError, match="no_such_link"):
        export_urdf(bad, robot, tmp_path / URDF_FILE)
    assert not any(tmp_path.iterdir())


def test_cli_export_urdf(ur5, tmp_path, capsys):
    robot, design = ur5
    map_path = taxel_map.save(design, tmp_path / "map.json")
    out = tmp_path / "out"
    assert main(["export", str(map_path), str(out), "--urdf"]) == 0
    assert URDF_FILE in capsys.readouterr().out
    model = mujoco.MjModel.from_xml_path(str(out / URDF_FILE))
    assert model.nbody == robot.model.nbody + design.n_taxels
    assert (out / "scene.xml").exists()
