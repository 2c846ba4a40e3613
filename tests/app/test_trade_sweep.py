"""`skinsafe trade`: the Pareto front, the rows, and the quick sweep through a real local Ray."""
import json

import numpy as np
import pytest

from skinsafe.core.app import trade
from skinsafe.core.app.cli import main

# the module's quick sweep starts a local Ray: one worker builds it once, and never beside another test's Ray
# (two starting at once on the shared cores miss their start-up timeout)
pytestmark = pytest.mark.xdist_group("ray")


def test_pareto_front_on_hand_made_points():
    cost = [1.0, 2.0, 3.0, 2.0, 4.0, 1.0, 5.0]
    err = [5.0, 2.0, 1.0, 3.0, 1.0, 5.0, 0.5]
    # 0 and 5 are equal (both kept); 3 is dominated by 1; 4 by 2 (same error, higher cost)
    assert trade.pareto_front(cost, err).tolist() == [True, True, True, False, False, True, True]
    assert trade.pareto_front([1.0], [0.0]).tolist() == [True]
    assert trade.pareto_front([1, 2, 3], [3, 2, 1]).all()  # a clean trade: all optimal
    assert trade.pareto_front([1, 2, 3], [1, 2, 3]).tolist() == [True, False, False]  # one point beats all
    with pytest.raises(ValueError, match="same length"):
        trade.pareto_front([1, 2], [1])


def test_rows_errors_speedups_and_cost_axis():
    assert trade.KNOBS["damping"].quick == (0.0, 0.01, 0.05, 0.2)
    path = {0.0: np.zeros((2, 3)), 0.01: np.array([[0, 0, 0.003], [0, 0, 0.004]]),
            0.05: np.full((2, 3), 0.01), 0.2: np.full((2, 3), 0.02)}
    peak = {0.0: 20.0, 0.01: 5.0, 0.05: 6.0, 0.2: 1.0}
    results = {("damping", v): {"ms": 2.0 if v == 0.0 else 1.0, "unit": "tick", "out": path[v], "peak_qdot": peak[v]}
               for v in path}
    rows = trade.rows_from_results(results, ["damping"], quick=True)
    assert [r["value"] for r in rows] == [0.0, 0.01, 0.05, 0.2]
    assert [r["speedup_vs_reference"] for r in rows] == [1.0, 2.0, 2.0, 2.0]
    assert rows[1]["error"] == pytest.approx(4.0)  # max path deviation, mm
    assert rows[2]["error"] == pytest.approx(np.sqrt(3) * 10)
    # front on (peak joint speed, error), not on ms: 0.05 is dominated by 0.01
    assert [r["pareto"] for r in rows] == [True, True, False, True]
    assert rows[0]["peak_qdot"] == 20.0 and "out" not in rows[0]


def test_unknown_knob_is_refused_before_anything_runs(tmp_path, capsys):
    with pytest.raises(ValueError, match="choose from density"):
        trade.run_sweep(["density", "bogus"], quick=True, out=tmp_path / "t")
    assert not (tmp_path / "t").exists()
    with pytest.raises(SystemExit, match="bogus"):
        main(["trade", "--knobs", "bogus", "--out", str(tmp_path / "t")])
    assert not (tmp_path / "t").exists()


@pytest.fixture(scope="module")
def quick(tmp_path_factory):
    out = tmp_path_factory.mktemp("trade")
    return trade.run_sweep(list(trade.KNOBS), quick=True, out=out, progress=False), out


def test_quick_sweep_rows_for_every_knob(quick):
    rows, out = quick
    for name, knob in trade.KNOBS.items():
        mine = [r for r in rows if r["knob"] == name]
        assert [r["value"] for r in mine] == list(knob.quick)
        ref = mine[0]
        assert ref["error"] == 0.0 and ref["speedup_vs_reference"] == 1.0
        # the reference is on the front unless an equally exact point is faster (nearest kernel vs touch)
        exact_faster = any(r["error"] == 0.0 and r["speedup_vs_reference"] > 1.0 for r in mine[1:])
        assert ref["pareto"] != exact_faster
        for r in mine:
            assert np.isfinite(r["error"]) and r["error"] >= 0
            assert np.isfinite(r["ms"]) and r["ms"] > 0
            assert r["error_metric"] == knob.error_metric
        assert any(r["error"] > 0 for r in mine[1:])  # every knob costs accuracy somewhere
    saved = json.loads((out / "trade.json").read_text())
    assert [(r["knob"], r["value"], r["pareto"]) for r in saved] == [(r["knob"], r["value"], r["pareto"]) for r in rows]
    assert (out / "trade.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    md = (out / "trade.md").read_text().splitlines()
    assert md[0].startswith("| knob | value | ms |") and len(md) == 2 + len(rows)


def test_quick_sweep_shows_the_expected_trades(quick):
    rows, _ = quick
    by = {k: [r for r in rows if r["knob"] == k] for k in trade.KNOBS}
    # timestep: 0.5, 2, 8 ms; each coarser step is faster (4x fewer steps) and less accurate
    ts = by["timestep"]
    assert [r["value"] for r in ts] == [0.0005, 0.002, 0.008]
    assert ts[0]["speedup_vs_reference"] < ts[1]["speedup_vs_reference"] < ts[2]["speedup_vs_reference"]
    assert 0 < ts[1]["error"] < ts[2]["error"] < 0.5
    assert all(r["stable"] and r["pareto"] for r in ts)
    # density: coarser skin, fewer taxels, worse localisation (errors in mm, a fraction of the pitch)
    de = by["density"]
    assert [r["n_taxels"] for r in de] == [2149, 485, 192]  # the sample at 1, 2, 3 cm (arc-length wraps)
    assert 0 < de[1]["error"] < de[2]["error"] < 15.0
    assert all(r["missed"] == 0 and r["truth_err_mm"] < 0.5 * 1e3 * r["value"] for r in de)
    # damping: more damping asks less joint speed near the elbow singularity and tracks worse
    dp = by["damping"]
    peak = [r["peak_qdot"] for r in dp]
    assert peak[0] > np.pi and all(a >= b - 1e-3 for a, b in zip(peak, peak[1:]))
    assert all(a < b for a, b in zip([r["error"] for r in dp], [r["error"] for r in dp][1:]))
    assert dp[0]["tracking_err_mm"] < 2.0 < dp[-1]["tracking_err_mm"]
    # n-step: Monte Carlo error shrinks with the samples, about 1/sqrt(samples)
    ns = {r["value"]: r["error"] for r in by["nstep"]}
    assert ns[1] > ns[4] > ns[16] > 0
    assert 2.5 < ns[1] / ns[16] < 8.0
    # sensing: the nearest kernel is MuJoCo's touch cell model; the linear kernel spreads the force
    se = {r["value"]: r["error"] for r in by["sensing"]}
    assert se["nearest R=1p"] < 1e-6 and se["linear R=1p"] > 0.05
