"""python -m tpsr_ros.view: the view topics reach a Foxglove WebSocket client unchanged.

A client of the Foxglove WebSocket protocol (``websockets``) connects to the view node,
reads the ``advertise`` op (topics, ROS 2 schema names, ``cdr``), subscribes, and decodes
the binary message-data frames (opcode 1, uint32 subscription id, uint64 log time,
payload) back into the published messages with the rosbags typestore. The publisher is a
node on the same in-process bus as the view; the command line runs as a subprocess on
the in-process transport (its advertise needs no publisher), and on each real backend
with the publisher in this process.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import struct
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("foxglove", reason="foxglove-sdk not installed (the view extra)")
from graph_support import BACKENDS, LOOPBACK, fresh_domain
from websockets.sync.client import ClientConnection, connect

from tpsr_ros.io import messages as m
from tpsr_ros.io.qos import (
    DEFAULT_QOS,
    LATCHED_QOS,
    SENSOR_DATA_QOS,
    Durability,
    History,
    QoSProfile,
    Reliability,
)
from tpsr_ros.runtime import Node, NodeOptions
from tpsr_ros.runtime.inproc import InprocBus, InprocTransport
from tpsr_ros.runtime.transport import TopicEndpoint, pad_cdr
from tpsr_ros.view import VIEW_TOPICS, ViewNode, main
from tpsr_ros.view.relays import RELAY_DEPTH, plan_relays
from tpsr_ros.view.server import MISSING_SDK, ws_url

ROOT = Path(__file__).resolve().parent.parent
# the subprotocol foxglove-sdk's server speaks (and the one of the older ws-protocol)
SUBPROTOCOLS = ["foxglove.sdk.v1", "foxglove.websocket.v1"]
MESSAGE_DATA = 0x01
S = 10**9


# -- which subscriptions the graph calls for (no ROS) -------------------------------------


def _endpoint(topic, msgtype, qos):
    return TopicEndpoint(topic, msgtype, qos, "/n")


def test_the_reader_qos_matches_every_publisher_and_keeps_the_last_few():
    topics = {"/tpsr/state_markers": "visualization_msgs/msg/MarkerArray",
              "/camera/image_raw": m.IMAGE_TYPE}
    relays, warnings = plan_relays(
        [_endpoint("/tpsr/state_markers", topics["/tpsr/state_markers"], LATCHED_QOS),
         _endpoint("/camera/image_raw", m.IMAGE_TYPE, SENSOR_DATA_QOS),
         _endpoint("/camera/image_raw", m.IMAGE_TYPE, DEFAULT_QOS),
         _endpoint("/elsewhere", m.IMAGE_TYPE, DEFAULT_QOS)],
        topics, {},
    )  # fmt: skip
    assert warnings == []
    qos = {r.topic: r.qos for r in relays}
    assert qos == {
        "/camera/image_raw": QoSProfile(
            Reliability.BEST_EFFORT, Durability.VOLATILE, History.KEEP_LAST, RELAY_DEPTH
        ),
        "/tpsr/state_markers": QoSProfile(
            Reliability.RELIABLE, Durability.TRANSIENT_LOCAL, History.KEEP_LAST, RELAY_DEPTH
        ),
    }
    # subscribed: nothing to do until a publisher appears that the reader cannot hear
    markers = [_endpoint("/tpsr/state_markers", topics["/tpsr/state_markers"], LATCHED_QOS)]
    assert plan_relays(markers, topics, qos) == ([], [])
    markers.append(_endpoint("/tpsr/state_markers", topics["/tpsr/state_markers"], DEFAULT_QOS))
    (again,), _ = plan_relays(markers, topics, qos)
    assert again.qos.durability is Durability.VOLATILE
    assert again.qos.reliability is Reliability.RELIABLE


def test_a_publisher_of_another_type_is_named_not_relayed():
    relays, warnings = plan_relays(
        [_endpoint("/tpsr/state", "std_msgs/msg/Float64MultiArray", DEFAULT_QOS)],
        {"/tpsr/state": m.STATE_TYPE}, {},
    )  # fmt: skip
    assert relays == []
    ((key, message),) = warnings
    assert key == ("/tpsr/state", "std_msgs/msg/Float64MultiArray")
    assert "not relaying" in message and m.STATE_TYPE in message


def test_ws_url_brackets_ipv6_hosts():
    assert ws_url("127.0.0.1", 8765) == "ws://127.0.0.1:8765"
    assert ws_url("::1", 1) == "ws://[::1]:1"


# -- the relay, end to end in one process ---------------------------------------------------


def _advertised(ws: ClientConnection, deadline_s: float = 5.0) -> dict[str, dict]:
    """The channels of the first ``advertise`` op, by topic."""
    end = time.monotonic() + deadline_s
    while time.monotonic() < end:
        frame = ws.recv(timeout=max(0.01, end - time.monotonic()))
        if isinstance(frame, str) and json.loads(frame)["op"] == "advertise":
            return {c["topic"]: c for c in json.loads(frame)["channels"]}
    raise AssertionError("no advertise op")


def _connect(url: str) -> ClientConnection:
    ws = connect(url, subprotocols=SUBPROTOCOLS, compression=None, open_timeout=5)
    assert ws.subprotocol in SUBPROTOCOLS
    return ws


def test_the_view_relays_the_published_bytes_to_a_foxglove_client(capsys):
    bus = InprocBus()
    view = ViewNode(NodeOptions.for_node(ViewNode, port=0), transport=InprocTransport("/v", bus))
    talker = Node(NodeOptions(name="talker"), transport=InprocTransport("/talker", bus))
    try:
        assert capsys.readouterr().out == ""  # the address comes once the node spins
        view.spin_once(0.05)
        url = capsys.readouterr().out.strip()
        assert url == f"ws://127.0.0.1:{view.server.port}" and view.server.port > 0
        state_pub = talker.create_publisher("/tpsr/state", m.STATE_TYPE)
        image_pub = talker.create_publisher("/tpsr/predicted_image", m.IMAGE_TYPE)
        view.discover()  # the timer's scan, now
        assert set(view.subscriptions) == {"/tpsr/state", "/tpsr/predicted_image"}

        state = np.array([0.25, -1.5, 3.0, 1e-3])
        pixels = np.arange(16 * 16 * 3, dtype=np.uint8).reshape(16, 16, 3)
        sent = {
            "/tpsr/state": pad_cdr(m.serialize(m.state_msg(7 * S, state), m.STATE_TYPE)),
            "/tpsr/predicted_image": pad_cdr(
                m.serialize(m.image_msg(7 * S, pixels), m.IMAGE_TYPE)
            ),
        }
        with _connect(url) as ws:
            channels = _advertised(ws)
            assert set(channels) == {"/" + t.lstrip("/") for t in VIEW_TOPICS}
            assert channels["/tpsr/state"]["schemaName"] == "sensor_msgs/msg/JointState"
            assert channels["/tpsr/predicted_image"]["schemaName"] == "sensor_msgs/msg/Image"
            for topic in sent:
                assert channels[topic]["encoding"] == "cdr"
                assert channels[topic]["schemaEncoding"] == "ros2msg"
                assert "MSG: std_msgs/Header" in channels[topic]["schema"]
            by_sub = {1: "/tpsr/state", 2: "/tpsr/predicted_image"}
            ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                {"id": sub, "channelId": channels[topic]["id"]} for sub, topic in by_sub.items()
            ]}))  # fmt: skip
            received: dict[str, bytes] = {}
            end = time.monotonic() + 10
            while len(received) < 2 and time.monotonic() < end:
                state_pub.publish_raw(sent["/tpsr/state"])
                image_pub.publish_raw(sent["/tpsr/predicted_image"])
                view.spin_once(0.05)
                try:
                    frame = ws.recv(timeout=0.2)
                except TimeoutError:
                    continue
                if isinstance(frame, bytes) and frame[0] == MESSAGE_DATA:
                    sub, log_time = struct.unpack_from("<IQ", frame, 1)
                    assert log_time > 0
                    received[by_sub[sub]] = frame[13:]
        assert received == sent  # the bytes, unchanged
        decoded = m.deserialize(received["/tpsr/state"], m.STATE_TYPE)
        np.testing.assert_array_equal(m.state_to_array(decoded), state)
        assert list(decoded.name) == ["b0", "b1", "b2", "b3"] and m.stamp_of(decoded) == 7 * S
        image = m.deserialize(received["/tpsr/predicted_image"], m.IMAGE_TYPE)
        assert (image.height, image.width, image.encoding) == (16, 16, "rgb8")
        np.testing.assert_array_equal(m.image_to_array(image), pixels)
    finally:
        talker.close()
        view.close()


# -- the command line -----------------------------------------------------------------------


def _env() -> dict[str, str]:
    return {**os.environ, "TPSR_TRANSPORT": "inproc", "PYTHONUNBUFFERED": "1"}


def test_python_m_tpsr_ros_view_prints_its_address_serves_and_stops_on_sigint():
    proc = subprocess.Popen(
        [sys.executable, "-m", "tpsr_ros.view", "--port", "0"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT, env=_env(),
    )  # fmt: skip
    try:
        line = proc.stdout.readline().strip()
        assert line.startswith("ws://127.0.0.1:") and int(line.rsplit(":", 1)[1]) > 0, (
            line + proc.stderr.read() if proc.poll() is not None else line
        )
        with _connect(line) as ws:
            channels = _advertised(ws)
        assert {t: c["schemaName"] for t, c in channels.items()} == {
            "/" + t.lstrip("/"): msgtype for t, msgtype in VIEW_TOPICS.items()
        }
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, err
    assert out == ""  # the address was the only line on stdout
    assert "relaying /tpsr/state (sensor_msgs/msg/JointState)" in err
    assert "Traceback" not in err


@pytest.mark.parametrize("backend", BACKENDS)
def test_the_view_relays_a_publisher_of_another_process(backend, monkeypatch):
    for key, value in {"TPSR_TRANSPORT": backend, "ROS_DOMAIN_ID": str(fresh_domain(23)),
                       "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST", "CYCLONEDDS_URI": LOOPBACK,
                       "PYTHONUNBUFFERED": "1"}.items():  # fmt: skip
        monkeypatch.setenv(key, value)
    proc = subprocess.Popen(
        [sys.executable, "-m", "tpsr_ros.view", "--port", "0"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT,
    )  # fmt: skip
    talker = Node(NodeOptions(name="talker", transport=backend))
    try:
        url = proc.stdout.readline().strip()
        assert url.startswith("ws://127.0.0.1:"), proc.stderr.read() if not url else url
        pub = talker.create_publisher("tpsr/state", m.STATE_TYPE)
        state = np.array([1.0, -2.0, 0.5])
        received = None
        with _connect(url) as ws:
            channel = _advertised(ws)["/tpsr/state"]["id"]
            ws.send(json.dumps({"op": "subscribe",
                                "subscriptions": [{"id": 3, "channelId": channel}]}))
            end = time.monotonic() + 30
            while received is None and time.monotonic() < end:
                pub.publish(m.state_msg(9 * S, state))
                talker.spin_once(0.05)
                try:
                    frame = ws.recv(timeout=0.2)
                except TimeoutError:
                    continue
                if isinstance(frame, bytes) and frame[0] == MESSAGE_DATA:
                    received = m.deserialize(frame[13:], m.STATE_TYPE)
        assert received is not None, "nothing relayed"
        np.testing.assert_array_equal(m.state_to_array(received), state)
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=30)
    finally:
        talker.close()
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, err
    assert "subscribed to /tpsr/state (sensor_msgs/msg/JointState" in err


def _run_main(argv, capsys):
    with pytest.raises(SystemExit) as info:
        main(argv)
    out, err = capsys.readouterr()
    return info.value.code, out, err


@pytest.mark.parametrize(
    "argv, code, needle",
    [
        (["--ros-args", "-p", "port:=70000"], 2, "'port' (-p): 70000 must be from 0 to 65535"),
        (["--ros-args", "-p", "port:=web"], 2, "parameter 'port' (-p) expects an integer"),
        (["--port", "x"], 2, "argument --port: 'x' is not an integer"),
        (["--ros-args", "-p", "host:=''"], 2, "host must not be empty"),
    ],
)
def test_bad_parameters_are_one_line(argv, code, needle, capsys, monkeypatch):
    monkeypatch.setenv("TPSR_TRANSPORT", "inproc")
    got, out, err = _run_main(argv, capsys)
    assert (got, out) == (code, "")
    assert err.count("\n") == 1 and err.startswith("python -m tpsr_ros.view: error: ")
    assert needle in err


def test_a_taken_port_is_one_line(capsys, monkeypatch):
    monkeypatch.setenv("TPSR_TRANSPORT", "inproc")
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        code, out, err = _run_main(["--port", str(port)], capsys)
    assert (code, out) == (1, "")
    (line,) = [x for x in err.splitlines() if "error" in x]
    assert line.startswith(f"python -m tpsr_ros.view: error: cannot serve on ws://127.0.0.1:{port}")
    assert "Traceback" not in err


def test_without_foxglove_sdk_it_says_how_to_install_it(capsys, monkeypatch):
    monkeypatch.setenv("TPSR_TRANSPORT", "inproc")
    monkeypatch.setitem(sys.modules, "foxglove", None)  # import foxglove raises ImportError
    code, out, err = _run_main(["--port", "0"], capsys)
    assert (code, out) == (1, "")
    assert err == f"python -m tpsr_ros.view: error: {MISSING_SDK}\n"
    assert "pip install 'tpsr-ros[view]'" in err
