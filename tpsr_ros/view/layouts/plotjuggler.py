"""The PlotJuggler layout: the state over time, the phase plot, decoded against true pose.

PlotJuggler's ROS 2 parser names a ``JointState``'s series by joint name,
``<topic>/<name>/position``, so b_k's coordinates are ``/tpsr/state/b0/position``...;
other messages are flattened field by field (``/tpsr/decoded_pose/pose/position/x``).
The layout starts PlotJuggler's "ROS2 Topic Subscriber" on the topics it plots (File ->
Load layout, then accept the streamer). Open it with
``ros2 run plotjuggler plotjuggler --layout share/tpsr_ros/layouts/tpsr_view.plotjuggler.xml``.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET

from tpsr_ros.view.layouts import topic

__all__ = ["plotjuggler_layout"]

STREAMER = "ROS2 Topic Subscriber"
COLORS = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728")


def _state(index: int) -> str:
    return f"{topic('tpsr/state')}/b{index}/position"


def _position(name: str, axis: str) -> str:
    return f"{topic(name)}/pose/position/{axis}"


def _plot(area: ET.Element, mode: str) -> ET.Element:
    plot = ET.SubElement(
        area, "plot", {"mode": mode, "style": "Lines", "flip_x": "false", "flip_y": "false"}
    )
    ET.SubElement(plot, "range", {"left": "0", "right": "1", "bottom": "0", "top": "1"})
    ET.SubElement(plot, "limitY")
    return plot


def _time_series(parent: ET.Element, title: str, curves: list[str]) -> None:
    plot = _plot(ET.SubElement(parent, "DockArea", {"name": title}), "TimeSeries")
    for i, name in enumerate(curves):
        ET.SubElement(plot, "curve", {"name": name, "color": COLORS[i % len(COLORS)]})


def _xy(parent: ET.Element, title: str, x: str, y: str, name: str) -> None:
    plot = _plot(ET.SubElement(parent, "DockArea", {"name": title}), "XYPlot")
    ET.SubElement(
        plot, "curve", {"name": name, "curve_x": x, "curve_y": y, "color": COLORS[2]}
    )


def _splitter(parent: ET.Element, orientation: str, count: int) -> ET.Element:
    sizes = ";".join([f"{1 / count:.6f}"] * count)
    return ET.SubElement(
        parent, "DockSplitter", {"orientation": orientation, "count": str(count), "sizes": sizes}
    )


def plotjuggler_layout() -> str:
    """Build the layout XML, as PlotJuggler saves it."""
    root = ET.Element("root")
    tabs = ET.SubElement(root, "tabbed_widget", {"name": "Main Window", "parent": "main_window"})
    tab = ET.SubElement(tabs, "Tab", {"tab_name": "TPSR state", "containers": "1"})
    rows = _splitter(ET.SubElement(tab, "Container"), "-", 2)
    _time_series(rows, "state b0, b1, b2", [_state(i) for i in range(3)])
    bottom = _splitter(rows, "|", 2)
    _xy(bottom, "phase: b2 against b1", _state(1), _state(2),
        f"{topic('tpsr/state')}/[b1;b2]/position")  # fmt: skip
    _time_series(bottom, "decoded and true position (m)", [
        _position("tpsr/decoded_pose", "x"), _position("ground_truth/pose", "x"),
        _position("tpsr/decoded_pose", "y"), _position("ground_truth/pose", "y"),
    ])  # fmt: skip
    ET.SubElement(tabs, "currentTabIndex", {"index": "0"})
    ET.SubElement(root, "use_relative_time_offset", {"enabled": "1"})
    plugins = ET.SubElement(root, "Plugins")
    streamer = ET.SubElement(plugins, "plugin", {"ID": STREAMER})
    for key, value in (
        ("use_header_stamp", "false"),
        ("discard_large_arrays", "true"),
        ("max_array_size", "100"),
        ("boolean_strings_to_number", "true"),
        ("remove_suffix_from_strings", "true"),
    ):
        ET.SubElement(streamer, key, {"value": value})
    topics = [topic(n) for n in ("tpsr/state", "tpsr/decoded_pose", "ground_truth/pose")]
    ET.SubElement(streamer, "selected_topics", {"value": ";".join(topics)})
    ET.SubElement(root, "previouslyLoaded_Datafiles")
    ET.SubElement(root, "previouslyLoaded_Streamer", {"name": STREAMER})
    ET.SubElement(root, "customMathEquations")
    ET.SubElement(root, "snippets")
    ET.indent(root, space=" ")
    return "<?xml version='1.0' encoding='UTF-8'?>\n" + ET.tostring(root, encoding="unicode") + "\n"
