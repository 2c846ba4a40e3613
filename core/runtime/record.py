"""The run's record: MCAP with ROS 2 message schemas (Foxglove and ROS 2 tools open it), record version 3.

Topics (log time: host wall clock; header stamps: the robot's clock):
- `/joint_states` (sensor_msgs/msg/JointState): measured q and qd, every tick;
- `/skinsafe/command` (sensor_msgs/msg/JointState, velocity): the joint velocity sent, every tick
  (zero on the tick a watchdog stopped the robot);
- `/skinsafe/planned` (sensor_msgs/msg/JointState, velocity): the command source's output, every tick;
- `/skinsafe/forces` (skinsafe_msgs/msg/TaxelForces): the (N,) taxel forces the layers saw (N, after tare;
  excluded taxels 0; float64, the taxel map's order, so a replay is exact), whenever a new reading arrived;
- `/skinsafe/tick` (skinsafe_msgs/msg/Tick): the robot's clock, the measured dt, the reading's sequence number,
  the tick's number and whether the stack ticked (false: the stop), every tick, after the tick's other topics;
- `/skinsafe/state` (skinsafe_msgs/msg/LayerState): danger potential, speed factor, retracting, the taxel ids
  retracted from (highest priority first; metadata `skinsafe_taxels` maps ids to the map's order), flags, stop,
  every tick after its `/skinsafe/tick`;
- `/skinsafe/obstacles` (geometry_msgs/msg/PoseArray, `world`): per tick, the pose of each of the metadata's
  `obstacles`, in order, where they move (an experiment's person, written by core/runtime/sim_record.py);
  absent from runs (their obstacles stand still);
- `/diagnostics` (diagnostic_msgs/msg/DiagnosticArray): layers (retracting, pool, flags), skin (board
  ages, frames lost), command (source age) at 10 Hz and on every change of the layers' flags; the
  watchdog's stop (level ERROR, its reason) once at the end.
With `topics` (`skinsafe run --record DIR`) the record is a rosbag2 folder a ROS 2 user plays
(core/runtime/rosbag2.py: DIR/metadata.yaml beside DIR/DIR_0.mcap) and it also holds the ROS 2 tools' topics
(core/runtime/ros2_topics.py: `/robot_description`, `/tf_static`, `/tf`, `/skinsafe/tactile`, `/skinsafe/skin`,
`/skinsafe/contacts`, `/rosout`), telemetry like the forces; without (an experiment's record,
core/runtime/sim_record.py) a bare FILE.mcap. Records of versions 1 and 2 held the tick, the forces, the layers
and the obstacles as std_msgs/Float64MultiArray; core/runtime/record_read.py reads every version.
Metadata `skinsafe` holds the configuration a replay needs (map, limits, period, excluded taxels, ...,
`record_version`) and, as `run`, the run's whole configuration as given (core/runtime/run_config.py
`RunConfig.to_json`).

The loop only enqueues (`put`, never blocks): a writer thread encodes and writes. `skinsafe run` runs the recorder
in a writer process of its own (core/app/record_writer.py), fed through shared memory, so that its encoding does not
share the loop's interpreter lock; that process's ring is the loop's queue. When the writer is
behind (`queue_size` ticks waiting) a tick's telemetry (its taxel forces, state, diagnostics) is dropped
and counted (`dropped`, in the record's last diagnostics; the replay then says the record is incomplete);
its safety topics (`/joint_states`, `/skinsafe/command`, `/skinsafe/planned`, `/skinsafe/tick`) never are:
every tick, the stop's and the ramp's after it included, is in the record.
Messages are CDR-encoded by core/runtime/ros2_msgs.py and written with `mcap`'s writer (ros2 profile, LZ4
chunks). The file (the folder) is written as FILE.part and renamed when complete.
"""
from __future__ import annotations

import json
import os
import queue
import shutil
import threading
import time
from pathlib import Path

import numpy as np
from mcap.well_known import MessageEncoding, Profile, SchemaEncoding
from mcap.writer import CompressionType, Writer

from skinsafe.core.runtime import ros2_msgs as msgs
from skinsafe.core.runtime import rosbag2
from skinsafe.core.runtime.record_read import TAXEL_IDS
from skinsafe.core.runtime.ros2_topics import LATCHED, WORLD, Ros2Topics, state
from skinsafe.core.runtime.ros2_topics import TOPICS as ROS2_TOPICS
from skinsafe.core.runtime.tick import Tick

TOPICS = {"/joint_states": "sensor_msgs/msg/JointState", "/skinsafe/command": "sensor_msgs/msg/JointState",
          "/skinsafe/planned": "sensor_msgs/msg/JointState", "/skinsafe/forces": "skinsafe_msgs/msg/TaxelForces",
          "/skinsafe/tick": "skinsafe_msgs/msg/Tick", "/skinsafe/state": "skinsafe_msgs/msg/LayerState",
          "/diagnostics": "diagnostic_msgs/msg/DiagnosticArray"}
OBSTACLES = ("/skinsafe/obstacles", "geometry_msgs/msg/PoseArray")  # registered with its first message
DIAG_EVERY_S = 0.1
OK, WARN, ERROR = 0, 1, 2


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
        self.file = open(self.part / rosbag2.mcap_name(self.path) if topics else self.part, "wb")
        self.writer = Writer(self.file, compression=CompressionType.LZ4)
        self.writer.start(profile=Profile.ROS2, library="skinsafe")
        self.types = dict(TOPICS) | (ROS2_TOPICS if topics else {})
        self.schemas = {}
        self.channels = {topic: self._channel(topic, name) for topic, name in self.types.items()}
        self.counts = dict.fromkeys(self.types, 0)
        self.writer.add_metadata("skinsafe", {"config": json.dumps(config | {"record_version": rosbag2.RECORD_VERSION})})
        if topics is not None:
            self.writer.add_metadata(TAXEL_IDS, {"ids": ",".join(map(str, topics.ids.tolist()))})
        self.joints = msgs.JointStateEncoder(joint_names)
        self.state = topics.state if topics else state
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

    def _channel(self, topic: str, name: str) -> int:
        if name not in self.schemas:
            self.schemas[name] = self.writer.register_schema(name, SchemaEncoding.ROS2, msgs.schema(name).encode())
        return self.writer.register_channel(topic, MessageEncoding.CDR, self.schemas[name],
                                            {"offered_qos_profiles": rosbag2.qos_text(topic in LATCHED)})

    def _raw(self, topic: str, data: bytes, ns: int) -> None:
        self.writer.add_message(self.channels[topic], log_time=ns, data=data, publish_time=ns, sequence=self.written)
        self.written += 1
        self.counts[topic] += 1
        self.last_ns = max(self.last_ns, ns)

    def _joints(self, k: Tick) -> None:
        """A tick's joint states: measured, planned, sent."""
        t, ns = k.t, k.ns
        self._raw("/joint_states", self.joints(t, k.q, np.zeros_like(k.q) if k.qd is None else k.qd), ns)
        self._raw("/skinsafe/planned", self.joints(t, (), k.command if k.planned is None else k.planned), ns)
        self._raw("/skinsafe/command", self.joints(t, (), k.command), ns)

    def _tick_msg(self, k: Tick) -> None:
        self._raw("/skinsafe/tick", msgs.tick(k.t, k.dt, k.reading_seq, k.index, k.ticked), k.ns)

    def _safety(self, k: Tick) -> None:
        """A tick's safety topics (module docstring)."""
        self._joints(k)
        self._tick_msg(k)

    def _tick(self, k: Tick) -> None:
        """One tick: its forces only when new, its obstacles' poses when they move."""
        ns, t = k.ns, k.t
        self._joints(k)
        if k.force_new and k.force is not None:
            self._raw("/skinsafe/forces", msgs.taxel_forces(t, k.force), ns)
        if k.obstacles is not None:
            topic, name = OBSTACLES
            if topic not in self.channels:
                self.channels[topic], self.types[topic], self.counts[topic] = self._channel(topic, name), name, 0
            self._raw(topic, msgs.pose_array(t, WORLD, k.obstacles), ns)
        self._tick_msg(k)
        self._raw("/skinsafe/state", self.state(k), ns)
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
        self._raw("/diagnostics", msgs.diagnostics(t, status), ns)
