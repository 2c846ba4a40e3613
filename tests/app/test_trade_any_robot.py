"""`skinsafe trade` on a skin designed on the bundled Franka description (points run in-process
here; the Ray fan-out itself is tested on the UR5 in test_trade_sweep)."""
import json
from pathlib import Path

import numpy as np
import pytest

from skinsafe.core.app import trade
from skinsafe.core.app.cli import main

pytestmark = pytest.mark.xdist_group("franka-map")  # the session's Franka skin (tests/app/conftest.franka_map), made once


@pytest.fixture(scope="module")
def skin(franka_map) -> str:
    return str(franka_map)


def test_timestep_and_sensing_knobs_on_the_franka_skin(skin):
    names = ["timestep", "sensing"]
    results = {(n, v): trade._task(n, v, True, skin) for n in names
               for v in trade.KNOBS[n].sweep(True, skin)}
    rows = trade.rows_from_results(results, names, True, skin)
    n = json.loads(Path(skin).read_text())["taxels"]["ids"]
    ts = [r for r in rows if r["knob"] == "timestep"]
    assert all(r["n_taxels"] == len(n) and r["stable"] for r in ts)
    assert 0 <= ts[1]["error"] < ts[2]["error"] < 0.5  # coarser steps, larger force errors
    se = {r["value"]: r for r in rows if r["knob"] == "sensing"}
    assert se["touch"]["error"] == 0 and np.isfinite(se["nearest R=1p"]["error"]) and se["nearest R=1p"]["error"] < 0.5
    forces = results[("sensing", "touch")]["out"]
    assert forces.sum() > 0  # the probes touch the Franka's skin


def test_map_sweeps_use_the_map_pitch_and_refuse_ur5_only_knobs(skin, tmp_path):
    assert trade.KNOBS["density"].sweep(True, skin) == (0.012, 0.018, 0.03)
    assert trade.KNOBS["collision"].sweep(True, skin)[0] == "skin"
    with pytest.raises(ValueError, match="knob 'damping' sweeps the built-in UR5 only"):
        trade.parse_knobs("timestep,damping", skin)
    with pytest.raises(SystemExit, match="damping"):
        main(["trade", "--map", skin, "--knobs", "damping", "--out", str(tmp_path / "t")])
    assert main(["trade", "--map", str(tmp_path / "missing.json"), "--knobs", "timestep",
                 "--out", str(tmp_path / "t")]) == 2
    assert not (tmp_path / "t").exists()


def test_robot_by_catalogue_name_designs_first(tmp_path):
    """`--robot NAME` of a public description designs on that description (its package folders and
    xacro arguments from the catalogue) before sweeping."""
    import argparse

    layout = tmp_path / "layout.json"
    layout.write_text(json.dumps({"module": {"rows": 2, "cols": 2, "pitch": 0.012}, "bodies": ["link3"]}))
    ns = argparse.Namespace(robot="xarm7", package_dir=[], xacro_arg=[], layout=str(layout), out=str(tmp_path / "t"))
    saved = json.loads(Path(trade.design_first(ns)).read_text())
    assert saved["robot"]["path"].endswith("xarm7.urdf") and saved["bodies"] == ["link3"]
