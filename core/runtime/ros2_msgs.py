"""ROS 2 messages for the record and the live Foxglove stream: their schema texts and CDR encoders.

Schemas come from rosbags' ROS 2 Jazzy type store (`schema`, `type_hash`: the text and RIHS01 hash a
rosbag2 stores), plus packages a ROS install may lack, registered from their message definitions so the
record carries them: `tactile_msgs/msg/TactileState` (ubi-agni's tactile_toolbox: a header and named
sensor arrays, `sensor_msgs/ChannelFloat32`) and skinsafe's own: `LayerState` (the safety layers' state as
named fields), `Tick` (a control tick: the robot's clock as the layers saw it, the stamp being it rounded to
nanoseconds) and `TaxelForces` (a reading as the layers saw it, float64 in the taxel map's order: what a
replay needs exactly; TactileState's float32 is for viewers). One encoder per message type, little-endian
CDR with numpy for the arrays (rosbags' serializer gives the same bytes, tested; it builds a Python object
per element, milliseconds for a skin's thousands of taxels).
"""
from __future__ import annotations

import functools
import math
import struct

import numpy as np

TACTILE_STATE = "std_msgs/Header header\nsensor_msgs/ChannelFloat32[] sensors\n"
LAYER_STATE = ("std_msgs/Header header\nfloat64 potential\nfloat64 speed_factor\nbool retracting\n"
               "uint32[] pool_taxels\nstring[] flags\nstring stop\n")
TICK = "std_msgs/Header header\nfloat64 t\nfloat64 dt\nfloat64 reading_seq\nuint64 index\nbool ticked\n"
TAXEL_FORCES = "std_msgs/Header header\nfloat64[] force\n"
PACKAGES = {"tactile_msgs/msg/TactileState": TACTILE_STATE, "skinsafe_msgs/msg/LayerState": LAYER_STATE,
            "skinsafe_msgs/msg/Tick": TICK, "skinsafe_msgs/msg/TaxelForces": TAXEL_FORCES}
CDR_LE = b"\x00\x01\x00\x00"
FLOAT32 = 7  # sensor_msgs/PointField datatype
LOG_INFO, LOG_WARN, LOG_ERROR = 20, 30, 40  # rcl_interfaces/msg/Log levels
TRIANGLE_LIST, ADD = 11, 0  # visualization_msgs/msg/Marker type and action


@functools.cache
def typestore():
    """rosbags' ROS 2 Jazzy type store with `PACKAGES` registered."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    for name, text in PACKAGES.items():
        store.register(get_types_from_msg(text, name))
    return store


def schema(name: str) -> str:
    """The ros2msg schema text of message type `name` (e.g. "tf2_msgs/msg/TFMessage"), its dependencies appended."""
    return typestore().generate_msgdef(name, ros_version=2)[0]


def type_hash(name: str) -> str:
    """The type's RIHS01 hash (rosbag2's `type_description_hash`)."""
    return typestore().hash_rihs01(name)


class Cdr:
    """One message's CDR bytes, built field by field (alignment counted from after the encapsulation header)."""

    def __init__(self, start: bytes = CDR_LE):
        self.buf = bytearray(start)

    def align(self, n: int) -> Cdr:
        self.buf += b"\0" * (-(len(self.buf) - 4) % n)
        return self

    def pack(self, fmt: str, *values, size: int = 4) -> Cdr:
        self.align(size)
        self.buf += struct.pack("<" + fmt, *values)
        return self

    def string(self, s: str) -> Cdr:
        b = s.encode() + b"\0"
        self.pack("I", len(b))
        self.buf += b
        return self

    def header(self, t: float, frame: str = "") -> Cdr:
        return self.pack("iI", *_sec_ns(t)).string(frame)

    def array(self, x: np.ndarray, dtype: str) -> Cdr:
        """A sequence of numbers: its length, then the numbers as `dtype` ("<f4", "<f8", "<u4", "u1")."""
        x = np.ascontiguousarray(x, dtype)
        self.pack("I", len(x))
        if len(x):
            self.align(x.itemsize)
            self.buf += x.tobytes()
        return self

    def bytes(self) -> bytes:
        return bytes(self.buf)


class JointStateEncoder:
    """sensor_msgs/msg/JointState for one robot's joint names (laid out once: a message writes its stamp and
    numbers)."""

    def __init__(self, names: list[str], frame: str = ""):
        c = Cdr().header(0.0, frame).pack("I", len(names))
        for n in names:
            c.string(n)
        self.head = bytes(c.buf)

    def __call__(self, t: float, position=(), velocity=(), effort=()) -> bytes:
        c = Cdr(self.head)
        struct.pack_into("<iI", c.buf, 4, *_sec_ns(t))
        for x in (position, velocity, effort):
            c.array(np.asarray(x, float), "<f8")
        return c.bytes()


def diagnostics(t: float, status: list) -> bytes:
    """diagnostic_msgs/msg/DiagnosticArray: `status` = [(name, level, message, [(key, value)])], from skinsafe."""
    c = Cdr().header(t).pack("I", len(status))
    for name, level, message, values in status:
        c.pack("B", level, size=1).string(name).string(message).string("skinsafe").pack("I", len(values))
        for k, v in values:
            c.string(k).string(v)
    return c.bytes()


def tick(t: float, dt: float, reading_seq: float, index: int, ticked: bool) -> bytes:
    """skinsafe_msgs/msg/Tick (`TICK`)."""
    return Cdr().header(t).pack("ddd", t, dt, reading_seq, size=8).pack("Q", index, size=8).pack(
        "B", bool(ticked), size=1).bytes()


def taxel_forces(t: float, force: np.ndarray) -> bytes:
    """skinsafe_msgs/msg/TaxelForces (`TAXEL_FORCES`)."""
    return Cdr().header(t).array(force, "<f8").bytes()


def pose_array(t: float, frame: str, poses: np.ndarray) -> bytes:
    """geometry_msgs/msg/PoseArray of (P, 7) poses: position, quaternion w x y z."""
    poses = np.asarray(poses, float).reshape(-1, 7)
    c = Cdr().header(t, frame).pack("I", len(poses))
    if len(poses):
        c.align(8).buf += np.ascontiguousarray(poses[:, [0, 1, 2, 4, 5, 6, 3]], "<f8").tobytes()
    return c.bytes()


def triangle_markers(t: float, markers: list[tuple]) -> bytes:
    """visualization_msgs/msg/MarkerArray of TRIANGLE_LIST markers locked to their frames: each (frame, ns, id, pose
    (x y z, qw qx qy qz in the frame), rgba, triangles (T, 3, 3) m in the pose)."""
    c = Cdr().pack("I", len(markers))
    for frame, ns, mid, pose, rgba, tri in markers:
        x, y, z, qw, qx, qy, qz = pose
        c.header(t, frame).string(ns).pack("iii", mid, TRIANGLE_LIST, ADD)
        c.pack("10d", x, y, z, qx, qy, qz, qw, 1.0, 1.0, 1.0, size=8).pack("4f", *rgba).pack("iI", 0, 0)
        points = np.ascontiguousarray(tri, "<f8").reshape(-1, 3)
        c.pack("B", 1, size=1).pack("I", len(points))
        if len(points):
            c.align(8).buf += points.tobytes()
        c.pack("I", 0).string("").header(0.0).string("").pack("I", 0)  # colors, texture_resource, texture
        c.pack("I", 0).string("").string("").string("").pack("I", 0).pack("B", 0, size=1)  # uv, text, mesh
    return c.bytes()


def string_msg(text: str) -> bytes:
    """std_msgs/msg/String."""
    return Cdr().string(text).bytes()


def tf_message(t: float, parents: list[str], children: list[str], xyz: np.ndarray, quat_xyzw: np.ndarray) -> bytes:
    """tf2_msgs/msg/TFMessage: one TransformStamped per child (translation (K, 3) m, rotation (K, 4) x y z w)."""
    return TfEncoder(parents, children)(t, xyz, quat_xyzw)


class TfEncoder:
    """`tf_message` for fixed frames, laid out once: a message writes its stamps and numbers in place (a tick's
    /tf in microseconds)."""

    def __init__(self, parents: list[str], children: list[str]):
        c = Cdr().pack("I", len(children))
        stamps, numbers = [], []
        for parent, child in zip(parents, children):
            c.align(4)
            stamps.append(len(c.buf))
            c.header(0.0, parent).string(child).align(8)
            numbers.append(len(c.buf))
            c.buf += bytes(56)
        self.template = bytes(c.buf)
        self.stamps = (np.asarray(stamps, np.intp)[:, None] + np.arange(8)).ravel()
        self.numbers = (np.asarray(numbers, np.intp)[:, None] + np.arange(56)).ravel()
        self.n = len(children)

    def __call__(self, t: float, xyz: np.ndarray, quat_xyzw: np.ndarray) -> bytes:
        buf = np.frombuffer(bytearray(self.template), np.uint8)
        buf[self.stamps] = np.tile(np.frombuffer(struct.pack("<iI", *_sec_ns(t)), np.uint8), self.n)
        pose = np.empty((self.n, 7), "<f8")
        pose[:, :3], pose[:, 3:] = xyz, quat_xyzw
        buf[self.numbers] = pose.view(np.uint8).ravel()
        return buf.tobytes()


def point_cloud(t: float, frame: str, fields: tuple[str, ...], points: np.ndarray) -> bytes:
    """sensor_msgs/msg/PointCloud2: one row of K points, `fields` float32 each ((K, len(fields)) values)."""
    points = np.ascontiguousarray(points, "<f4").reshape(-1, len(fields))
    c = Cdr().header(t, frame).pack("III", 1, len(points), len(fields))
    for i, name in enumerate(fields):
        c.string(name).pack("I", 4 * i).pack("B", FLOAT32, size=1).pack("I", 1)
    step = 4 * len(fields)
    c.pack("B", 0, size=1).pack("II", step, step * len(points))
    return c.array(points.reshape(-1).view(np.uint8), "u1").pack("B", 1, size=1).bytes()


def tactile_state(t: float, names: list[str], values: list[np.ndarray]) -> bytes:
    """tactile_msgs/msg/TactileState: one named ChannelFloat32 per sensor array."""
    c = Cdr().header(t).pack("I", len(names))
    for name, v in zip(names, values):
        c.string(name).array(v, "<f4")
    return c.bytes()


class TactileEncoder:
    """`tactile_state` for fixed sensors, laid out once: sensor j holds `sizes[j]` values, taxel i's value goes to
    sensor `sensor[i]` at `index[i]`, the rest NaN; a message writes the forces in place (one scatter)."""

    def __init__(self, names: list[str], sizes: list[int], sensor: np.ndarray, index: np.ndarray):
        c = Cdr().header(0.0).pack("I", len(names))
        starts = []
        for name, size in zip(names, sizes):
            c.string(name).pack("I", size)
            starts.append(len(c.buf) // 4)  # float32 slots: 4-aligned after the header, so whole words
            c.buf += np.full(size, np.nan, "<f4").tobytes()
        self.template = bytes(c.buf)
        self.slots = np.asarray(starts, np.intp)[np.asarray(sensor, np.intp)] + np.asarray(index, np.intp)

    def __call__(self, t: float, force: np.ndarray) -> bytes:
        buf = bytearray(self.template)
        struct.pack_into("<iI", buf, 4, *_sec_ns(t))
        np.frombuffer(buf, "<f4")[self.slots] = force
        return bytes(buf)


def layer_state(t: float, potential: float, speed_factor: float, retracting: bool, pool_taxels: np.ndarray,
                flags: tuple[str, ...], stop: str) -> bytes:
    """skinsafe_msgs/msg/LayerState (`LAYER_STATE`)."""
    c = Cdr().header(t).pack("dd", potential, speed_factor, size=8).pack("B", bool(retracting), size=1)
    c.array(pool_taxels, "<u4").pack("I", len(flags))
    for f in flags:
        c.string(f)
    return c.string(stop).bytes()


def log(t: float, level: int, name: str, message: str) -> bytes:
    """rcl_interfaces/msg/Log (what Foxglove's Log panel lists)."""
    c = Cdr().pack("iI", *_sec_ns(t)).pack("B", level, size=1)
    for s in (name, message, "", ""):
        c.string(s)
    return c.pack("I", 0).bytes()


def _sec_ns(t: float) -> tuple[int, int]:
    sec = math.floor(t)
    return sec, min(int(round((t - sec) * 1e9)), 999_999_999)
