"""`skinsafe run --foxglove [PORT]`: the run live in Foxglove, over its WebSocket protocol (foxglove-sdk's server).

The same ROS 2 topics the record holds (core/runtime/ros2_topics.py, plus `/joint_states` and
`/skinsafe/command`), CDR with their ros2msg schemas, so Foxglove's 3D panel shows the robot from
`/robot_description` and `/tf` with the skin coloured by force. A thread samples `latest` (`rate_hz`, the
newest tick) and encodes and logs that tick's messages; the latched ones (the URDF, the taxel links) go out
again to each new subscriber. `skinsafe run --foxglove` runs it in a process of its own (core/app/foxglove_serve.py)
fed by the loop's shared tick (core/runtime/view_share.py): in the loop's process its encoding shared the loop's
interpreter lock, and the tick period's p99 rose by half with a client connected (`skinsafe bench runtime
--view foxglove`).
"""
from __future__ import annotations

import threading
import time
from collections.abc import Callable

from foxglove.websocket import ServerListener

from skinsafe.core.runtime.ros2_msgs import JointStateEncoder, schema
from skinsafe.core.runtime.ros2_topics import LATCHED, TOPICS, Ros2Topics
from skinsafe.core.runtime.tick import Tick

JOINT_TOPICS = {"/joint_states": "sensor_msgs/msg/JointState", "/skinsafe/command": "sensor_msgs/msg/JointState"}
RATE_HZ = 30.0


class FoxgloveLive:
    """A Foxglove WebSocket server at `host:port` (0: any free one, see `port`) fed by `latest()` (the newest tick,
    None before the first); `close()` ends it."""

    def __init__(self, topics: Ros2Topics, joint_names: list[str], latest: Callable[[], Tick | None], port: int,
                 host: str = "127.0.0.1", rate_hz: float = RATE_HZ):
        import foxglove

        self.topics, self.latest, self.period = topics, latest, 1.0 / rate_hz
        self.joints = JointStateEncoder(joint_names)
        self.context = foxglove.Context()
        self.channels = {topic: foxglove.Channel(topic, message_encoding="cdr", context=self.context,
                                                 schema=foxglove.Schema(name=typ, encoding="ros2msg",
                                                                        data=schema(typ).encode()))
                         for topic, typ in (TOPICS | JOINT_TOPICS).items()}
        self.static = dict(topics.static())  # before serving: the robot's meshes are decimated once, in seconds
        self.resend = set(LATCHED)  # latched topics a new subscriber is owed
        self.subscriptions = _Subscriptions(self.resend)
        self.server = foxglove.start_server(name="skinsafe", host=host, port=port, context=self.context,
                                            server_listener=self.subscriptions)
        self.port = self.server.port
        self.sent = 0
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._work, name="foxglove", daemon=True)
        self.thread.start()

    def close(self) -> None:
        self._stop.set()
        self.thread.join()
        self.server.stop()

    def _work(self) -> None:
        last = None
        while not self._stop.wait(self.period):
            while self.resend:
                topic = self.resend.pop()
                self._log(topic, self.static[topic])
            if not self.subscriptions.count:  # nobody watching: no tick taken (the loop then shares none)
                continue
            k = self.latest()
            if k is None or k is last:
                continue
            last = k
            for topic, data in self.topics.tick(k, every=True):
                self._log(topic, data)
            self._log("/joint_states", self.joints(k.t, k.q, () if k.qd is None else k.qd))
            self._log("/skinsafe/command", self.joints(k.t, (), k.command))

    def _log(self, topic: str, data: bytes) -> None:
        self.channels[topic].log(data, log_time=time.time_ns())
        self.sent += 1


class _Subscriptions(ServerListener):
    """Counts the clients' subscriptions and marks a latched topic owed when a client subscribes to it (called on
    the server's thread)."""

    def __init__(self, owed: set):
        self.owed, self.count = owed, 0

    def on_subscribe(self, client, channel) -> None:
        self.count += 1
        if channel.topic in LATCHED:
            self.owed.add(channel.topic)

    def on_unsubscribe(self, client, channel) -> None:
        self.count -= 1
