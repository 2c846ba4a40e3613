"""A record folder whose writer died (killed, out of memory) finished from what reached the disk.

The writer (core/runtime/record.py) writes `DIR.part/DIR_0.mcap` and renames the folder into place only when it
finishes; a writer that dies leaves an MCAP without its summary, footer and last chunk, that indexed readers
(rosbags, `ros2 bag`) refuse. `recover` reads it front to back without seeking (mcap's StreamReader, CRCs checked)
up to the unfinished end, writes each schema, channel, metadata and message it holds into a finished MCAP with
`metadata.yaml` beside it (core/runtime/rosbag2.py) in `DIR.recovering`, marks it (metadata `skinsafe_recovered`:
why, the messages kept) and renames it to `DIR` (an earlier record there replaced, as a finished one would): what
was in the writer's memory (at most its open chunk, a MiB of messages, and its file buffer) is lost, every message
before it is kept. The run's parent calls it when its writer died, and at the start of a record whose folder's
`.part` a run that died left behind (into `DIR-recovered-<its time>`: core/app/record_writer.py).
"""
from __future__ import annotations

import os
import shutil
from pathlib import Path

from mcap.exceptions import McapError
from mcap.records import Channel, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap.well_known import Profile
from mcap.writer import CompressionType, Writer

from skinsafe.core.runtime import rosbag2
from skinsafe.core.runtime.ros2_topics import LATCHED


def recover(path: str | Path, reason: str, into: str | Path | None = None) -> dict:
    """Finish `path`.part as the record `into` (default `path`; module docstring): {path, written (messages kept)}."""
    path = Path(path)
    dest = Path(into or path)
    part, tmp = path.with_name(path.name + ".part"), dest.with_name(dest.name + ".recovering")
    name = rosbag2.mcap_name(dest)
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir()
    schemas, channels, types, counts = {}, {}, {}, {}
    first = last = None
    with open(part / rosbag2.mcap_name(path), "rb") as f, open(tmp / name, "wb") as out:
        w = Writer(out, compression=CompressionType.LZ4)
        w.start(profile=Profile.ROS2, library="skinsafe (recovered)")
        try:
            for r in StreamReader(f, validate_crcs=True).records:
                if isinstance(r, Schema):
                    schemas[r.id] = (w.register_schema(r.name, r.encoding, r.data), r.name)
                elif isinstance(r, Channel):
                    sid, typ = schemas[r.schema_id]
                    channels[r.id] = (w.register_channel(r.topic, r.message_encoding, sid, r.metadata), r.topic)
                    types[r.topic], counts[r.topic] = typ, 0
                elif isinstance(r, Metadata):
                    w.add_metadata(r.name, r.metadata)
                elif isinstance(r, Message):
                    cid, topic = channels[r.channel_id]
                    w.add_message(cid, log_time=r.log_time, data=r.data, publish_time=r.publish_time,
                                  sequence=r.sequence)
                    counts[topic] += 1
                    first = r.log_time if first is None else min(first, r.log_time)
                    last = r.log_time if last is None else max(last, r.log_time)
        except McapError:  # the unfinished end: a record cut short, no footer
            pass
        kept = sum(counts.values())
        w.add_metadata("skinsafe_recovered", {"reason": reason, "messages": str(kept)})
        w.finish()
    rosbag2.write_metadata(tmp, name, types, counts, LATCHED, first or 0, last or 0)
    if dest.is_dir():
        shutil.rmtree(dest)
    elif dest.exists():
        dest.unlink()
    os.replace(tmp, dest)
    shutil.rmtree(part)
    return {"path": str(dest), "written": kept}
