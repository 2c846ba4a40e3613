"""The poke scenario in MuJoCo (exported UR5 skin, vectorised readout) and the CLI's outputs."""
import json

import numpy as np

from skinsafe.core.app.cli import main
from skinsafe.core.design.sample import make_sample_design
from skinsafe.core.experiments.poke import (
    Poke,
    compare_forms,
    force_sweep,
    multicontact,
    pick_taxel,
    poke_scene,
    simulate,
)
from skinsafe.core.robot.models import build_ur5
from skinsafe.core.safety.retraction import RetractionParams


def test_heavier_poke_retracts_further_linearly():
    robot = build_ur5()
    design = make_sample_design("ur5", robot=robot)
    params = RetractionParams(alpha=0.01)
    sweep = force_sweep(design, robot, params, [0.0005, 0.0015])
    f, d = np.array(sweep["force"]), np.array(sweep["distance"])
    assert len(f) == 2 and 60.0 > f[1] > f[0] > 2.0 and d[1] > d[0] > 0  # a 20 N/mm probe, not a rigid one
    assert np.allclose(d, 0.01 * f / 12, rtol=0.02)  # eq. 10: alpha f / 12
    assert abs(sweep["slope"] - 0.01 / 12) < 0.02 * 0.01 / 12
    assert max(sweep["profile_rel_err"]) < 0.15
    rows = multicontact(design, robot, params, ["forearm_link", "upper_arm_link"], [30.0, 20.0], [1.0])
    assert [r["merge"] for r in rows] == ["qp", "joint", "paper"]
    assert all(r["dominant_fraction"] > 0.5 and min(r["others_fraction"]) > 0.3 for r in rows)
    assert rows[0]["into_contact_mm"] <= 0.5  # the prioritised QP never carries a taxel into its contact
    forms = compare_forms(design, robot, params, stride=200)
    assert forms["3d"]["achieved_median"] > 0.95 > 0.5 > forms["6d"]["achieved_median"]


def test_pokes_of_other_depths_share_one_scene_and_give_the_same_run():
    """force_sweep builds the probe's scene once for all its depths: a run in it repeats a run in its own scene
    exactly (a depth only drives the probe), and a deeper poke pushes harder."""
    robot = build_ur5()
    design = make_sample_design("ur5", robot=robot)
    params = RetractionParams(alpha=0.01)
    i = pick_taxel(design, robot, "forearm_link")
    shared = poke_scene(design, robot, [Poke(i, 0.0)])
    runs = {}
    for depth in (0.0005, 0.0015):
        alone = simulate(design, robot, [Poke(i, depth)], params, 0.3)
        runs[depth] = simulate(design, robot, [Poke(i, depth)], params, 0.3, scene=shared)
        for key in ("t", "q", "force"):
            np.testing.assert_array_equal(runs[depth][key], alone[key])
    assert runs[0.0015]["force"].max() > 2 * runs[0.0005]["force"].max() > 0


def test_poke_cli_writes_plots_and_numbers(tmp_path, capsys):
    out = tmp_path / "poke"
    assert main(["poke", "--out", str(out), "--depths", "0.0006,0.0012", "--epsilons", "1",
                 "--forms-stride", "400"]) == 0
    for name in ("poke_force_distance.png", "poke_displacement.png", "poke_multicontact.png"):
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    res = json.loads((out / "poke_results.json").read_text())
    assert res["force_sweep"]["r2"] > 0.99 and len(res["multicontact"]) == 6
    assert "slope" in capsys.readouterr().out
