"""The tracking experiment in the view: an episode of a result is run again into a record of the runtime's
format (core/runtime/sim_record.py) with the same contact ticks as the result says, which the view's reader
opens (ticks, taxel forces, the balls as obstacles, "next contact" on the first tick over the threshold) and
a replay refuses in one line."""
import json
from dataclasses import asdict, replace

import numpy as np
import pytest

from skinsafe.core.app.experiment_view import record_tracking
from skinsafe.core.experiments.tracking_runs import RunConfig, run_method
from skinsafe.core.runtime.recording import Recording
from skinsafe.core.runtime.replay import ReplayError, replay

# one worker runs the module's tracking episode once (pytest-xdist: ungrouped tests each run it again)
pytestmark = pytest.mark.xdist_group("tracking-view")


@pytest.fixture(scope="module")
def result(tmp_path_factory):
    """A vanilla tracking result: one 3 s episode on the coarse skin (the experiment's own code)."""
    config = json.loads(json.dumps(asdict(replace(RunConfig.quick(), episodes=1, duration=3.0))))
    r = run_method("vanilla", 0, config)
    path = tmp_path_factory.mktemp("tracking") / "tracking.json"
    path.write_text(json.dumps({"config": config, "runs": {"vanilla": {"0": r["rows"]}}, "balls": {"0": r["balls"]}}))
    return path, r


def test_an_episode_runs_again_into_a_record_the_view_opens(result, tmp_path):
    path, r = result
    out = record_tracking(path, tmp_path / "ep.mcap")
    assert out["contacts"] == out["contacts_in_result"] == r["rows"][0]["contacts"] > 0
    rec = Recording(tmp_path / "ep.mcap")
    assert len(rec.t) == out["ticks"] == 150 and np.allclose(np.diff(rec.t), 0.02)
    assert rec.forces.shape == (150, r["n_taxels"])
    assert np.allclose([b["pos"] for b in rec.config["obstacles"]], r["balls"])
    over = rec.peak > rec.config["threshold_N"]
    assert over.any()
    t = rec.next_contact(float(rec.t[0]))
    first = int(np.argmax(over))
    assert t is not None and rec.t[first] <= t and over[rec.index(t)]  # the peak of the first contact
    h, force = rec.frame(rec.index(t))
    assert h["speed_factor"] > 0 and np.nanmax(force) == pytest.approx(rec.peak[rec.index(t)])
    with pytest.raises(ReplayError, match="experiment"):
        replay(tmp_path / "ep.mcap", None)


def test_a_method_or_episode_the_result_lacks_is_named(result, tmp_path):
    path, _ = result
    with pytest.raises(ValueError, match="no tdm run with seed 0; it has vanilla seeds"):
        record_tracking(path, tmp_path / "x.mcap", "tdm")
    with pytest.raises(ValueError, match="episodes 0..0, not 3"):
        record_tracking(path, tmp_path / "x.mcap", episode=3)
