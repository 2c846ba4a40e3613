"""A 3D picture of a run rendered from its record's ROS 2 topics alone (what Foxglove's 3D panel is given): the links'
frames composed from `/tf`, the arm drawn as lines between them, the skin's points of `/skinsafe/skin` coloured by
force (turbo, 0 to the layout's `vmax`, as core/runtime/foxglove_layout.py colours them), the taxels the layers
retracted from (`/skinsafe/contacts`) circled in red. The frame shown: the skin message with the largest force.
Read by rosbags (ROS 2 Jazzy type store, the bag's own schemas); drawn with matplotlib (core/app/report_figures.py).

`python -m skinsafe.core.app.ros2_picture DIR FILE.png`
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from skinsafe.core.runtime.foxglove_layout import VMAX_N


def _stamp(header) -> int:
    return header.stamp.sec * 1_000_000_000 + header.stamp.nanosec


def _points(msg) -> np.ndarray:
    return np.frombuffer(bytes(msg.data), "<f4").reshape(msg.width, len(msg.fields))


def scene(folder: Path) -> dict:
    """The frame to draw: skin points (N, 4), contact points (K, 5), the arm's bones [(parent xyz, child xyz)], t."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    skin, contacts, tf = {}, {}, {}
    with AnyReader([folder], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        for con, _, raw in reader.messages([c for c in reader.connections
                                            if c.topic in ("/skinsafe/skin", "/skinsafe/contacts", "/tf")]):
            msg = reader.deserialize(raw, con.msgtype)
            if con.topic == "/tf":
                tf[_stamp(msg.transforms[0].header)] = msg
            else:
                (skin if con.topic == "/skinsafe/skin" else contacts)[_stamp(msg.header)] = _points(msg)
    if not skin:
        raise ValueError(f"{folder}: no /skinsafe/skin in the record; record a run with `skinsafe run --record DIR`")
    at = max(skin, key=lambda k: float(np.nanmax(skin[k][:, 3], initial=0.0)))
    pose = {"world": (Rotation.identity(), np.zeros(3))}
    edges = {t.child_frame_id: t for t in tf[at].transforms}

    def place(frame):
        if frame not in pose:
            t = edges[frame]
            R0, p0 = place(t.header.frame_id)
            r, v = t.transform.rotation, t.transform.translation
            pose[frame] = (R0 * Rotation.from_quat([r.x, r.y, r.z, r.w]), R0.apply([v.x, v.y, v.z]) + p0)
        return pose[frame]

    bones = [(place(t.header.frame_id)[1], place(c)[1]) for c, t in edges.items()]
    return {"skin": skin[at], "contacts": contacts.get(at, np.zeros((0, 5), np.float32)), "bones": bones, "t": at * 1e-9}


def picture(folder: Path, path: Path, vmax: float = VMAX_N) -> Path:
    """Draw `scene(folder)` (two views) into `path`."""
    from skinsafe.core.app.report_figures import _plt, save

    s = scene(folder)
    plt = _plt()
    pts, hit = s["skin"], s["contacts"]
    fig = plt.figure(figsize=(11, 5))
    ends = np.array([x for bone in s["bones"] for x in bone])
    lo, hi = np.minimum(pts[:, :3].min(0), ends.min(0)), np.maximum(pts[:, :3].max(0), ends.max(0))
    for i, (elev, azim) in enumerate(((25, -50), (25, 40))):
        ax = fig.add_subplot(1, 2, i + 1, projection="3d")
        for a, b in s["bones"]:
            ax.plot(*np.stack([a, b]).T, color="0.55", lw=2)
        order = np.argsort(np.nan_to_num(pts[:, 3]))  # the pressed taxels drawn last, larger
        p = pts[order]
        sc = ax.scatter(*p[:, :3].T, c=p[:, 3], cmap="turbo", s=2 + 120 * np.clip(p[:, 3] / vmax, 0, 1), vmin=0,
                        vmax=vmax, depthshade=False)
        ax.scatter(*hit[:, :3].T, s=60, facecolors="none", edgecolors="red", linewidths=1.2)
        ax.view_init(elev, azim)
        ax.set_box_aspect(hi - lo + 1e-3)
        for axis, name in zip((ax.set_xlabel, ax.set_ylabel, ax.set_zlabel), "xyz"):
            axis(f"{name} (m)")
    fig.colorbar(sc, ax=fig.axes, shrink=0.7, label="taxel force (N), /skinsafe/skin")
    fig.suptitle(f"{folder.name} at t = {s['t']:.3f} s: {len(pts)} taxels on /tf's links, the most force "
                 f"{float(np.nanmax(pts[:, 3])):.1f} N, {len(hit)} retracted from (red); rendered by skinsafe from the "
                 "record's topics", fontsize=9)
    return save(fig, path)


def main(argv: list[str]) -> int:
    if len(argv) != 2:
        print("usage: python -m skinsafe.core.app.ros2_picture DIR FILE.png", file=sys.stderr)
        return 2
    try:
        print(picture(Path(argv[0]), Path(argv[1])))
    except (ValueError, OSError) as e:
        print(f"ros2_picture: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
