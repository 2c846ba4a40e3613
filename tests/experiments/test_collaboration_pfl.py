"""`skinsafe experiment collaboration`: with the skin that covers where the person is met and the
full stack with the PFL cap, every contact is sensed and within ISO/TS 15066 (force and pressure,
the standard's numbers) in the robot-driven scenarios, and the person pushing into the still robot
meets less than without safety, while without safety the limits are exceeded. Run at the sweep's
harshest corner (damping ratio 0.5, attachment 3,000 N/m, where the person's own push reaches its 200 N
limit against a robot that does not give way; a 1 ms step) on the committed skin."""
import json
import shutil
from pathlib import Path

import pytest

from skinsafe.core.experiments.collaboration import cell
from skinsafe.core.experiments.collaboration_result import summarise, tables
from skinsafe.core.experiments.collaboration_scenario import ROBOT_DRIVEN, SCENARIOS, CollabConfig
from skinsafe.core.sim.body_regions import REGIONS

pytestmark = pytest.mark.xdist_group("collaboration-pfl")  # one worker builds the module's costly fixtures, once

SKIN = Path(__file__).resolve().parents[2] / "results" / "collaboration" / "collaboration_skin.json"
CFG = CollabConfig(finish=0.3, samples=300, steps=150)
KEYS = {"stack", "region", "peak_N", "limit_N", "within", "sensed", "sensed_ms", "kind", "peak_pressure_N_cm2",
        "pressure_limit_N_cm2"}
SWEEP_KEYS = {"damping_ratio", "attachment_N_m", "dt_ms", "scenario", "stack", "worst_ratio"}


def _peak(events):
    return max((max(e["peak_N"], e["quasi_static_N"]) for e in events), default=0.0)


@pytest.fixture(scope="module")
def corner():
    return {s: cell(f"test_{s}", 0, s, 0.5, 3000.0, 1.0, ["none", "full+pfl"], CFG.to_json(), str(SKIN)) for s in SCENARIOS}


@pytest.mark.parametrize("scenario", SCENARIOS)
def test_full_pfl_meets_iso_ts_15066_where_no_safety_does_not(corner, scenario):
    none, pfl = (corner[scenario]["stacks"][s]["events"] for s in ("none", "full+pfl"))
    assert none and any(not e["within"] for e in none)  # without safety the limits are exceeded
    assert pfl and all(e["sensed"] for e in pfl)  # every contact with the full stack is on skin
    for e in none + pfl:
        reg = REGIONS[e["region"]]
        quasi = e["kind"] in ("clamp", "quasi_static")
        assert e["limit_N"] == (reg.quasi_static_N if quasi else 2 * reg.quasi_static_N)
        assert e["pressure_limit_N_cm2"] == (reg.pressure_N_cm2 if quasi else 2 * reg.pressure_N_cm2)
        assert e["within"] == (max(e["peak_N"] / e["limit_N"], e["quasi_static_N"] / reg.quasi_static_N,
                                   e["peak_pressure_N_cm2"] / e["pressure_limit_N_cm2"]) <= 1 + 1e-12)
    if scenario in ROBOT_DRIVEN:
        assert all(e["within"] for e in pfl), [(e["region"], e["ratio"]) for e in pfl]
    else:  # the person pushes into the still robot: the stack gives way
        assert _peak(pfl) < 0.95 * _peak(none)
    if scenario == "clamp":  # the fist is pressed against the table: the quasi-static limits from the start
        assert any(e["kind"] == "clamp" and e["region"] == "hand" for e in none + pfl)


def test_result_rows_and_tables(corner):
    """The result file's contract (contact rows, sweep rows) and its Markdown tables."""
    from skinsafe.core.skin.taxel_map import load

    nominal = [dict(r, stacks={k: dict(v, force_N=[], pan_rad=[], no_person_task_time_s=None)
                               for k, v in r["stacks"].items()}) for r in corner.values()]
    res = summarise(nominal, list(corner.values()), load(SKIN), CFG)
    assert res["contacts"] and all(KEYS <= set(e) for e in res["contacts"])
    assert len(res["sweep"]) == 2 * len(SCENARIOS) and all(SWEEP_KEYS <= set(r) for r in res["sweep"])
    for r in res["sweep"]:
        ev = corner[r["scenario"]]["stacks"][r["stack"]]["events"]
        assert r["worst_ratio"] == max((e["ratio"] for e in ev), default=0.0)
    md = tables(res)
    assert md.count("\n| person | 1 |") == 1 and "zeta 0.5, 3000 N/m" in md
    json.dumps(res, allow_nan=False)


def test_command_writes_the_result(tmp_path):
    from skinsafe.core.app.cli import main

    shutil.copy(SKIN, tmp_path / "collaboration_skin.json")
    assert main(["experiment", "collaboration", "--out", str(tmp_path), "--no-sweep", "--stacks", "none",
                 "--samples", "50", "--steps", "10", "--stay", "0.5", "--finish", "0.3", "--workers", "0",
                 "--no-progress"]) == 0
    res = json.loads((tmp_path / "collaboration.json").read_text())
    assert (tmp_path / "collaboration.png").read_bytes()[:4] == b"\x89PNG"
    assert (tmp_path / "collaboration.md").read_text().startswith("| scenario | stack |")
    assert set(res["runs"]) == {f"{s}/none" for s in SCENARIOS} and res["sweep"] == []
    assert res["contacts"] and all(KEYS <= set(e) for e in res["contacts"])


def test_bad_options_are_refused(tmp_path):
    from skinsafe.core.app.cli import main

    for opt, msg in ((["--pfl-factor", "1.5"], "--pfl-factor is 1.5"), (["--pfl-regions", "elbow"], "'elbow' is unknown"),
                     (["--person-speed", "-1"], "--person-speed is -1.0"), (["--sweep-dt", "0"], "--sweep-dt has 0.0"),
                     (["--push", "0"], "--push is 0.0")):
        with pytest.raises(SystemExit, match=msg):
            main(["experiment", "collaboration", "--out", str(tmp_path), *opt])
    assert not list(tmp_path.iterdir())  # nothing written
