"""`skinsafe trade` on a skin designed on the bundled Franka description (points run in-process
here; the Ray fan-out itself is tested on the UR5 in test_trade_sweep)."""
import json
from pathlib import Path

import numpy as np
import pytest

from skinsafe.core.app import trade
from skinsafe.core.app.cli import main

ASSET = Path(__file__).resolve().parents[2] / "blend_assets" / "franka_description"


@pytest.fixture(scope="module")
def franka_map(tmp_path_factory):
    out = tmp_path_factory.mktemp("trade_franka") / "skin.json"
    layout = out.parent / "layout.json"
    layout.write_text(json.dumps({"module": {"rows": 3, "cols": 3, "pitch": 0.012}, "bodies": ["panda_link4"]}))
    assert main(["design", str(ASSET / "robots/panda/panda.urdf.xacro"), "--package-dir", str(ASSET),
                 "--layout", str(layout), "--out", str(out)]) == 0
    return str(out.resolve())


def test_timestep_and_sensing_knobs_on_the_franka_skin(franka_map):
    names = ["timestep", "sensing"]
    results = {(n, v): trade._task(n, v, True, franka_map) for n in names
               for v in trade.KNOBS[n].sweep(True, franka_map)}
    rows = trade.rows_from_results(results, names, True, franka_map)
    n = json.loads(Path(franka_map).read_text())["taxels"]["ids"]
    ts = [r for r in rows if r["knob"] == "timestep"]
    assert all(r["n_taxels"] == len(n) and r["stable"] for r in ts)
    assert 0 <= ts[1]["error"] < ts[2]["error"] < 0.5  # coarser steps, larger force errors
    se = {r["value"]: r for r in rows if r["knob"] == "sensing"}
    assert se["touch"]["error"] == 0 and np.isfinite(se["nearest R=1p"]["error"]) and se["nearest R=1p"]["error"] < 0.5
    forces = results[("sensing", "touch")]["out"]
    assert forces.sum() > 0  # the probes touch the Franka's skin


def test_map_sweeps_use_the_map_pitch_and_refuse_ur5_only_knobs(franka_map, tmp_path):
    assert trade.KNOBS["density"].sweep(True, franka_map) == (0.012, 0.018, 0.03)
    assert trade.KNOBS["collision"].sweep(True, franka_map)[0] == "skin"
    with pytest.raises(ValueError, match="knob 'damping' sweeps the built-in UR5 only"):
        trade.parse_knobs("timestep,damping", franka_map)
    with pytest.raises(SystemExit, match="damping"):
        main(["trade", "--map", franka_map, "--knobs", "damping", "--out", str(tmp_path / "t")])
    assert main(["trade", "--map", str(tmp_path / "missing.json"), "--knobs", "timestep",
                 "--out", str(tmp_path / "t")]) == 2
    assert not (tmp_path / "t").exists()
