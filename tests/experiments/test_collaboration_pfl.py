"""`skinsafe experiment collaboration`: contact events with the person against ISO/TS 15066, per stack."""
import argparse
import json

from skinsafe.core.experiments import scenes as es
from skinsafe.core.experiments.collaboration import STACKS, contact_events


def test_collaboration_within_limits_with_pfl(tmp_path):
    args = argparse.Namespace(command_name="collaboration", out=str(tmp_path), pitch=0.02, duration=None, gap=0.1,
                              samples=400, steps=200, tangent_gain=0.0, seed=0, no_progress=True, stay=1.0, source="planner",
                              attach=1500.0,
                              finish=2.5, presence=0.5, pfl_regions=None, pfl_factor=0.8)
    assert es.run(args) == 0
    res = json.loads((tmp_path / "collaboration.json").read_text())
    assert (tmp_path / "collaboration.png").read_bytes()[:4] == b"\x89PNG"
    keys = {"stack", "region", "peak_N", "limit_N", "quasi_static_N", "quasi_static_limit_N", "within"}
    assert res["contacts"] and all(keys <= set(e) for e in res["contacts"])
    by = {s: [e for e in res["contacts"] if e["stack"] == s] for s in STACKS}
    assert by["full+pfl"] and all(e["within"] for e in by["full+pfl"])
    assert any(not e["within"] for e in by["none"])  # without safety the fast delivery hurts
    assert max(e["peak_N"] for e in by["full+pfl"]) < max(e["peak_N"] for e in by["none"])
    for e in res["contacts"]:
        assert e["within"] == (e["peak_N"] <= e["limit_N"] and e["quasi_static_N"] <= e["quasi_static_limit_N"])
    run = res["runs"]["full+pfl"]
    assert run["task_time_s"] is not None and run["task_time_s"] > res["person_out_s"]  # completed after the person left
    assert run["safety_cost_s"] > 0


def test_contact_events_split_transient_and_quasi_static():
    import numpy as np

    f = np.zeros((300, 2))
    f[10:15, 0] = [50, 400, 200, 100, 50]  # a 50 ms impact on the lower arm: transient only
    f[100:200, 1] = 100.0  # 1 s on the hand: quasi-static after 0.5 s
    f[150, 1] = 0.0  # a short gap does not split it
    ev = contact_events(f, ["lower_arm", "hand"], 0.01)
    assert [(e["region"], e["start_s"]) for e in ev] == [("lower_arm", 0.1), ("hand", 1.0)]
    assert ev[0]["peak_N"] == 400 and ev[0]["quasi_static_N"] == 0 and not ev[0]["within"]  # 400 > 320
    assert ev[1]["duration_s"] == 1.0 and ev[1]["quasi_static_N"] == 100 and ev[1]["within"]


def test_bad_options_are_refused(tmp_path):
    import pytest

    from skinsafe.core.app.cli import main

    for opt, msg in ((["--pfl-factor", "1.5"], "--pfl-factor is 1.5"), (["--pfl-regions", "elbow"], "'elbow' is unknown"),
                     (["--attach", "-1"], "--attach is -1.0")):
        with pytest.raises(SystemExit, match=msg):
            main(["experiment", "collaboration", "--out", str(tmp_path), *opt])
    assert not list(tmp_path.iterdir())  # nothing written
