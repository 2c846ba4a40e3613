"""`skinsafe pfl`: the per-taxel report at a pose and the taxels a fast trajectory drives too fast."""
import json

import numpy as np

from skinsafe.core.app.cli import main
from skinsafe.core.design.sample import make_sample_design
from skinsafe.core.experiments.collaboration_scenario import _delivery
from skinsafe.core.robot.kinematics import TaxelKinematics
from skinsafe.core.robot.models import build_ur5
from skinsafe.core.safety import pfl


def test_pose_and_trajectory_report(tmp_path, capsys):
    t = np.linspace(0, 1.0, 41)
    q = np.array([_delivery(x, 1.0)[0] for x in t])
    np.savetxt(tmp_path / "traj.csv", np.c_[t, q], delimiter=",")
    out = tmp_path / "pfl.json"
    assert main(["pfl", "--sample", "ur5", "--pitch", "0.02", "--trajectory", str(tmp_path / "traj.csv"),
                 "--regions", "hand", "chest", "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert "wrist_3_link" in text and "taxels exceed v_max" in text
    rep = json.loads(out.read_text())
    robot = build_ur5()
    design = make_sample_design("ur5", pitch=0.02, robot=robot)
    kin = TaxelKinematics(robot.model, design)
    m = pfl.effective_mass(kin, robot.home)
    assert np.allclose(rep["effective_mass_kg"], np.where(np.isfinite(m), m, -1), rtol=1e-3)
    assert np.allclose(rep["v_max_m_s"]["chest"], pfl.v_max("chest", 1 / m), rtol=1e-3)
    assert len(rep["trajectory_min_v_max_m_s"]["hand"]) == design.n_taxels
    assert np.all(np.array(rep["trajectory_min_v_max_m_s"]["chest"]) <= np.array(rep["trajectory_min_v_max_m_s"]["hand"]))
    ex = rep["exceeds"]
    assert ex and {e["region"] for e in ex} == {"hand", "chest"}
    # the worst one, checked by hand: its normal speed at that time over its v_max
    e = ex[0]
    i = int(np.flatnonzero(design.taxels.ids == e["taxel"])[0])
    k = int(np.argmin(np.abs(t - e["time_s"])))
    qd = np.gradient(q, t, axis=0)[k]
    J, _, frames = kin.jacobians(q[k])
    vn = frames[i, :, 2] @ J[i, :3] @ qd
    assert np.isclose(vn / pfl.v_max(e["region"], 1 / pfl.effective_mass(kin, q[k])[i]), e["speed_over_v_max"])
    assert e["link"] == design.bodies[design.taxels.body[i]]
    # a slow version of the same path exceeds nothing for the hand
    np.savetxt(tmp_path / "slow.csv", np.c_[t * 10, q], delimiter=",")
    assert main(["pfl", "--sample", "ur5", "--pitch", "0.02", "--trajectory", str(tmp_path / "slow.csv"),
                 "--regions", "hand", "--json", str(out)]) == 0
    assert json.loads(out.read_text())["exceeds"] == []


def test_bad_input_is_a_clear_error(tmp_path, capsys):
    (tmp_path / "bad.csv").write_text("0,1,2\n1,2,3\n")
    assert main(["pfl", "--sample", "ur5", "--trajectory", str(tmp_path / "bad.csv")]) == 2
    assert "give at least 2 rows of t and 6 joint values" in capsys.readouterr().err
    assert main(["pfl", "--sample", "ur5", "--regions", "elbow"]) == 2
    assert "body region 'elbow' is unknown" in capsys.readouterr().err
    assert main(["pfl", "--sample", "ur5", "--q", "0", "1"]) == 2
    assert "has 2 values" in capsys.readouterr().err
    assert main(["pfl", "--sample", "ur5", "--q", "0", "1", "nan", "0", "0", "0"]) == 2
    assert "finite joint values" in capsys.readouterr().err
