"""The run's record: MCAP with ROS 2 message schemas (Foxglove and ROS 2 tools open it).

Topics (log time: host wall clock; header stamps: the robot's clock):
- `/joint_states` (sensor_msgs/msg/JointState): measured q and qd, every tick;
- `/skinsafe/command` (sensor_msgs/msg/JointState, velocity): the joint velocity sent, every tick
  (zero on the tick a watchdog stopped the robot);
- `/skinsafe/planned` (sensor_msgs/msg/JointState, velocity): the command source's output, every tick;
- `/skinsafe/taxels` (std_msgs/msg/Float64MultiArray): the (N,) taxel forces the layers saw (N, after
  tare; excluded taxels 0), whenever a new reading arrived; float64 so a replay is exact;
- `/skinsafe/tick` (std_msgs/msg/Float64MultiArray): per tick [robot t, measured dt, reading seq, tick,
  1 if the stack ticked (0: the stop)];
- `/skinsafe/layers` (std_msgs/msg/Float64MultiArray): per tick [danger potential f, speed factor
  |command| / |planned|, 1 if retracting, K, then the K retracting taxels, highest priority first]
  (what the live view shows of the layers; absent from records of older versions);
- `/skinsafe/obstacles` (std_msgs/msg/Float64MultiArray): per tick, the pose [x, y, z, qw, qx, qy, qz]
  of each of the metadata's `obstacles`, in order, where they move (an experiment's person, written by
  core/runtime/sim_record.py); absent from runs and older records (their obstacles stand still);
- `/diagnostics` (diagnostic_msgs/msg/DiagnosticArray): layers (retracting, pool, flags), skin (board
  ages, frames lost), command (source age) at 10 Hz and on every change of the layers' flags; the
  watchdog's stop (level ERROR, its reason) once at the end.
With `topics` (`skinsafe run --record DIR`, record version 2) the record is a rosbag2 folder a ROS 2 user plays
(core/runtime/rosbag2.py: DIR/metadata.yaml beside DIR/DIR_0.mcap) and it also holds the ROS 2 tools' topics
(core/runtime/ros2_topics.py: `/robot_description`, `/tf_static`, `/tf`, `/skinsafe/tactile`, `/skinsafe/skin`,
`/skinsafe/contacts`, `/skinsafe/state`, `/rosout`), telemetry like the forces; without (an experiment's
record, core/runtime/sim_record.py) a bare FILE.mcap (the layout of version 1).
Metadata `skinsafe` holds the configuration a replay needs (map, limits, period, excluded taxels, ...) and, as
`run`, the run's whole configuration as given (core/runtime/run_config.py `RunConfig.to_json`).

The loop only enqueues (`put`, never blocks): a writer thread encodes and writes. `skinsafe run` runs the recorder
in a writer process of its own (core/app/record_writer.py), fed through shared memory, so that its encoding does not
share the loop's interpreter lock; that process's ring is the loop's queue. When the writer is
behind (`queue_size` ticks waiting) a tick's telemetry (its taxel forces, layers, diagnostics) is dropped
and counted (`dropped`, in the record's last diagnostics; the replay then says the record is incomplete);
its safety topics (`/joint_states`, `/skinsafe/command`, `/skinsafe/planned`, `/skinsafe/tick`) never are:
every tick, the stop's and the ramp's after it included, is in the record.
Messages are CDR-encoded here (`JointStateEncoder`, `encode_float64_array`, `encode_diagnostics`:
byte-equal to mcap-ros2-support's encoder, tested; that one writes arrays one element at a time,
milliseconds for 4,096 floats where numpy takes microseconds) and written with `mcap`'s writer
(ros2 profile, LZ4 chunks). The file (the folder) is written as FILE.part and renamed when complete.
"""
from __future__ import annotations

import json
import os
import queue
import shutil
import struct
import threading
import time
from pathlib import Path

import numpy as np
from mcap.well_known import MessageEncoding, Profile, SchemaEncoding
from mcap.writer import CompressionType, Writer

from skinsafe.core.runtime import rosbag2
from skinsafe.core.runtime.ros2_msgs import schema
from skinsafe.core.runtime.ros2_topics import LATCHED, Ros2Topics
from skinsafe.core.runtime.ros2_topics import TOPICS as ROS2_TOPICS
from skinsafe.core.runtime.tick import Tick

TIME = "================================================================================\nMSG: builtin_interfaces/Time\nint32 sec\nuint32 nanosec\n"
HEADER = ("================================================================================\nMSG: std_msgs/Header\n"
          "builtin_interfaces/Time stamp\nstring frame_id\n") + TIME
JOINT_STATE = "std_msgs/Header header\nstring[] name\nfloat64[] position\nfloat64[] velocity\nfloat64[] effort\n" + HEADER
FLOAT64_ARRAY = ("std_msgs/MultiArrayLayout layout\nfloat64[] data\n"
                 "================================================================================\n"
                 "MSG: std_msgs/MultiArrayLayout\nstd_msgs/MultiArrayDimension[] dim\nuint32 data_offset\n"
                 "================================================================================\n"
                 "MSG: std_msgs/MultiArrayDimension\nstring label\nuint32 size\nuint32 stride\n")
DIAGNOSTIC_ARRAY = ("std_msgs/Header header\ndiagnostic_msgs/DiagnosticStatus[] status\n" + HEADER
                    + "================================================================================\n"
                    "MSG: diagnostic_msgs/DiagnosticStatus\nbyte OK=0\nbyte WARN=1\nbyte ERROR=2\nbyte STALE=3\n"
                    "byte level\nstring name\nstring message\nstring hardware_id\ndiagnostic_msgs/KeyValue[] values\n"
                    "================================================================================\n"
                    "MSG: diagnostic_msgs/KeyValue\nstring key\nstring value\n")
SCHEMAS = {"sensor_msgs/msg/JointState": JOINT_STATE, "std_msgs/msg/Float64MultiArray": FLOAT64_ARRAY,
           "diagnostic_msgs/msg/DiagnosticArray": DIAGNOSTIC_ARRAY}
TOPICS = {"/joint_states": "sensor_msgs/msg/JointState", "/skinsafe/command": "sensor_msgs/msg/JointState",
          "/skinsafe/planned": "sensor_msgs/msg/JointState", "/skinsafe/taxels": "std_msgs/msg/Float64MultiArray",
          "/skinsafe/tick": "std_msgs/msg/Float64MultiArray", "/skinsafe/layers": "std_msgs/msg/Float64MultiArray",
          "/diagnostics": "diagnostic_msgs/msg/DiagnosticArray"}
OBSTACLES = "/skinsafe/obstacles"  # registered with its first message: a run's record has no such channel
CDR_LE = b"\x00\x01\x00\x00"
DIAG_EVERY_S = 0.1
OK, WARN, ERROR = 0, 1, 2


def _string(s: str) -> bytes:
    b = s.encode() + b"\0"
    return struct.pack("<I", len(b)) + b


def _pad(buf: bytearray, size: int) -> None:
    buf.extend(b"\0" * (-(len(buf) - 4) % size))


def _f64_seq(buf: bytearray, x: np.ndarray) -> None:
    _pad(buf, 4)
    buf += struct.pack("<I", len(x))
    if len(x):
        _pad(buf, 8)
        buf += np.ascontiguousarray(x, "<f8").tobytes()


def _stamp(t: float) -> bytes:
    sec = int(np.floor(t))
    return struct.pack("<iI", sec, min(int(round((t - sec) * 1e9)), 999_999_999))


class JointStateEncoder:
    """sensor_msgs/msg/JointState in CDR for one robot's joint names (the names encoded once)."""

    def __init__(self, names: list[str], frame_id: str = ""):
        self.frame = _string(frame_id)
        names_part = bytearray()
        names_part += struct.pack("<I", len(names))
        for n in names:  # the block starts 4-aligned: alignment within it is the message's
            names_part += b"\0" * (-len(names_part) % 4) + _string(n)
        self.names = bytes(names_part)

    def __call__(self, t: float, position=(), velocity=(), effort=()) -> bytes:
        buf = bytearray(CDR_LE)
        buf += _stamp(t)
        buf += self.frame
        _pad(buf, 4)
        buf += self.names
        for x in (position, velocity, effort):
            _f64_seq(buf, np.asarray(x, float))
        return bytes(buf)


def encode_float64_array(data: np.ndarray) -> bytes:
    """std_msgs/msg/Float64MultiArray in CDR: no layout dimensions, `data` as float64."""
    buf = bytearray(CDR_LE)
    buf += struct.pack("<II", 0, 0)  # dim: empty sequence; data_offset 0
    _f64_seq(buf, data)
    return bytes(buf)


def encode_diagnostics(t: float, status: list) -> bytes:
    """diagnostic_msgs/msg/DiagnosticArray in CDR: `status` = [(name, level, message, [(key, value)])]."""
    buf = bytearray(CDR_LE)
    buf += _stamp(t) + _string("")
    _pad(buf, 4)
    buf += struct.pack("<I", len(status))
    for name, level, message, values in status:
        buf.append(level)
        for s in (name, message, "skinsafe"):
            _pad(buf, 4)
            buf += _string(s)
        _pad(buf, 4)
        buf += struct.pack("<I", len(values))
        for k, v in values:
            for s in (k, v):
                _pad(buf, 4)
                buf += _string(s)
    return bytes(buf)


class Recorder:
    """A writer thread behind a bounded queue (module docstring)."""

    def __init__(self, path: str | Path, joint_names: list[str], config: dict, queue_size: int = 8192,
                 topics: Ros2Topics | None = None):
        self.path = Path(path)
        self.part = self.path.with_name(self.path.name + ".part")
        self.topics = topics
        if topics is not None:  # a rosbag2 folder (module docstring)
            if self.path.is_dir() and not (self.path / rosbag2.METADATA).exists():
                raise FileExistsError(f"{self.path} is a folder but not a record; choose a new folder for the record")
            self.part.mkdir(exist_ok=True)
            config = config | {"record_version": rosbag2.RECORD_VERSION}
        self.file = open(self.part / rosbag2.mcap_name(self.path) if topics else self.part, "wb")
        self.writer = Writer(self.file, compression=CompressionType.LZ4)
        self.writer.start(profile=Profile.ROS2, library="skinsafe")
        self.schemas = {name: self.writer.register_schema(name, SchemaEncoding.ROS2, text.encode())
                        for name, text in SCHEMAS.items()}
        self.types = dict(TOPICS) | (ROS2_TOPICS if topics else {})
        for name in set(self.types.values()) - set(self.schemas):
            self.schemas[name] = self.writer.register_schema(name, SchemaEncoding.ROS2, schema(name).encode())
        self.channels = {topic: self.writer.register_channel(topic, MessageEncoding.CDR, self.schemas[name],
                                                             {"offered_qos_profiles": rosbag2.qos_text(topic in LATCHED)})
                         for topic, name in self.types.items()}
        self.counts = dict.fromkeys(self.types, 0)
        self.writer.add_metadata("skinsafe", {"config": json.dumps(config)})
        self.joints = JointStateEncoder(joint_names)
        self.names = list(joint_names)
        self.q: queue.Queue = queue.Queue()  # unbounded: only telemetry is dropped (`put`)
        self.queue_size = queue_size
        self.dropped = self.written = 0
        self.error = ""
        self.first_ns = self.last_ns = time.time_ns()
        for topic, data in topics.static() if topics else ():
            self._raw(topic, data, self.first_ns)
        self._diag_t = -np.inf
        self._flags = ()
        self.thread = threading.Thread(target=self._work, name="recorder", daemon=True)
        self.thread.start()

    def put(self, tick: Tick, wait: bool = False, telemetry: bool = True) -> None:
        """Enqueue one tick, never blocking; when the writer is behind, only its safety topics (module docstring), its
        telemetry dropped and counted. `wait`: a writer with no loop to keep (core/runtime/sim_record.py, the run's
        writer process core/app/record_writer.py) waits for room and keeps what it is given (without `telemetry`:
        the safety topics, the telemetry dropped and counted by the loop's side)."""
        if wait:
            while self.q.qsize() >= self.queue_size and self.thread.is_alive():
                time.sleep(0.001)
            self.q.put(tick if telemetry else ("safety", tick))
        elif self.q.qsize() >= self.queue_size:
            self.dropped += 1
            self.q.put(("safety", tick))
        else:
            self.q.put(tick)

    def close(self, stop: dict | None = None) -> dict:
        """Write the final diagnostics (`stop`: reason, kind, stats), finish the file, rename it into place."""
        self.q.put(("stop", stop or {}))
        self.q.put(None)
        self.thread.join()
        self.writer.finish()
        self.file.close()
        if self.error:
            return {"written": self.written, "dropped": self.dropped, "error": self.error}
        if self.topics is not None:
            rosbag2.write_metadata(self.part, rosbag2.mcap_name(self.path), self.types, self.counts, LATCHED,
                                   self.first_ns, self.last_ns)
            if self.path.is_dir():  # an earlier record (its metadata.yaml checked when this one began)
                shutil.rmtree(self.path)
            elif self.path.exists():
                self.path.unlink()
        os.replace(self.part, self.path)
        return {"written": self.written, "dropped": self.dropped, "path": str(self.path)}

    # -- the writer thread -------------------------------------------------------------------
    def _work(self) -> None:
        while True:
            item = self.q.get()
            if item is None:
                return
            if self.error:
                continue
            try:
                if isinstance(item, Tick):
                    self._tick(item)
                elif item[0] == "safety":
                    self._safety(item[1])
                else:
                    self._stop(item[1])
            except Exception as e:  # a disk that fills up must not take the loop down: named at the end
                self.error = f"{self.part}: recording failed ({e})"

    def _raw(self, topic: str, data: bytes, ns: int) -> None:
        self.writer.add_message(self.channels[topic], log_time=ns, data=data, publish_time=ns, sequence=self.written)
        self.written += 1
        self.counts[topic] += 1
        self.last_ns = max(self.last_ns, ns)

    def _safety(self, k: Tick) -> None:
        """A tick's safety topics (module docstring)."""
        ns, t = k.ns, k.t
        self._raw("/joint_states", self.joints(t, k.q, np.zeros_like(k.q) if k.qd is None else k.qd), ns)
        self._raw("/skinsafe/planned", self.joints(t, (), k.command if k.planned is None else k.planned), ns)
        self._raw("/skinsafe/command", self.joints(t, (), k.command), ns)
        self._raw("/skinsafe/tick", encode_float64_array(
            np.array([t, k.dt, k.reading_seq, k.index, float(k.ticked)], float)), ns)

    def _tick(self, k: Tick) -> None:
        """One tick: its forces only when new, its obstacles' poses when they move."""
        ns, t = k.ns, k.t
        self._raw("/joint_states", self.joints(t, k.q, np.zeros_like(k.q) if k.qd is None else k.qd), ns)
        self._raw("/skinsafe/planned", self.joints(t, (), k.command if k.planned is None else k.planned), ns)
        self._raw("/skinsafe/command", self.joints(t, (), k.command), ns)
        if k.force_new and k.force is not None:
            self._raw("/skinsafe/taxels", encode_float64_array(k.force), ns)
        if k.obstacles is not None:
            if OBSTACLES not in self.channels:
                self.channels[OBSTACLES] = self.writer.register_channel(
                    OBSTACLES, MessageEncoding.CDR, self.schemas["std_msgs/msg/Float64MultiArray"])
                self.types[OBSTACLES], self.counts[OBSTACLES] = "std_msgs/msg/Float64MultiArray", 0
            self._raw(OBSTACLES, encode_float64_array(np.ravel(k.obstacles)), ns)
        self._raw("/skinsafe/tick", encode_float64_array(
            np.array([t, k.dt, k.reading_seq, k.index, float(k.ticked)], float)), ns)
        pool = () if k.pool_taxels is None else k.pool_taxels
        layers = np.empty(4 + len(pool))
        layers[:4] = k.potential, k.speed_factor, float(k.retracting), len(pool)
        layers[4:] = pool
        self._raw("/skinsafe/layers", encode_float64_array(layers), ns)
        for topic, data in self.topics.tick(k) if self.topics else ():
            self._raw(topic, data, ns)
        if k.flags != self._flags or t - self._diag_t >= DIAG_EVERY_S:
            self._flags, self._diag_t = k.flags, t
            layers = [("retracting", str(k.retracting)), ("pool", str(k.pool)), ("flags", ",".join(k.flags))]
            skin = [(f"board {uid:#x} age_ms", f"{a * 1e3:.2f}") for uid, a in (k.board_age_s or {}).items()]
            skin.append(("frames_lost", str(k.frames_lost)))
            self._diag(ns, t, [("skinsafe/layers", WARN if k.flags else OK, "retracting" if k.retracting else "ok",
                                layers), ("skinsafe/skin", OK, "streaming", skin),
                               ("skinsafe/command", WARN if k.command_refused else OK, "fresh",
                                [("age_s", f"{k.command_age:.4f}"), ("refused", str(k.command_refused))])])

    def _stop(self, stop: dict) -> None:
        level = OK if stop.get("kind") in ("end", None) else ERROR
        values = [(str(k), str(v)) for k, v in stop.items()]
        self._diag(stop.get("ns", 0), stop.get("t", 0.0),
                   [("skinsafe/watchdog", level, stop.get("reason", "stopped"), values)])

    def _diag(self, ns: int, t: float, status: list) -> None:
        self._raw("/diagnostics", encode_diagnostics(t, status), ns)
