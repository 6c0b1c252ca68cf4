"""The shipped layouts read only what the project publishes.

Every topic a layout names is in the view's topic table (``VIEW_TOPICS``, the one the
relay serves and msgs_doc/view.md documents) with the type the panel or display expects,
and every field path it reads (``/tpsr/state.position[1]`` in Foxglove,
``/tpsr/decoded_pose/pose/position/x`` in PlotJuggler) exists with a numeric type in the
ROS 2 Jazzy message definitions (the rosbags typestore). The checked-in files are what
the code builds.
"""

from __future__ import annotations

import json
import re
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

import pytest
import yaml

pytest.importorskip("foxglove", reason="foxglove-sdk not installed (the view extra)")
from test_msgs_doc import _unquote, sections, table

from tpsr_ros.io import messages as m
from tpsr_ros.io.messages import jazzy_typestore
from tpsr_ros.io.qos import DEFAULT_QOS, LATCHED_QOS, SENSOR_DATA_QOS, compatible, parse_qos_text
from tpsr_ros.runtime.diagnostics import DIAGNOSTICS_TYPE
from tpsr_ros.view import MARKER_ARRAY_TYPE, VIEW_TOPICS
from tpsr_ros.view.layouts import (
    FOXGLOVE_FILE,
    LAYOUT_FILES,
    PLOTJUGGLER_FILE,
    RVIZ_FILE,
    SHIPPED,
    build_layouts,
    main,
)
from tpsr_ros.view.topics import MAP_FRAME, STATE_FRAME, default_topic

DOC = Path(__file__).resolve().parent.parent / "msgs_doc" / "view.md"
CONTRACT = {default_topic(name): msgtype for name, msgtype in VIEW_TOPICS.items()}
NUMERIC = {"float64", "float32", "int8", "int16", "int32", "int64", "uint8", "uint16",
           "uint32", "uint64", "byte", "bool"}  # fmt: skip
_PART = re.compile(r"([A-Za-z_]\w*)(?:\[(\d+)\])?")


def field_type(msgtype: str, path: str) -> str:
    """The type at ``path`` (``position[1]``, ``pose.position.x``) of ``msgtype``: a base
    type (``float64``), a message type, or ``T[]`` for a whole array."""
    current = msgtype
    parts = path.split(".")
    for i, part in enumerate(parts):
        match = _PART.fullmatch(part)
        assert match, f"{path!r}: {part!r} is not a field name"
        name, index = match.group(1), match.group(2)
        fields = dict(jazzy_typestore().fielddefs[current][1])
        assert name in fields, f"{current} has no field {name!r} ({path!r})"
        kind, spec = fields[name]
        if kind.name in ("SEQUENCE", "ARRAY"):
            (element_kind, element), length = spec
            element_type = element[0] if element_kind.name == "BASE" else element
            if index is None:
                assert i == len(parts) - 1, f"{path!r}: {name} is an array, index it"
                return f"{element_type}[]"
            assert kind.name == "SEQUENCE" or int(index) < length, f"{path!r}: out of range"
            current = element_type
        else:
            assert index is None, f"{path!r}: {name} is not an array"
            current = spec[0] if kind.name == "BASE" else spec
    return current


def test_field_type_reads_the_message_definitions():
    assert field_type(m.STATE_TYPE, "position[1]") == "float64"
    assert field_type(m.STATE_TYPE, "position") == "float64[]"
    assert field_type(MARKER_ARRAY_TYPE, "markers") == "visualization_msgs/msg/Marker[]"
    assert field_type(MARKER_ARRAY_TYPE, "markers[0].points[2].x") == "float64"
    assert field_type(m.POSE_TYPE, "pose.position.x") == "float64"
    assert field_type(m.TWIST_TYPE, "linear") == "geometry_msgs/msg/Vector3"
    for bad in ("positions[0]", "header.stamp.sec[0]", "pose.position", "markers.ns"):
        with pytest.raises(AssertionError):
            msgtype = m.POSE_TYPE if bad.startswith("pose") else m.STATE_TYPE
            msgtype = MARKER_ARRAY_TYPE if bad.startswith("markers") else msgtype
            assert field_type(msgtype, bad) in NUMERIC


def _numeric_path(reference: str, separator: str) -> tuple[str, str]:
    """``(topic, field path)`` of a reference ``<topic><separator><path>`` to a number."""
    topics = [t for t in CONTRACT if reference.startswith(t + separator)]
    assert topics, f"{reference!r} reads no topic of the contract"
    topic = max(topics, key=len)
    path = reference[len(topic) + 1:]
    if separator == "/":
        path = path.replace("/", ".")
    assert field_type(CONTRACT[topic], path) in NUMERIC, reference
    return topic, path


def _shipped(name: str) -> str:
    return (SHIPPED / name).read_text(encoding="utf-8")


def test_the_checked_in_layouts_are_what_the_code_builds(capsys):
    assert build_layouts() == {name: _shipped(name) for name in LAYOUT_FILES}
    assert main(["--check"]) == 0
    assert "up to date" in capsys.readouterr().out


def test_written_layouts_equal_the_checked_in_ones(tmp_path):
    assert main(["--write", str(tmp_path / "out")]) == 0
    for name in LAYOUT_FILES:
        assert (tmp_path / "out" / name).read_text(encoding="utf-8") == _shipped(name)


def test_the_view_page_documents_the_relayed_topics():
    rows = table(sections(DOC.read_text())["Relayed topics"], ["topic", "type", "from"])
    assert {_unquote(r[0]): _unquote(r[1]) for r in rows or []} == dict(VIEW_TOPICS)
    text = DOC.read_text()
    assert all(f"`{name}`" in text for name in LAYOUT_FILES)


# -- Foxglove -------------------------------------------------------------------------------


def _panels(node: Any) -> list[dict[str, Any]]:
    """Every panel of a layout's content tree."""
    if isinstance(node, dict):
        found = [node] if node.get("type") == "panel" else []
        return found + [p for value in node.values() for p in _panels(value)]
    if isinstance(node, list):
        return [p for value in node for p in _panels(value)]
    return []


def _references(node: Any, key: str = "") -> list[tuple[str, str]]:
    """``(key, text)`` of every string starting with '/' and of every 3D topic key."""
    found: list[tuple[str, str]] = []
    if isinstance(node, dict):
        for k, value in node.items():
            if k == "topics":
                found += [("topics", t) for t in value]
            found += _references(value, k)
    elif isinstance(node, list):
        for value in node:
            found += _references(value, key)
    elif isinstance(node, str) and node.startswith("/"):
        found.append((key, node))
    return found


PANEL_TOPIC_TYPES = {"imageTopic": {m.IMAGE_TYPE}, "topicToRender": {DIAGNOSTICS_TYPE},
                     "topics": {MARKER_ARRAY_TYPE, m.POSE_TYPE}}  # fmt: skip
FRAME_OF = {MARKER_ARRAY_TYPE: STATE_FRAME, m.POSE_TYPE: MAP_FRAME}


def test_the_foxglove_layout_reads_topics_and_fields_of_the_contract():
    layout = json.loads(_shipped(FOXGLOVE_FILE))
    references = _references(layout)
    read = set()
    for key, text in references:
        if key in PANEL_TOPIC_TYPES:
            assert CONTRACT.get(text) in PANEL_TOPIC_TYPES[key], (key, text)
            read.add(text)
        else:
            assert key in ("value", "xValuePath"), f"unexpected reference {key}: {text}"
            read.add(_numeric_path(text, ".")[0])
    for panel in _panels(layout):
        if panel["panelType"] == "ThreeDee":  # each 3D panel shows its topics' frame
            frames = {FRAME_OF[CONTRACT[t]] for t in panel["config"]["topics"]}
            assert frames == {panel["config"]["followTf"]}, panel["title"]
    assert {"/tpsr/state", "/tpsr/predicted_image", "/camera/image_raw",
            "/tpsr/state_markers", "/diagnostics"} <= read  # fmt: skip


def test_the_foxglove_layout_has_the_panels_that_show_the_state():
    panels = _panels(json.loads(_shipped(FOXGLOVE_FILE)))
    kinds = [p["panelType"] for p in panels]
    for kind in ("Image", "Plot", "ThreeDee", "DiagnosticsSummary", "DiagnosticsDetail",
                 "Parameters"):
        assert kind in kinds, kind
    images = [p["config"]["imageMode"]["imageTopic"] for p in panels if p["panelType"] == "Image"]
    assert images == ["/camera/image_raw", "/tpsr/predicted_image"]  # side by side
    plots = [p["config"] for p in panels if p["panelType"] == "Plot"]
    series = [[s["value"] for s in c["paths"]] for c in plots]
    assert [f"/tpsr/state.position[{i}]" for i in range(3)] in series
    (phase,) = [c for c in plots if c.get("xAxisVal") == "custom"]
    assert phase["xAxisPath"]["value"] == "/tpsr/state.position[1]"
    assert [s["value"] for s in phase["paths"]] == ["/tpsr/state.position[2]"]
    markers = [p for p in panels if "/tpsr/state_markers" in p.get("config", {}).get("topics", {})]
    assert len(markers) == 1 and markers[0]["config"]["followTf"] == STATE_FRAME


# -- RViz2 ----------------------------------------------------------------------------------

RVIZ_TYPES = {"rviz_default_plugins/MarkerArray": MARKER_ARRAY_TYPE,
              "rviz_default_plugins/Image": m.IMAGE_TYPE}  # fmt: skip
OFFERED = {MARKER_ARRAY_TYPE: [LATCHED_QOS], m.IMAGE_TYPE: [DEFAULT_QOS, SENSOR_DATA_QOS]}
_RVIZ_QOS = {"Reliable": "reliable", "Best Effort": "best_effort",
             "Volatile": "volatile", "Transient Local": "transient_local"}  # fmt: skip


def test_the_rviz_config_shows_the_markers_and_images_in_frame_tpsr():
    config = yaml.safe_load(_shipped(RVIZ_FILE))
    manager = config["Visualization Manager"]
    assert manager["Global Options"]["Fixed Frame"] == STATE_FRAME
    shown = {}
    for display in manager["Displays"]:
        if "Topic" not in display:
            assert display["Class"] == "rviz_default_plugins/Grid"
            continue
        msgtype = RVIZ_TYPES[display["Class"]]
        name = display["Topic"]["Value"]
        assert CONTRACT[name] == msgtype, name
        requested = parse_qos_text(
            f"{_RVIZ_QOS[display['Topic']['Reliability Policy']]}, "
            f"{_RVIZ_QOS[display['Topic']['Durability Policy']]}, "
            f"keep_last({display['Topic']['Depth']})"
        )
        # the profiles the filter node and cameras offer reach the display
        assert all(compatible(q, requested) for q in OFFERED[msgtype]), name
        shown[name] = display["Class"]
    assert shown == {
        "/tpsr/state_markers": "rviz_default_plugins/MarkerArray",
        "/camera/image_raw": "rviz_default_plugins/Image",
        "/tpsr/predicted_image": "rviz_default_plugins/Image",
    }


# -- PlotJuggler ----------------------------------------------------------------------------

_JOINT_SERIES = re.compile(r"b\d+/(position|velocity|effort)")


def _plotjuggler_series(name: str) -> str:
    """The topic of a PlotJuggler series, its field path checked: a ``JointState`` is named
    ``<topic>/<joint name>/<field>`` (b_k's joints are b0, b1...), any other message
    field by field, ``<topic>/a/b/c``."""
    topics = [t for t in CONTRACT if name.startswith(t + "/")]
    assert topics, f"{name!r} reads no topic of the contract"
    topic = max(topics, key=len)
    if CONTRACT[topic] == m.STATE_TYPE:
        rest = name[len(topic) + 1:]
        assert _JOINT_SERIES.fullmatch(rest), name
        assert field_type(m.STATE_TYPE, rest.split("/")[1]) == "float64[]"
        return topic
    return _numeric_path(name, "/")[0]


def test_the_plotjuggler_layout_plots_fields_of_the_contract():
    root = ET.fromstring(_shipped(PLOTJUGGLER_FILE))
    plotted = set()
    for plot in root.iter("plot"):
        for curve in plot.iter("curve"):
            names = ([curve.get("curve_x"), curve.get("curve_y")]
                     if plot.get("mode") == "XYPlot" else [curve.get("name")])  # fmt: skip
            plotted |= {_plotjuggler_series(n) for n in names}
    streamer = root.find("Plugins/plugin[@ID='ROS2 Topic Subscriber']")
    assert streamer is not None
    assert root.find("previouslyLoaded_Streamer").get("name") == "ROS2 Topic Subscriber"
    subscribed = streamer.find("selected_topics").get("value").split(";")
    assert set(subscribed) <= set(CONTRACT) and plotted <= set(subscribed)
    curves = {c.get("name") for c in root.iter("curve")}
    assert {f"/tpsr/state/b{i}/position" for i in range(3)} <= curves
    (xy,) = [c for p in root.iter("plot") if p.get("mode") == "XYPlot" for c in p.iter("curve")]
    assert (xy.get("curve_x"), xy.get("curve_y")) == (
        "/tpsr/state/b1/position", "/tpsr/state/b2/position"
    )
