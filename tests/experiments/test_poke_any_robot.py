"""`skinsafe poke` on a robot's own description (the bundled Franka): a sprung probe gives forces
of about stiffness x depth whatever the arm's effective mass, and the retraction follows eq. 10."""
import json
from pathlib import Path

import numpy as np
import pytest

from skinsafe.core.app.cli import main
from skinsafe.core.app.design import design_robot
from skinsafe.core.experiments.poke import PROBE_STIFFNESS, Poke, force_sweep, pick_taxel, simulate
from skinsafe.core.robot.models import load_robot
from skinsafe.core.safety.retraction import RetractionParams
from skinsafe.core.skin.model import RobotRef
from skinsafe.core.skin.taxel_map import save

pytestmark = pytest.mark.xdist_group("poke-any-robot")  # one worker builds the module's costly fixtures, once

ASSET = Path(__file__).resolve().parents[2] / "blend_assets" / "franka_description"
REF = RobotRef("urdf", "franka", str(ASSET / "robots/panda/panda.urdf.xacro"), (str(ASSET),))


@pytest.fixture(scope="module")
def franka(tmp_path_factory):
    robot = load_robot(REF)
    spec = {"module": {"rows": 3, "cols": 3, "pitch": 0.012}, "bodies": ["panda_link2", "panda_link4"]}
    design = design_robot(robot, REF, spec)[0]
    path = save(design, tmp_path_factory.mktemp("franka") / "skin.json")
    return robot, design, path


def test_franka_pokes_give_physical_forces_and_the_fig12_slope(franka):
    robot, design, _ = franka
    params = RetractionParams(alpha=0.01)
    sweep = force_sweep(design, robot, params, [0.0005, 0.0015], body="panda_link4")
    f, d = np.array(sweep["force"]), np.array(sweep["distance"])
    # a 20 N/mm probe: about stiffness x depth (plus its damper on the way in), not kN
    assert len(f) == 2 and 5.0 < f[0] < f[1] < 60.0
    # eq. 10's alpha / 12 within the retraction's measured tracking: the taxel picked on the buildable skin
    # (normal 52 degrees from up) reaches 85% of its distance; taxels facing sideways reach 99.5-100%
    assert abs(sweep["slope"] - 0.01 / 12) < 0.2 * 0.01 / 12 and d[1] > 2.5 * d[0] > 0
    assert max(sweep["profile_rel_err"]) < 0.2


def test_force_does_not_scale_with_the_arm_effective_mass(franka):
    """Near the shoulder axis (panda_link2) the arm's effective mass is about 1,000 kg; a rigid probe
    driven 1 mm in met 60-140 kN there. Through the spring the peak stays near k x depth."""
    robot, design, _ = franka
    i = pick_taxel(design, robot, "panda_link2")
    params = RetractionParams(alpha=0.01)
    run = simulate(design, robot, [Poke(i, 0.001)], params, 0.3)
    assert 10.0 < run["force"].max() < 3 * PROBE_STIFFNESS * 0.001


def test_poke_cli_on_a_franka_map(franka, tmp_path, capsys):
    _, design, path = franka
    out = tmp_path / "poke"
    assert main(["poke", "--map", str(path), "--out", str(out), "--depths", "0.0006,0.0012", "--epsilons", "1",
                 "--forms-stride", "60"]) == 0
    res = json.loads((out / "poke_results.json").read_text())
    sweep = res["force_sweep"]
    assert sweep["body"] == "panda_link4"  # the link the arm can pull back (a lever), not the shoulder
    assert max(sweep["force"]) < 60.0 and abs(sweep["slope"] - 0.01 / 12) < 0.2 * 0.01 / 12
    assert res["multicontact"][0]["into_contact_mm"] <= 0.5
    assert "slope" in capsys.readouterr().out
