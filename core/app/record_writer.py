"""`skinsafe run --record DIR`'s writer process: the record's encoding and writing (core/runtime/record.py
`Recorder`, with the ROS 2 topics) outside the loop's process, fed every tick through a shared-memory ring
(core/runtime/view_share.py `SharedFrames` with slots, forces float64). In the loop's process its encoding shared
the loop's interpreter lock: `skinsafe bench runtime --view record` measured the tick period's p99 +50% (4,083
taxels) and +72% (16,331) against `--view off`.

The loop only copies a tick's arrays into the ring (`RecordFeed.put`, never waiting). When the ring is full (the
writer behind) the tick's telemetry is dropped and counted, and its safety topics wait in the loop's backlog (the
tick's own arrays, which nobody writes again) until the ring has room: every tick's joint state, command and tick
message reaches the record, the stop's and the ramp's to rest included. `close(stop)` hands the backlog over, sends
the stop and waits for the writer to finish the folder; a writer that died is named in the result's `error`, and
what it had written is recovered into the folder (core/runtime/record_recover.py; `recovered`: its path).

`start(...)` starts `python -m skinsafe.core.app.record_writer SHM SLOTS MAP DIR JOINT...` on the normal scheduler
at nice 0 (core/realtime.py `background`: not the loop's real-time priority; at the view's nice 10 on a loaded 2-core
host it fell behind and dropped the telemetry of 10-55% of 16,331-taxel ticks); `begin(config)` sends the record's
configuration on its stdin and returns once the writer is ready (an OSError naming the folder when it cannot write it). The writer ignores Ctrl+C (the run's handler stops the
robot; the writer still gets the stop) and, when its run ends without a stop, finishes the record saying so.
"""
from __future__ import annotations

import functools
import json
import os
import select
import signal
import subprocess
import sys
import time
from collections import deque
from pathlib import Path

from skinsafe.core.realtime import background
from skinsafe.core.runtime.record_recover import recover
from skinsafe.core.runtime.rosbag2 import mcap_name
from skinsafe.core.runtime.tick import Tick
from skinsafe.core.runtime.view_share import SharedFrames

RING_BYTES = 64 << 20  # the ring's shared memory: ~330 ticks of 16,331 taxels, ~1,300 of 4,083
MIN_SLOTS = 64


class RecordFeed:
    """The loop's side of the writer process (module docstring): `put` each tick, `close` once."""

    def __init__(self, frames: SharedFrames, proc: subprocess.Popen, path: Path, recovered_part: dict | None = None):
        self.frames, self.proc, self.path = frames, proc, path
        self.backlog: deque[Tick] = deque()
        self.dropped = 0
        self.result: dict | None = None
        self.recovered_part = recovered_part  # `start`'s recovery of a dead run's record (path, written), if any
        self.begun = False

    def begin(self, config: dict) -> None:
        """The record's configuration to the writer; returns once the writer is ready (an OSError naming why not)."""
        self.proc.stdin.write((json.dumps(config) + "\n").encode())
        self.proc.stdin.flush()
        line = self.proc.stdout.readline().decode().strip()
        if line != "ready":
            self.proc.stdin.close()
            self.proc.wait(10)
            self.frames.close()
            self.result = {"written": 0, "dropped": 0, "error": line}
            raise OSError(line.removeprefix("error ") or
                          f"the record's writer process did not start (exit {self.proc.returncode})")
        self.begun = True

    def put(self, tick: Tick) -> None:
        """Copy the tick into the ring, never waiting: when it is full, only its safety topics, later (module docstring)."""
        while self.backlog and self.frames.push(self.backlog[0], telemetry=False):
            self.backlog.popleft()
        if not self.backlog and self.frames.push(tick):
            return
        self.dropped += 1
        if self.backlog or not self.frames.push(tick, telemetry=False):
            if self.proc.poll() is None:  # a writer that died reads nothing more: its error is named at `close`
                self.backlog.append(Tick(t=tick.t, q=tick.q, qd=tick.qd, dt=tick.dt, command=tick.command,
                                         planned=tick.planned, reading_seq=tick.reading_seq, stop=tick.stop,
                                         flags=tick.flags, ticked=tick.ticked, index=tick.index, ns=tick.ns))

    def close(self, stop: dict | None = None) -> dict:
        """Hand over the backlog, send the stop (reason, kind, stats: the record's last diagnostics), wait for the
        folder; {written, dropped, path} or {written, dropped, error}."""
        if self.result is not None:
            return self.result
        if not self.begun:  # the run ended before its record began (refused at its pre-flight): nothing written
            self.proc.stdin.close()
            self.proc.wait()
            self.frames.close()
            self.result = {"written": 0, "dropped": 0, "error": "the run ended before its record began"}
            return self.result
        while self.backlog and self.proc.poll() is None:
            if self.frames.push(self.backlog[0], telemetry=False):
                self.backlog.popleft()
            else:
                select.select([], [], [], 0.001)
        try:
            self.proc.stdin.write((json.dumps(stop or {}, default=str) + "\n").encode())
            self.proc.stdin.close()
        except OSError:  # the writer died: named below
            pass
        line = self.proc.stdout.readline()
        rc = self.proc.wait()
        self.frames.close()
        try:
            self.result = json.loads(line) | {"dropped": self.dropped}
        except ValueError:
            how = f"killed by signal {-rc}" if rc < 0 else f"exit {rc}"
            died = f"the record's writer process (pid {self.proc.pid}) died ({how})"
            try:
                kept = recover(self.path, died)
            except OSError as e:  # a folder that cannot be written
                self.result = {"written": 0, "dropped": self.dropped,
                               "error": f"{died}; {self.path.name}.part cannot be recovered ({e})"}
            else:
                self.result = {"written": kept["written"], "dropped": self.dropped, "recovered": kept["path"],
                               "error": f"{died}; recovered what it had written into {kept['path']}"}
        return self.result


def start(path: Path, map_path: Path, joint_names: list[str], boards: list[int], n_taxels: int,
          config: dict | None = None) -> RecordFeed:
    """The writer process of the record folder `path` and the loop's feed to it (module docstring). A `path`.part
    left by a run that died with its writer is recovered first, beside (`recovered_part`), not written over. The
    writer loads the robot and its topics at once; the record begins with `begin(config)` (here when `config` is
    given), so a run starts it before its pre-flight and the writer's start-up runs beside it."""
    part = Path(path).with_name(Path(path).name + ".part")
    recovered = None
    if (part / mcap_name(Path(path))).is_file():
        when = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime((part / mcap_name(Path(path))).stat().st_mtime))
        recovered = recover(path, "its run died before finishing it",
                            into=Path(path).with_name(f"{Path(path).name}-recovered-{when}"))
        print(f"skinsafe run: --record {path}: {part.name} is the unfinished record of a run that died; recovered "
              f"{recovered['written']} messages into {recovered['path']}", file=sys.stderr)
    slots = max(MIN_SLOTS, RING_BYTES // SharedFrames.size(n_taxels, len(joint_names), len(boards), 1, True))
    frames = SharedFrames.create(n_taxels, len(joint_names), boards, slots, exact=True)
    proc = subprocess.Popen([sys.executable, "-m", "skinsafe.core.app.record_writer", frames.name, str(slots),
                             str(map_path), str(path), *joint_names], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            preexec_fn=functools.partial(background, 0))
    feed = RecordFeed(frames, proc, Path(path), recovered)
    if config is not None:
        feed.begin(config)
    return feed


def _line(buf: bytearray) -> str | None:
    """A line from stdin (fd 0) once one is whole within 2 ms, '' at its end without one, None for now."""
    if b"\n" not in buf and select.select([0], [], [], 0.002)[0]:
        chunk = os.read(0, 1 << 16)
        if not chunk:
            return ""
        buf += chunk
    if b"\n" not in buf:
        return None
    line, _, rest = bytes(buf).partition(b"\n")
    buf[:] = rest
    return line.decode()


def _serve(argv: list[str]) -> int:
    from skinsafe.core.app.run_topics import ros2_topics
    from skinsafe.core.robot.models import load_robot, only_joints
    from skinsafe.core.runtime.record import Recorder
    from skinsafe.core.skin.taxel_map import load

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the run's handler stops the robot; the stop comes on stdin
    name, slots, map_path, path, *joints = argv
    map_path = Path(map_path)
    robot = load_robot(load(map_path).robot, base_dir=map_path.parent)
    design = load(map_path, robot.body_names)
    frames = SharedFrames.attach(name, design.n_taxels, len(joints), [b.uid for b in design.boards], int(slots), True)
    topics = ros2_topics(robot, only_joints(robot, joints), design)
    buf = bytearray()
    config = None
    while config is None:  # the run's pre-flight meanwhile
        config = _line(buf)
    if not config:  # the run ended before the record began
        frames.close()
        return 2
    try:
        rec = Recorder(path, joints, json.loads(config), topics=topics)
    except OSError as e:
        print(f"error {e.strerror or e}", flush=True)
        return 2
    print("ready", flush=True)
    stop = None
    while stop is None:
        taken = frames.take()
        if taken is not None:
            rec.put(taken[0], wait=True, telemetry=taken[1])
            continue
        line = _line(buf)
        if line is not None:
            stop = json.loads(line) if line else {"reason": "the run ended without closing its record", "kind": "fault"}
    while (taken := frames.take()) is not None:  # all the loop pushed before its stop
        rec.put(taken[0], wait=True, telemetry=taken[1])
    result = rec.close(stop)
    frames.close()
    print(json.dumps({k: v for k, v in result.items() if k != "dropped"}), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(_serve(sys.argv[1:]))
