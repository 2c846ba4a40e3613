"""`skinsafe run --foxglove`'s server process: the run's ROS 2 topics to Foxglove (core/runtime/foxglove_live.py)
from the loop's shared newest tick (core/runtime/view_share.py `SharedFrames`), outside the loop's process.

`start(frames, map_path, joint_names, port)` starts `python -m skinsafe.core.app.foxglove_serve SHM MAP PORT
JOINT...` at the view's low priority (core/realtime.py `background`) and returns (the process, its port) once it
serves; it rebuilds the robot and the URDF from the map, attaches to the block and serves until its parent ends.
"""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from skinsafe.core.runtime.view_share import SharedFrames, wait_for_parent


def start(frames: SharedFrames, map_path: Path, joint_names: list[str], port: int, preexec=None):
    """The server process and the port it serves on; OSError naming the port when it cannot serve."""
    proc = subprocess.Popen([sys.executable, "-m", "skinsafe.core.app.foxglove_serve", frames.name, str(map_path),
                             str(port), *joint_names], stdout=subprocess.PIPE, text=True, preexec_fn=preexec)
    line = proc.stdout.readline().strip()
    if not line.startswith("serving "):
        proc.wait(10)
        raise OSError(f"the Foxglove server did not start on port {port} (exit {proc.returncode}): {line or 'no line'}; "
                      "is the port in use? (--foxglove 0: any free one)")
    return proc, int(line.split()[1])


def _serve(argv: list[str]) -> int:
    from skinsafe.core.app.run_topics import ros2_topics
    from skinsafe.core.robot.models import load_robot, only_joints
    from skinsafe.core.runtime.foxglove_live import FoxgloveLive
    from skinsafe.core.skin.taxel_map import load

    name, map_path, port, *joints = argv
    map_path = Path(map_path)
    robot = load_robot(load(map_path).robot, base_dir=map_path.parent)
    design = load(map_path, robot.body_names)
    frames = SharedFrames.attach(name, design.n_taxels, len(joints), [b.uid for b in design.boards])
    try:
        live = FoxgloveLive(ros2_topics(robot, only_joints(robot, joints), design), joints, frames.newest, int(port))
    except RuntimeError as e:  # foxglove-sdk: the port taken
        print(f"error {e}", flush=True)
        return 2
    print(f"serving {live.port}", flush=True)
    wait_for_parent()
    live.close()
    frames.close()
    return 0


if __name__ == "__main__":
    sys.exit(_serve(sys.argv[1:]))
