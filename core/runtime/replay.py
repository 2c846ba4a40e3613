"""`skinsafe replay DIR` (or a FILE.mcap of version 1): re-run the layers on a record's readings and states, compare the commands.

The record holds everything the stack needs to repeat itself (core/runtime/record.py): its
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
import json
import struct
from pathlib import Path

import numpy as np
from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from skinsafe.core.runtime.limiter import Limiter
from skinsafe.core.runtime.rosbag2 import record_file


class ReplayError(ValueError):
    """A record that cannot be replayed: one line naming the file and why."""


def decode_float64_array(data: bytes) -> np.ndarray:
    """std_msgs/msg/Float64MultiArray CDR (little-endian, no layout dimensions) -> float64 array."""
    ndim, = struct.unpack_from("<I", data, 4)
    if data[:4] != b"\x00\x01\x00\x00" or ndim:
        raise ReplayError("a Float64MultiArray with layout dimensions or big-endian CDR: not written by skinsafe")
    n, = struct.unpack_from("<I", data, 12)
    return np.frombuffer(data, "<f8", n, 20 if n else 16).copy()


REPLAYED = ("/joint_states", "/skinsafe/command", "/skinsafe/planned", "/skinsafe/taxels", "/skinsafe/tick",
            "/skinsafe/layers", "/skinsafe/obstacles")  # what a replay and a viewer read of a record


def read_record(path: str | Path, diagnostics: bool = False):
    """(config dict, iterator of (topic, message)) of a record (a rosbag2 folder, or a bare .mcap of version 1:
    core/runtime/rosbag2.py), its `REPLAYED` topics; JointStates (and, with `diagnostics`, the DiagnosticArrays)
    decoded by mcap-ros2-support."""
    path = record_file(path)
    try:
        f = open(path, "rb")
    except OSError as e:
        raise ReplayError(f"{path}: cannot open the record ({e.strerror or e})") from None
    try:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
    except (McapError, struct.error, ValueError) as e:
        f.close()
        raise ReplayError(f"{path}: not a readable MCAP record ({e})") from None
    if "skinsafe" not in meta:
        f.close()
        raise ReplayError(f"{path}: no 'skinsafe' metadata; record it with `skinsafe run --record`")
    config = json.loads(meta["skinsafe"]["config"])

    def messages():
        decoders = {}
        with f:
            topics = REPLAYED + (("/diagnostics",) if diagnostics else ())
            for schema, channel, msg in reader.iter_messages(topics=topics, log_time_order=False):
                if channel.topic in ("/skinsafe/taxels", "/skinsafe/tick", "/skinsafe/layers"):
                    yield channel.topic, decode_float64_array(msg.data)
                else:
                    if schema.id not in decoders:
                        decoders[schema.id] = DecoderFactory().decoder_for(channel.message_encoding, schema)
                    yield channel.topic, decoders[schema.id](msg.data)
    return config, messages()


def replay(path: str | Path, stack_from_config, map_path: str | Path | None = None) -> dict:
    """Re-run a record (module docstring). `stack_from_config(config, design)` rebuilds the stack."""
    from skinsafe.core.skin.taxel_map import load

    config, messages = read_record(path)
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
    q = qd = planned = command = force = None
    seq, fresh, stale = None, False, 0  # a reading's sequence advanced without its forces: telemetry dropped
    for topic, msg in messages:
        if topic == "/joint_states":
            q, qd = np.asarray(msg.position, float), np.asarray(msg.velocity, float)
        elif topic == "/skinsafe/planned":
            planned = np.asarray(msg.velocity, float)
        elif topic == "/skinsafe/command":
            command = np.asarray(msg.velocity, float)
        elif topic == "/skinsafe/taxels":
            force, fresh = msg, True
        elif topic == "/skinsafe/tick":
            t, dt, reading, tick, ticked = msg[:5]
            gaps += int(tick) != last_tick + 1
            last_tick = int(tick)
            stale += seq is not None and reading != seq and not fresh and bool(ticked)
            seq, fresh = reading, False
            if not ticked:  # the stop and the commands after it (the ramp, the hold): the stack did not tick
                stops += 1
                continue
            if force is None or q is None or len(q) != n:
                raise ReplayError(f"{path}: tick {int(tick)} comes before any reading or joint state")
            v = stack.tick(t, q, {"force": force}, planned, dt, qdot=qd)
            if limiter is not None:
                v = stack.last = limiter(v, q, dt)
            worst = max(worst, float(np.abs(v - command).max()))
            compared += 1
    if not compared:
        raise ReplayError(f"{path}: no tick to replay (the robot never moved)")
    return {"ticks": compared, "stops": stops, "max_abs_diff": worst, "complete": bool(gaps == 0 and not stale),
            "gaps": gaps, "readings_missing": int(stale), "map": str(mp)}
