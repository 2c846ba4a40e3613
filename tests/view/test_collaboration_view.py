"""The collaboration experiment in the view: a nominal episode of a result is run again into a record of the
runtime's format, one tick per control period, with the person's parts where the simulator has them at every
tick (they move), the taxel forces from the tick the experiment's trace has the contact, and the same contact
events as the result; the page moves the parts with the timeline. Bad input is named in one line.

The person scenario with the retraction stack (no TDM to learn) on the committed skin, the episode 2.3 s."""
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from skinsafe.core.app.experiment_view import record_collaboration
from skinsafe.core.experiments import collaboration_scenario as co
from skinsafe.core.experiments.collaboration import cell
from skinsafe.core.experiments.collaboration_result import summarise
from skinsafe.core.robot.kinematics import TaxelKinematics
from skinsafe.core.robot.models import build_ur5
from skinsafe.core.runtime.recording import Recording
from skinsafe.core.skin.taxel_map import load

SKIN = Path(__file__).resolve().parents[2] / "results" / "collaboration" / "collaboration_skin.json"
CFG = co.CollabConfig(finish=0.3, samples=300, steps=150)
# one worker builds the module's episode and record once (pytest-xdist: ungrouped tests each rebuild them)
pytestmark = pytest.mark.xdist_group("collaboration-view")


@pytest.fixture(scope="module")
def result(tmp_path_factory):
    """A result of the person scenario with the retraction stack (the experiment's own cell and summary), its
    skin beside it."""
    d = tmp_path_factory.mktemp("collaboration")
    skin = shutil.copy(SKIN, d / "collaboration_skin.json")
    run = cell("t", 0, "person", stacks=["retraction"], config=CFG.to_json(), skin=str(skin), detail=True, **co.NOMINAL)
    (d / "collaboration.json").write_text(json.dumps(summarise([run], [], load(skin), CFG)))
    return d / "collaboration.json"


@pytest.fixture(scope="module")
def simulated(result):
    """The same episode in the experiment's loop: per control tick the parts' body poses and whether the
    retraction is active; the person trace; physics steps per tick."""
    design = load(SKIN)
    lay = co.layout("person", TaxelKinematics(build_ur5().model, design), CFG)
    sc = co.build(lay, design, co.NOMINAL["damping_ratio"], co.NOMINAL["attachment_N_m"], co.NOMINAL["dt_ms"], CFG)
    h, ticks = sc.human, []

    def seen(t, source, force, v, st, cap):
        ticks.append((sc.data.xpos[h.body].copy(), sc.data.xquat[h.body].copy(), st.defensiveness.active))

    run = co.episode(sc, lay, "retraction", None, CFG, on_tick=seen)
    pos, quat, active = (np.array(x) for x in zip(*ticks))
    return pos, quat, active, run["trace"], sc.substeps, sc.control_dt


@pytest.fixture(scope="module")
def recorded(result):
    """`record_collaboration`'s summary and the record it wrote (beside the result)."""
    out = record_collaboration(result, result.with_name("ep.mcap"), "person", "retraction")
    return out, Recording(result.with_name("ep.mcap"))


def test_an_episode_runs_again_into_a_record_with_the_person_moving(result, simulated, recorded):
    pos, quat, active, trace, substeps, dt = simulated
    out, rec = recorded
    doc = json.loads(result.read_text())
    assert out["contacts"] and out["same"] and out["contacts_in_result"] == doc["contacts"]
    n = len(pos)
    assert len(rec.t) == out["ticks"] == n == int(round(2.3 / dt)) and np.allclose(rec.t, dt * np.arange(1, n + 1))
    assert [o["name"] for o in rec.config["obstacles"]] == ["lower_arm", "hand"]
    # the parts' poses: the simulator's at every tick, moving (the hand reaches 0.3 m into the wrist and back)
    assert rec.obstacles.shape == (n, 2, 7) and np.allclose(rec.obstacles[:, :, :3], pos, rtol=0, atol=1e-12)
    k = n // 3
    assert np.allclose(np.abs(np.einsum("pi,pi->p", rec.obstacles[k, :, 3:], quat[k])), 1.0)
    assert np.ptp(rec.obstacles[:, 1, :3], axis=0).max() > 0.2
    h, force = rec.frame(k)
    assert np.array_equal(h["obstacles"], rec.obstacles[k])
    # the contact: the trace's first physics step with a taxel touched by the person is in the first tick with force
    first = int(np.flatnonzero(trace["touched"].any(axis=1))[0]) // substeps
    assert int(np.flatnonzero(rec.peak > 0)[0]) == first and rec.t[first] >= trace["time_s"][first * substeps]
    # the retraction's state on the tick the stack had it, and the contact "next contact" finds
    assert np.array_equal(rec.retracting > 0, active) and active.any()
    t = rec.next_contact(float(rec.t[0]))
    assert t is not None and rec.t[first] <= t


def test_the_page_moves_the_parts_with_the_timeline(recorded):
    from skinsafe.core.runtime.view_page import Page

    rec = recorded[1]
    design = load(rec.config["map"])
    page = Page(design, build_ur5().model, port=0, obstacles=rec.config["obstacles"], q0=rec.q[0])  # any free port
    try:
        for k in (0, len(rec.t) // 3):
            page.show(*rec.frame(k))
            assert np.allclose([o.position for o in page.obstacles], rec.obstacles[k, :, :3])
            assert np.allclose([o.wxyz for o in page.obstacles], rec.obstacles[k, :, 3:])
    finally:
        page.close()


def test_bad_input_is_named_in_one_line(result, tmp_path, capsys):
    from skinsafe.core.app.cli import main

    for args, msg in ((["--scenario", "kitchen"], "--scenario 'kitchen' is unknown; use one of delivery, clamp, person"),
                      (["--stack", "full"], "no person/full run (it has person/retraction); run `skinsafe experiment "
                                            "collaboration --stacks full`")):
        assert main(["view", "--collaboration", str(result), "--scenario", "person", *args]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and msg in err, err
    (tmp_path / "tracking.json").write_text(json.dumps({"config": {}, "runs": {"vanilla": {}}}))
    with pytest.raises(ValueError, match="not a collaboration result"):
        record_collaboration(tmp_path / "tracking.json", tmp_path / "x.mcap")
    shutil.copy(result, tmp_path / "collaboration.json")
    with pytest.raises(ValueError, match="collaboration_skin.json is missing"):
        record_collaboration(tmp_path / "collaboration.json", tmp_path / "x.mcap", "person", "retraction")
    assert not list(tmp_path.glob("*.mcap*"))
