"""The Foxglove layout, built with ``foxglove.layouts`` (foxglove-sdk).

Left: what the robot sees next to what the model expects it to see next, and the state
markers in 3D (frame ``tpsr``: the trail, the current state, the training states, the
action values). Right: the state's first three coordinates over time, the phase plot b1
against b2 next to the decoded and the true pose (frame ``map``), the command, and
``/diagnostics`` with a Parameters panel. Import it in Foxglove with Layouts -> Import
from file.
"""

from __future__ import annotations

import json

import foxglove.layouts as fl

from tpsr_ros.view.layouts import topic
from tpsr_ros.view.topics import MAP_FRAME, STATE_FRAME

__all__ = ["foxglove_layout"]

STATE = topic("tpsr/state")
COLORS = ("#1f77b4", "#ff7f0e", "#2ca02c")


def _image(title: str, name: str) -> fl.ImagePanel:
    return fl.ImagePanel(
        title=title, config=fl.ImageConfig(image_mode=fl.ImageModeConfig(image_topic=topic(name)))
    )


def _split(direction: str, *items: tuple[float, fl.Content]) -> fl.SplitContainer:
    return fl.SplitContainer(
        direction=direction,  # type: ignore[arg-type]
        items=[fl.SplitItem(proportion=p, content=c) for p, c in items],
    )


def _state_markers() -> fl.ThreeDeePanel:
    return fl.ThreeDeePanel(
        title="the state among the training states (leading principal coordinates)",
        config=fl.ThreeDeeConfig(
            follow_tf=STATE_FRAME,
            topics={
                topic("tpsr/state_markers"): fl.BaseRendererRosMarkerTopicSettings(visible=True)
            },
            camera_state=fl.ThreeDeeCameraState(
                perspective=True, distance=12.0, phi=60.0, theta_offset=45.0
            ),
        ),
    )


def _state_series() -> fl.PlotPanel:
    series = [
        fl.PlotSeries(value=f"{STATE}.position[{i}]", label=f"b{i}", color=COLORS[i])
        for i in range(3)
    ]
    return fl.PlotPanel(
        title="state b0, b1, b2",
        config=fl.PlotConfig(
            paths=series, show_legend=True, time_window_mode="sliding", following_view_width=60.0
        ),
    )


def _phase_plot() -> fl.PlotPanel:
    return fl.PlotPanel(
        title="phase: b2 against b1",
        config=fl.PlotConfig(
            x_axis_val="custom",
            x_axis_path=fl.PlotXAxisPath(value=f"{STATE}.position[1]"),
            paths=[fl.PlotSeries(value=f"{STATE}.position[2]", label="b2", color=COLORS[2])],
            x_axis_label="b1",
            y_axis_label="b2",
            time_range="all",
            show_legend=False,
        ),
    )


def _poses() -> fl.ThreeDeePanel:
    return fl.ThreeDeePanel(
        title="decoded pose (orange) and true pose (blue)",
        config=fl.ThreeDeeConfig(
            follow_tf=MAP_FRAME,
            topics={
                topic("tpsr/decoded_pose"): fl.BaseRendererPoseTopicSettings(
                    visible=True, type="arrow", color=COLORS[1]
                ),
                topic("ground_truth/pose"): fl.BaseRendererPoseTopicSettings(
                    visible=True, type="arrow", color=COLORS[0]
                ),
            },
            camera_state=fl.ThreeDeeCameraState(perspective=False, distance=70.0),
        ),
    )


def _command() -> fl.PlotPanel:
    cmd = topic("cmd_vel")
    return fl.PlotPanel(
        title="command (m/s)",
        config=fl.PlotConfig(
            paths=[
                fl.PlotSeries(value=f"{cmd}.linear.x", label="linear.x", color=COLORS[0]),
                fl.PlotSeries(value=f"{cmd}.linear.y", label="linear.y", color=COLORS[1]),
            ],
            show_legend=True,
            time_window_mode="sliding",
            following_view_width=60.0,
        ),
    )


def _health() -> fl.TabContainer:
    diagnostics = topic("/diagnostics")
    summary = fl.DiagnosticsSummaryPanel(
        config=fl.DiagnosticsSummaryConfig(topic_to_render=diagnostics)
    )
    detail = fl.DiagnosticsDetailPanel(
        config=fl.DiagnosticsDetailConfig(topic_to_render=diagnostics)
    )
    return fl.TabContainer(
        tabs=[
            fl.TabItem(title="diagnostics", content=_split("row", (1.0, summary), (1.0, detail))),
            fl.TabItem(title="command", content=_command()),
            fl.TabItem(title="parameters", content=fl.ParametersPanel()),
        ]
    )


def foxglove_layout() -> str:
    """Build the layout as Foxglove imports it (JSON, indented, ending in a newline)."""
    images = _split(
        "row",
        (1.0, _image("camera", "camera/image_raw")),
        (1.0, _image("predicted next image", "tpsr/predicted_image")),
    )
    left = _split("column", (1.0, images), (2.0, _state_markers()))
    phase_and_pose = _split("row", (1.0, _phase_plot()), (1.0, _poses()))
    right = _split("column", (1.0, _state_series()), (1.0, phase_and_pose), (1.0, _health()))
    layout = fl.Layout(content=_split("row", (1.0, left), (1.0, right)))
    return json.dumps(json.loads(layout.to_json()), indent=2) + "\n"
