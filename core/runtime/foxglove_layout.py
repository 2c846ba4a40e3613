"""The Foxglove layout for a run (live, `skinsafe run --foxglove`, or its record folder), built with foxglove-sdk's
typed layouts: the 3D panel on the robot (`/robot_description`, its meshes `/skinsafe/robot_meshes`, and `/tf`) with the skin's points coloured by force
(turbo, 0 to `vmax` N) and the taxels the layers retract from drawn larger in red; the layers' state (danger
potential and speed factor plotted, the whole `/skinsafe/state` message beside); the fault log (`/rosout`).

`python -m skinsafe.core.runtime.foxglove_layout FILE.json [VMAX]` writes it (docs/run/skinsafe.foxglove.json);
import it in Foxglove from Layouts > Import from file.
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

VMAX_N = 4.0  # top of the colour scale: twice the sample skins' 2 N threshold (core/runtime/view_scale.py's rule)


def layout(vmax: float = VMAX_N) -> dict:
    """The layout as the JSON object Foxglove imports."""
    import foxglove.layouts as fl

    three_d = fl.ThreeDeePanel(title="skin on the robot", config=fl.ThreeDeeConfig(
        follow_tf="world",
        scene=fl.BaseRendererSceneSettings(transforms=fl.BaseRendererTransforms(show_label=False, axis_size=0.0)),
        topics={
            "/robot_description": fl.BaseRendererUrdfTopicSettings(visible=True),
            "/skinsafe/robot_meshes": fl.BaseRendererRosMarkerTopicSettings(visible=True, show_outlines=False),
            "/skinsafe/skin": fl.BaseRendererPointCloudTopicSettings(
                visible=True, point_size=6.0, color_mode="colormap", color_field="force", color_map="turbo",
                min_value=0.0, max_value=vmax),
            "/skinsafe/contacts": fl.BaseRendererPointCloudTopicSettings(
                visible=True, point_size=14.0, color_mode="flat", flat_color="#ff2020"),
        }))
    plot = fl.PlotPanel(title="the layers", config=fl.PlotConfig(paths=[
        fl.PlotSeries(value="/skinsafe/state.potential", label="danger potential f"),
        fl.PlotSeries(value="/skinsafe/state.speed_factor", label="speed factor"),
        fl.PlotSeries(value="/skinsafe/state.retracting", label="retracting")]))
    state = fl.RawMessagesPanel(title="monitor state", config=fl.RawMessagesConfig(topic_path="/skinsafe/state"))
    faults = fl.LogPanel(title="fault log", config=fl.LogConfig(topic_to_render="/rosout"))
    side = fl.SplitContainer(direction="column", items=[
        fl.SplitItem(content=plot), fl.SplitItem(content=state), fl.SplitItem(content=faults)])
    doc = fl.Layout(content=fl.SplitContainer(direction="row", items=[
        fl.SplitItem(proportion=2, content=three_d), fl.SplitItem(proportion=1, content=side)]))
    return json.loads(doc.to_json())


def main(argv: list[str]) -> int:
    if not 1 <= len(argv) <= 2:
        print("usage: python -m skinsafe.core.runtime.foxglove_layout FILE.json [VMAX_N]", file=sys.stderr)
        return 2
    vmax = float(argv[1]) if len(argv) > 1 else VMAX_N
    Path(argv[0]).write_text(json.dumps(layout(vmax), indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
