"""The ROS 2 topics of a run (core/runtime/ros2_topics.py) as the record writer and the Foxglove server build them:
the arm's kinematics and the URDF of the robot with its skin (exporters/urdf.py, which core/runtime may not import)."""
from __future__ import annotations


def ros2_topics(robot, arm, design):
    """The run's ROS 2 topics: `arm`'s kinematics, the URDF of `robot` with its skin."""
    from skinsafe.core.runtime.ros2_topics import Ros2Topics
    from skinsafe.exporters.urdf import build_urdf

    return Ros2Topics(arm.model, design, build_urdf(design, robot))
