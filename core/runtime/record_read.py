"""A record's ticks, whichever skinsafe wrote it (core/runtime/record.py), for a replay and the viewers.

One reader per record version, chosen by the version the record carries (metadata `skinsafe`'s `record_version`;
none: 1); an unknown version is refused, naming it:
- 1 (a bare FILE.mcap) and 2 (a rosbag2 folder): the tick, the forces, the layers and the obstacles as
  std_msgs/Float64MultiArray (`/skinsafe/tick` [t, dt, reading seq, tick, 1 if ticked], `/skinsafe/taxels`,
  `/skinsafe/layers` [f, speed factor, retracting, K, the K retracting taxels' indices], `/skinsafe/obstacles`
  [x y z qw qx qy qz per obstacle]): `_Numeric`;
- 3: typed (`/skinsafe/tick` skinsafe_msgs/Tick, `/skinsafe/forces` skinsafe_msgs/TaxelForces, `/skinsafe/state`
  skinsafe_msgs/LayerState naming taxels by id, `/skinsafe/obstacles` geometry_msgs/PoseArray): `_Typed`.
Every version has `/joint_states`, `/skinsafe/planned`, `/skinsafe/command` (JointState) and `/diagnostics`, and
writes a tick's topics before its `/skinsafe/tick`, its layers and diagnostics after: `read_record` gathers them into
one `RecordedTick` per tick. mcap and mcap-ros2-support decode (no mujoco, no rosbags: Blender's add-on reads too).
"""
from __future__ import annotations

import json
import struct
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from skinsafe.core.runtime.rosbag2 import RECORD_VERSION, record_file

JOINTS = ("/joint_states", "/skinsafe/planned", "/skinsafe/command")
TAXEL_IDS = "skinsafe_taxels"  # metadata of version 3: the taxel ids in the map's order (a run's record)


class ReplayError(ValueError):
    """A record that cannot be read or replayed: one line naming the file and why."""


@dataclass(frozen=True)
class Layers:
    """The layers' state on a tick: the retracting taxels as indices in the map's order, highest priority first."""
    potential: float
    speed_factor: float
    retracting: bool
    pool: np.ndarray


NO_LAYERS = Layers(0.0, 1.0, False, np.zeros(0, np.int64))  # a tick whose telemetry was dropped


@dataclass(frozen=True)
class RecordedTick:
    """One tick as its record holds it (`force`: a new reading on this tick, else None; `layers`: None when
    dropped; `status`: the diagnostics written after it, {name: {level, message, values}})."""
    t: float
    dt: float
    reading_seq: float
    index: int
    ticked: bool
    q: np.ndarray | None
    qd: np.ndarray | None
    planned: np.ndarray | None
    command: np.ndarray | None
    force: np.ndarray | None = None
    layers: Layers | None = None
    obstacles: np.ndarray | None = None
    status: dict | None = None


def decode_float64_array(data: bytes) -> np.ndarray:
    """std_msgs/msg/Float64MultiArray CDR (little-endian, no layout dimensions) -> float64 array."""
    ndim, = struct.unpack_from("<I", data, 4)
    if data[:4] != b"\x00\x01\x00\x00" or ndim:
        raise ReplayError("a Float64MultiArray with layout dimensions or big-endian CDR: not written by skinsafe")
    n, = struct.unpack_from("<I", data, 12)
    return np.frombuffer(data, "<f8", n, 20 if n else 16).copy()


class _Numeric:
    """Versions 1 and 2 (module docstring): the numeric topics decoded from their bytes."""
    FORCES, TICK, LAYERS, OBSTACLES = "/skinsafe/taxels", "/skinsafe/tick", "/skinsafe/layers", "/skinsafe/obstacles"
    RAW = True

    def __init__(self, meta: dict):
        pass

    @staticmethod
    def decode(data: bytes) -> np.ndarray:
        return decode_float64_array(data)

    @staticmethod
    def forces(x) -> np.ndarray:
        return x

    @staticmethod
    def tick(x) -> tuple:
        return float(x[0]), float(x[1]), float(x[2]), int(x[3]), bool(x[4])

    @staticmethod
    def layers(x) -> Layers:
        return Layers(float(x[0]), float(x[1]), bool(x[2]), x[4:].astype(np.int64))

    @staticmethod
    def obstacles(x) -> np.ndarray:
        return x.reshape(-1, 7)


class _Typed:
    """Version 3 (module docstring): typed messages, decoded by mcap-ros2-support from the record's schemas."""
    FORCES, TICK, LAYERS, OBSTACLES = "/skinsafe/forces", "/skinsafe/tick", "/skinsafe/state", "/skinsafe/obstacles"
    RAW = False

    def __init__(self, meta: dict):
        ids = meta.get(TAXEL_IDS, {}).get("ids")
        ids = np.array([int(i) for i in ids.split(",")] if ids else [], np.int64)
        self.order = np.argsort(ids, kind="stable")
        self.sorted = ids[self.order]

    def forces(self, m) -> np.ndarray:
        return np.asarray(m.force, float)

    @staticmethod
    def tick(m) -> tuple:
        return m.t, m.dt, m.reading_seq, int(m.index), bool(m.ticked)

    def layers(self, m) -> Layers:
        ids = np.asarray(m.pool_taxels, np.int64)  # by id; without the ids in the metadata, indices
        pool = self.order[np.searchsorted(self.sorted, ids)] if len(self.sorted) else ids
        return Layers(m.potential, m.speed_factor, bool(m.retracting), pool)

    @staticmethod
    def obstacles(m) -> np.ndarray:
        return np.array([[p.position.x, p.position.y, p.position.z, p.orientation.w, p.orientation.x,
                          p.orientation.y, p.orientation.z] for p in m.poses]).reshape(-1, 7)


READERS = {1: _Numeric, 2: _Numeric, 3: _Typed}


def read_record(path: str | Path) -> tuple[dict, Iterator[RecordedTick]]:
    """(config dict, iterator of its ticks) of a record (a rosbag2 folder, or a bare .mcap: core/runtime/rosbag2.py)."""
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
    version = config.get("record_version", 1)
    if version not in READERS:
        f.close()
        raise ReplayError(f"{path}: record version {version} (metadata 'skinsafe', field record_version) is newer "
                          f"than this skinsafe reads ({RECORD_VERSION}); update skinsafe to read it")
    return config, _ticks(f, reader, READERS[version](meta))


def _ticks(f, reader, v) -> Iterator[RecordedTick]:
    """The record's messages gathered into ticks (module docstring)."""
    topics = (*JOINTS, v.FORCES, v.TICK, v.LAYERS, v.OBSTACLES, "/diagnostics")
    decoders, cur, pending = {}, {}, None
    with f:
        for schema, channel, msg in reader.iter_messages(topics=topics, log_time_order=False):
            topic = channel.topic
            if v.RAW and topic in (v.FORCES, v.TICK, v.LAYERS, v.OBSTACLES):
                m = v.decode(msg.data)
            else:
                if schema.id not in decoders:
                    decoders[schema.id] = DecoderFactory().decoder_for(channel.message_encoding, schema)
                m = decoders[schema.id](msg.data)
            if topic == "/joint_states":
                cur["q"], cur["qd"] = np.asarray(m.position, float), np.asarray(m.velocity, float)
            elif topic == "/skinsafe/planned":
                cur["planned"] = np.asarray(m.velocity, float)
            elif topic == "/skinsafe/command":
                cur["command"] = np.asarray(m.velocity, float)
            elif topic == v.FORCES:
                cur["force"] = v.forces(m)
            elif topic == v.OBSTACLES:
                cur["obstacles"] = v.obstacles(m)
            elif topic == v.TICK:
                if pending is not None:
                    yield RecordedTick(**pending)
                t, dt, seq, index, ticked = v.tick(m)
                pending = dict(t=t, dt=dt, reading_seq=seq, index=index, ticked=ticked, q=cur.get("q"),
                               qd=cur.get("qd"), planned=cur.get("planned"), command=cur.get("command"),
                               force=cur.pop("force", None), obstacles=cur.pop("obstacles", None))
            elif topic == v.LAYERS and pending is not None:
                pending["layers"] = v.layers(m)
            elif topic == "/diagnostics" and pending is not None:
                pending["status"] = (pending.get("status") or {}) | {
                    s.name: {"level": int(s.level), "message": s.message,
                             "values": {kv.key: kv.value for kv in s.values}} for s in m.status}
    if pending is not None:
        yield RecordedTick(**pending)
