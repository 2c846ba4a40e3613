"""The tick is one typed record: what the loop hands the recorder comes back from the record as the same tick
(what `skinsafe view FILE.mcap`, Blender's live link and `--publish` show)."""
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from skinsafe.core.runtime.record import Recorder
from skinsafe.core.runtime.recording import Recording
from skinsafe.core.runtime.tick import Tick
from skinsafe.core.runtime.view_stream import frame_header

NJ, N = 6, 40
BOARDS = (0x11, 0x2A)


@st.composite
def runs(draw):
    """A run's ticks as the loop makes them: a new reading on some ticks, retractions with their pools, flags
    that change, board ages, the stop's tick last; 1/8 s apart (the record's diagnostics come at 10 Hz, each
    tick's board ages then in the record)."""
    k = draw(st.integers(2, 30))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    out = []
    for i in range(k):
        last = i == k - 1
        retracting = not last and bool(rng.random() < 0.4)
        pool = rng.permutation(N)[:rng.integers(1, 6)] if retracting else None
        command = np.zeros(NJ) if last else rng.normal(size=NJ)
        out.append(Tick(t=0.125 * (i + 1), q=rng.normal(size=NJ), qd=rng.normal(size=NJ), dt=0.001, command=command,
                        planned=rng.normal(size=NJ), force=rng.random(N) * 30, force_new=bool(rng.random() < 0.5),
                        reading_seq=float(i // 2), retracting=retracting, pool=0 if pool is None else len(pool),
                        pool_taxels=pool, flags=("stop",) if last else (("limited",) if rng.random() < 0.5 else ()),
                        potential=float(rng.random()), speed_factor=0.0 if last else float(rng.random()),
                        stop="skin: board 0x2a silent" if last else "", ticked=not last,
                        board_age_s={b: round(float(rng.random()) * 0.05, 5) for b in BOARDS},
                        frames_lost=int(rng.integers(0, 9)), index=i + 1, ns=1_000_000 * (i + 1)))
    return out


@settings(max_examples=30, deadline=None)
@given(runs())
def test_each_tick_written_comes_back_from_the_record_as_the_loop_made_it(tmp_path_factory, ticks):
    path = tmp_path_factory.mktemp("rec") / "run.mcap"
    rec = Recorder(path, [f"j{i}" for i in range(NJ)], {"map": "", "period_s": 0.001})
    for k in ticks:
        rec.put(k, wait=True)
    assert rec.close({"reason": ticks[-1].stop, "kind": "skin", "t": ticks[-1].t})["dropped"] == 0
    got = Recording(path)
    assert len(got.t) == len(ticks)
    newest = None
    for i, k in enumerate(ticks):
        newest = k.force if k.force_new else newest
        r = got.tick(i)
        for name in ("q", "command", "planned"):
            np.testing.assert_array_equal(getattr(r, name), getattr(k, name))
        assert (r.t, r.retracting, r.pool, r.flags, r.stop, r.frames_lost, r.index) == (
            k.t, k.retracting, k.pool, k.flags, k.stop, k.frames_lost, k.index)
        assert (r.potential, r.speed_factor) == (k.potential, k.speed_factor)
        np.testing.assert_array_equal(r.pool_taxels, () if k.pool_taxels is None else k.pool_taxels)
        if newest is None:  # no reading yet: every taxel NaN
            assert np.isnan(r.force).all()
        else:
            np.testing.assert_array_equal(r.force, newest.astype(np.float32))
        assert r.board_age_s.keys() == k.board_age_s.keys()
        np.testing.assert_allclose(list(r.board_age_s.values()), list(k.board_age_s.values()), atol=5.1e-6)
        assert got.frame(i)[0] == frame_header(i + 1, r)  # the view's frame is the tick's header
