"""`skinsafe replay DIR` (or a FILE.mcap of version 1): re-run the layers on a record's readings and states, compare the commands.

The record holds everything the stack needs to repeat itself (core/runtime/record.py; every version read by
core/runtime/record_read.py): its
configuration (metadata `skinsafe`: the map and its SHA-256, the robot's limits, the period, the
retraction parameters, the excluded taxels), and per tick the robot's clock, the measured dt, q
and qd, the readings the layers saw and the command source's output. The stack is rebuilt from
the configuration and ticked on those inputs in order, its commands through the run's limiter
(core/runtime/limiter.py) where the record holds its limits; the report is the largest difference
between its commands and the recorded ones (0 or floating-point noise), ticks compared, and
whether the record is complete (no tick dropped by the recorder).
"""
from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np

from skinsafe.core.runtime.limiter import Limiter
from skinsafe.core.runtime.record_read import ReplayError, read_record


def replay(path: str | Path, stack_from_config, map_path: str | Path | None = None) -> dict:
    """Re-run a record (module docstring). `stack_from_config(config, design)` rebuilds the stack."""
    from skinsafe.core.skin.taxel_map import load

    config, ticks = read_record(path)
    if config.get("source") == "experiment":
        raise ReplayError(f"{path}: a record of the {config.get('experiment') or 'an'} experiment: its controller is "
                          "not the runtime's stack, so there is nothing to replay; see it with `skinsafe view`")
    mp = Path(map_path or config["map"])
    try:
        digest = hashlib.sha256(mp.read_bytes()).hexdigest()
    except OSError as e:
        raise ReplayError(f"{path}: its map {mp} cannot be read ({e.strerror or e}); give it with --map") from None
    if digest != config["map_sha256"]:
        raise ReplayError(f"{path}: the map {mp} changed since the run (SHA-256 {digest[:8]}, recorded "
                          f"{config['map_sha256'][:8]}); give the map the run used with --map")
    stack = stack_from_config(config, load(mp))
    # records before the limiter: the stack's output; before its command period: the measured dt
    limiter = Limiter(config["limits"], config.get("limiter_period_s")) if config.get("limits") else None
    n = len(config["joint_names"])
    worst, compared, stops, gaps, last_tick = 0.0, 0, 0, 0, 0
    force = None
    seq, stale = None, 0  # a reading's sequence advanced without its forces: telemetry dropped
    for k in ticks:
        fresh = k.force is not None
        force = k.force if fresh else force
        gaps += k.index != last_tick + 1
        last_tick = k.index
        stale += seq is not None and k.reading_seq != seq and not fresh and k.ticked
        seq = k.reading_seq
        if not k.ticked:  # the stop and the commands after it (the ramp, the hold): the stack did not tick
            stops += 1
            continue
        if force is None or k.q is None or len(k.q) != n:
            raise ReplayError(f"{path}: tick {k.index} comes before any reading or joint state")
        v = stack.tick(k.t, k.q, {"force": force}, k.planned, k.dt, qdot=k.qd)
        if limiter is not None:
            v = stack.last = limiter(v, k.q, k.dt)
        worst = max(worst, float(np.abs(v - k.command).max()))
        compared += 1
    if not compared:
        raise ReplayError(f"{path}: no tick to replay (the robot never moved)")
    return {"ticks": compared, "stops": stops, "max_abs_diff": worst, "complete": bool(gaps == 0 and not stale),
            "gaps": gaps, "readings_missing": int(stale), "map": str(mp)}
