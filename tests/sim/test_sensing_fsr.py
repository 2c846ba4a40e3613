"""FSR sensor model (encode/decode) and the board sample-and-hold; bench rows smoke test."""
import numpy as np
import pytest

from skinsafe.core.sim.sensor_model import BoardSampler, FSRModel


def test_curve_is_nonlinear_saturating_and_decode_inverts_it():
    m = FSRModel(noise_counts=0)
    f = np.array([0.0, 0.05, 0.2, 1.0, 5.0, 20.0, 1e4])
    c = m.encode(f)
    assert c.dtype == np.uint16 and c[0] == 0 and c[1] == 0  # open below the turn-on force
    assert c[3] == round(4095 * 10e3 / (10e3 + 6e3))  # divider at 1 N: 10k / (10k + 6k)
    assert (np.diff(c.astype(int)[1:]) > 0).all()
    top = round(4095 * 10e3 / (10e3 + 250))  # saturated: the FSR floor of 250 ohm
    assert m.max_force == pytest.approx(24 ** (1 / 0.9)) and c[-1] == top == m.encode(np.array([50.0]))[0]
    assert m.decode(np.array([top, 4095])) == pytest.approx([m.max_force] * 2, rel=5e-3)  # within a count
    back = m.decode(c[2:6])
    # quantisation: one count near the top is worth more force than near the bottom
    assert np.allclose(back, f[2:6], rtol=0.01)
    gain = np.diff(m.voltage(np.array([1.0, 1.001]))) / np.diff(m.voltage(np.array([10.0, 10.001])))
    assert gain[0] > 3  # nonlinear: far more sensitive at light touch


def test_noise_is_seeded_and_sized():
    m = FSRModel(noise_counts=3.0)
    f = np.full(20000, 2.0)
    a = m.encode(f, np.random.default_rng(5)).astype(float)
    b = m.encode(f, np.random.default_rng(5)).astype(float)
    np.testing.assert_array_equal(a, b)
    assert a.std() == pytest.approx(3.0, rel=0.05)
    assert a.mean() == pytest.approx(m.voltage(np.array([2.0]))[0] * 4095, abs=0.1)


def test_bad_model_parameters_named():
    with pytest.raises(ValueError, match="bits"):
        FSRModel(bits=20)
    with pytest.raises(ValueError, match="rate_hz"):
        FSRModel(rate_hz=0)


def test_board_sampler_holds_samples_and_delays_them():
    fsr = FSRModel(rate_hz=100.0, latency_s=0.005, noise_counts=0)
    s = BoardSampler(fsr, 2, noise=False)
    seen = []
    for k in range(60):  # 1 kHz simulation; force steps up at t = 12 ms
        t = k * 1e-3
        f = np.array([3.0, 0.0]) if t >= 0.012 else np.zeros(2)
        seen.append(s.read(t, f)[0])
    seen = np.array(seen)
    # sampled at 20 ms (first sample after the step), available 5 ms later, held until the next
    assert (seen[:25] == 0).all() and seen[25] == pytest.approx(3.0, rel=0.01)
    assert (seen[25:] == seen[25]).all()


def test_bench_rows_small(tmp_path):
    import argparse

    from skinsafe.core.bench import sensing as bench_sensing

    args = argparse.Namespace(sizes="1024", steps=20, sweeps="taxels,timestep", timesteps="0.002",
                              tactile_points="1,7", plot=str(tmp_path / "p.png"))
    rows = bench_sensing.rows(args)
    taxel = [r for r in rows if r["sweep"] == "taxels"]
    assert [r["readout"] for r in taxel] == ["vectorised"] * 2 + ["touch"] + ["tactile"] * 2
    truth = {"truth_lit_precision", "truth_lit_recall", "truth_lit_f1", "truth_force_err"}
    for r in taxel:
        assert {"n_taxels", "readout", "steps_per_s", "overhead_vs_skinless"} | truth <= set(r)
        assert 0 <= r["truth_lit_precision"] <= 1 and 0 <= r["truth_lit_recall"] <= 1
    nearest = [r for r in taxel if r["kernel"] == "nearest"][0]
    assert nearest["force_err"] < 1e-6 and nearest["lit_recall"] == 1.0
    assert nearest["truth_lit_precision"] == 1.0 and nearest["truth_lit_recall"] > 0.5  # one cell per contact
    assert {"speedup_vs_tactile", "tactile_points", "overhead_vs_bare"} <= set(nearest)
    one, seven = [r for r in taxel if r["readout"] == "tactile"]
    assert seven["truth_lit_recall"] > one["truth_lit_recall"]  # vertices filling the cells find more patches
    ts = [r for r in rows if r["sweep"] == "timestep"][0]
    assert ts["on_arm"] and ts["force_err"] < 0.05
    assert (tmp_path / "p.png").read_bytes()[:4] == b"\x89PNG"
