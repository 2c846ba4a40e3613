"""`skinsafe bench runtime --tap`: what the live view costs inside the control loop, per shared tick.

With `run --view`, the loop's tap hands the newest tick to the view's own process at 30 Hz
(core/runtime/view_share.py): one tick in ~33 carries that cost on top of its work. Per row (`--taxels`,
and a retracting pool of `pool` taxels: none, 64, every one): `copy_us_*` is the tap as it is (the tick's
arrays copied into shared memory), `encode_us_*` the reference it replaced (the stream message encoded in
the loop: its JSON header with the pool's indices, then copied), each p50 / p99 / max over `--seconds`
of publishes alternating between the two, and `encode_vs_copy` their p99s' ratio.
"""
from __future__ import annotations

import time

import numpy as np

from skinsafe.core.runtime.tick import Tick
from skinsafe.core.runtime.view_share import SharedFrames
from skinsafe.core.runtime.view_stream import frame_message

JOINTS, BOARDS = 6, 16


def _tick(n: int, pool: int, rng: np.random.Generator) -> Tick:
    """A retracting tick of `n` taxels with `pool` of them in the pool (none: not retracting)."""
    q = rng.normal(size=JOINTS)
    return Tick(t=1.0, q=q, force=rng.random(n) * 40, command=-q, retracting=pool > 0, pool=pool,
                flags=("limited",) if pool else (), planned=q * 2, pool_taxels=rng.permutation(n)[:pool] if pool else None,
                potential=0.3, speed_factor=0.8, board_age_s={b: 0.004 for b in range(BOARDS)})


def _figures(us: list[float], key: str) -> dict:
    a = np.asarray(us)
    return {f"{key}_us_p50": float(np.median(a)), f"{key}_us_p99": float(np.percentile(a, 99)),
            f"{key}_us_max": float(a.max())}


def rows(taxels: list[int], seconds: float) -> list[dict]:
    rng = np.random.default_rng(0)
    out = []
    for n in taxels:
        frames = SharedFrames.create(n, JOINTS, range(BOARDS))
        block = np.zeros(16 * n + (64 << 10), np.uint8)  # the encoded message's old block
        try:
            for pool in (0, 64, n):
                f, copy, encode = _tick(n, pool, rng), [], []
                end = time.monotonic() + seconds
                while time.monotonic() < end:
                    t0 = time.perf_counter()
                    frames.write(f)
                    t1 = time.perf_counter()
                    msg = frame_message(1, f)
                    block[:len(msg)] = np.frombuffer(msg, np.uint8)
                    t2 = time.perf_counter()
                    copy.append((t1 - t0) * 1e6)
                    encode.append((t2 - t1) * 1e6)
                row = {"taxels": n, "pool": pool, "publishes": len(copy)} | _figures(copy, "copy") | _figures(encode, "encode")
                out.append(row | {"encode_vs_copy": row["encode_us_p99"] / row["copy_us_p99"]})
        finally:
            frames.close()
    return out
