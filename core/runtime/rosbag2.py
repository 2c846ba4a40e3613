"""A record as a rosbag2 folder that a ROS 2 user plays (`ros2 bag play DIR`) and Foxglove opens.

`DIR/metadata.yaml` (rosbag2 format version 9: each topic's type, RIHS01 type hash, offered QoS and message
count; the record's version in `custom_data`) beside `DIR/DIR_0.mcap` (storage `mcap`). Latched topics
(`/robot_description`, `/tf_static`) are offered transient local, so a late subscriber gets them on play.
Record versions (core/runtime/record_read.py reads each): 1, a bare `FILE.mcap` (skinsafe before the ROS 2
topics); 2, the folder, the tick, forces and layers still as Float64MultiArray; 3, those typed (the folder of a run,
a bare `FILE.mcap` of an experiment).
"""
from __future__ import annotations

from io import StringIO
from pathlib import Path

from skinsafe.core.runtime.ros2_msgs import type_hash

RECORD_VERSION = 3
METADATA = "metadata.yaml"


def mcap_name(folder: Path) -> str:
    """The MCAP's name in a record folder (rosbag2's `<folder>_0.mcap`)."""
    return f"{Path(folder).name}_0.mcap"


def is_record(source: str) -> bool:
    """Whether a viewer's `source` names a record (a folder, or a bare .mcap) rather than a live HOST:PORT."""
    return source.endswith(".mcap") or Path(source).is_dir()


def record_file(path: str | Path) -> Path:
    """The MCAP of a record: a folder's (version 2; its one .mcap, named as `mcap_name` when skinsafe wrote it), or
    `path` itself (a bare .mcap, version 1). Read without a YAML parser: Blender's add-on reads records too."""
    path = Path(path)
    if not path.is_dir():
        return path
    files = sorted(path.glob("*.mcap"))
    return path / mcap_name(path) if path / mcap_name(path) in files or not files else files[0]


def qos(latched: bool) -> list[dict]:
    """The QoS a topic is offered with, as rosbag2 writes it: reliable, keep last; latched ones transient local."""
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
    from rosbags.rosbag2.metadata import dump_qos_v9

    zero = QosTime(0, 0)
    q = Qos(QosHistory.KEEP_LAST, 1 if latched else 10, QosReliability.RELIABLE,
            QosDurability.TRANSIENT_LOCAL if latched else QosDurability.VOLATILE, zero, zero, QosLiveliness.AUTOMATIC,
            zero, False)
    return dump_qos_v9([q])


def qos_text(latched: bool) -> str:
    """`qos` as the YAML text an MCAP channel's `offered_qos_profiles` metadata holds."""
    return _yaml(qos(latched))


def write_metadata(folder: Path, file: str, topics: dict[str, str], counts: dict[str, int], latched,
                   start_ns: int, end_ns: int) -> Path:
    """`folder/metadata.yaml` for `file` holding `topics` ({name: type}) with `counts` messages each."""
    span = lambda: {"nanoseconds": max(0, end_ns - start_ns)}  # noqa: E731 (a new dict each: YAML without anchors)
    start = lambda: {"nanoseconds_since_epoch": start_ns}  # noqa: E731
    total = sum(counts.values())
    info = {"version": 9, "storage_identifier": "mcap", "relative_file_paths": [file], "duration": span(),
            "starting_time": start(), "message_count": total,
            "topics_with_message_count": [
                {"topic_metadata": {"name": name, "type": typ, "serialization_format": "cdr",
                                    "offered_qos_profiles": qos(name in latched), "type_description_hash": type_hash(typ)},
                 "message_count": counts.get(name, 0)} for name, typ in topics.items()],
            "compression_format": "", "compression_mode": "",
            "files": [{"path": file, "starting_time": start(), "duration": span(), "message_count": total}],
            "custom_data": {"skinsafe_record_version": str(RECORD_VERSION)}, "ros_distro": "jazzy"}
    path = Path(folder) / METADATA
    path.write_text(_yaml({"rosbag2_bagfile_information": info}))
    return path


def _yaml(data) -> str:
    from ruamel.yaml import YAML  # rosbags' YAML library

    yaml = YAML(typ="safe")
    yaml.default_flow_style = False
    out = StringIO()
    yaml.dump(data, out)
    return out.getvalue()
