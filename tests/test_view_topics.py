"""The view topics: read-outs that recover a known linear system, and the filter node's
tpsr/predicted_image, tpsr/state_markers and tpsr/decoded_pose equal to what
`learner track --mcap` writes for the same steps, byte for byte."""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np
import pytest
from graph_support import fresh_domain, rclpy_available
from test_filter_node import Harness, S, small  # noqa: F401  (the module fixture)

from learner.cli import main as learner_main
from tpsr_ros.core.errors import DataError
from tpsr_ros.core.view_readout import fit_view_readout, next_step_pairs
from tpsr_ros.io import messages as m
from tpsr_ros.io.bag import BagReader
from tpsr_ros.io.marker_cdr import MarkerArrayTemplate, MarkerData, marker_array_cdr
from tpsr_ros.io.model_io import open_model
from tpsr_ros.io.view_messages import MARKERS_TYPE, ViewMessages, ViewSettings
from tpsr_ros.runtime import Node, NodeOptions
from tpsr_ros.runtime.launcher import Launch

VIEW_TOPICS = ("/tpsr/state", "/tpsr/state_markers", "/tpsr/predicted_image", "/tpsr/decoded_pose")


def _linear_system(seed: int = 0, steps: int = 4000, r: int = 4, k: int = 12, actions: int = 3):
    """States, actions, observations and positions of a system whose next observation is
    exactly affine in the state for each action, and whose pose is affine in the state."""
    rng = np.random.default_rng(seed)
    states = rng.normal(size=(steps, r))
    acts = rng.integers(0, actions, size=steps)
    maps = rng.normal(size=(actions, r + 1, k))
    observations = np.zeros((steps, k))
    design = np.concatenate([states, np.ones((steps, 1))], axis=1)
    observations[1:] = np.einsum("ti,tik->tk", design[:-1], maps[acts[1:]])
    pose_map = rng.normal(size=(r + 1, 2))
    positions = design @ pose_map
    return states, acts, observations, positions, maps, pose_map


def test_the_read_outs_recover_a_known_affine_system():
    states, acts, obs, positions, maps, pose_map = _linear_system()
    segments = np.zeros(len(states), dtype=np.int64)
    view = fit_view_readout(states, acts, obs, segments, 3, positions=positions)
    np.testing.assert_allclose(view.image[:3], maps, atol=1e-5)  # the guard ridge
    np.testing.assert_allclose(view.pose, pose_map, atol=1e-5)
    probe = np.array([0.3, -1.0, 0.5, 2.0])
    np.testing.assert_allclose(
        view.predicted_observation(probe, 1), np.append(probe, 1.0) @ maps[1], atol=1e-4
    )
    # the viewer's coordinates: unit spread along the three leading directions
    spread = ((states - view.center) @ view.axes).std(axis=0, ddof=1)
    np.testing.assert_allclose(spread, 1.0, rtol=1e-9)


def test_pairs_never_cross_a_segment_and_too_little_data_is_refused():
    segments = np.array([0, 0, 0, 1, 1, 2])
    np.testing.assert_array_equal(next_step_pairs(segments), [0, 1, 3])
    states, acts, obs, *_ = _linear_system(steps=6)
    with pytest.raises(DataError, match="consecutive step pairs"):
        fit_view_readout(states, acts, obs, segments, 3)


def test_a_grey_model_predicts_an_rgb8_image_and_errors_are_in_pixels():
    states, acts, obs, *_ = _linear_system(k=4)
    view = fit_view_readout(states, acts, obs, np.zeros(len(states)), 3)
    viewer = ViewMessages(view, (2, 2))  # 2x2 grey observations
    first = viewer.step(S, states[0], obs[0])
    second = viewer.step(2 * S, states[1], np.full(4, 0.5))
    image = m.deserialize(first.predicted_image, m.IMAGE_TYPE)
    assert (image.height, image.width, image.encoding) == (2, 2, "rgb8")
    pixels = np.asarray(image.data).reshape(2, 2, 3)
    assert (pixels[..., 0] == pixels[..., 2]).all()
    assert first.image_error is None
    expected = np.clip(view.predicted_observation(states[0], None), 0, 1)
    assert second.image_error == pytest.approx(np.sqrt(np.mean((expected - 0.5) ** 2)) * 255)
    assert len(first.markers) == 2 and len(second.markers) == 1  # the map, then the trail
    cloud = m.deserialize(first.markers[0], MARKERS_TYPE).markers[0]
    assert (cloud.ns, len(cloud.points)) == ("training_states", len(view.points))


def test_the_trail_holds_the_last_states_in_order():
    states, acts, obs, *_ = _linear_system(k=12)
    view = fit_view_readout(states, acts, obs, np.zeros(len(states)), 3)
    viewer = ViewMessages(view, (2, 2), settings=ViewSettings(trail=5, cloud_every=4))
    for k in range(12):
        step = viewer.step(k * S, states[k], obs[k])
        assert len(step.markers) == (2 if k % 4 == 0 else 1)
        trail = m.deserialize(step.markers[-1], MARKERS_TYPE).markers[0]
        points = np.array([[p.x, p.y, p.z] for p in trail.points])
        expected = [view.view_point(state) for state in states[max(0, k - 4) : k + 1]]
        np.testing.assert_array_equal(points, expected)


def _published(h: Harness) -> dict[str, list[bytes]]:
    received: dict[str, list[bytes]] = {topic: [] for topic in VIEW_TOPICS}
    types = dict(zip(VIEW_TOPICS, (m.STATE_TYPE, MARKERS_TYPE, m.IMAGE_TYPE, m.POSE_TYPE),
                     strict=True))  # fmt: skip
    for topic in VIEW_TOPICS:
        h.feeder.create_subscription(topic, types[topic], received[topic].append, raw=True)
    return received


@pytest.mark.parametrize("with_policy", [False, True], ids=["filter", "policy"])
def test_the_nodes_view_topics_equal_learner_track_mcap(small, with_policy, tmp_path):  # noqa: F811
    policy = small["policy"] if with_policy else None
    h = Harness(small["model"], policy, "view_trail:=7")
    received = _published(h)
    try:
        for k in range(1, 41):
            h.step(small["images"], small["actions"], k * S)
        for _ in range(5):
            h.feeder.spin_once(0.0)
        values = h.values()
    finally:
        h.close()
    assert isinstance(values["predicted_image_rmse"], float)
    bag = tmp_path / "view"
    args = ["track", str(small["model"]), str(small["tmp"] / "feed"), "--mcap", str(bag),
            "--view-trail", "7"]  # fmt: skip
    assert learner_main(args + (["--policy", str(policy)] if policy else [])) == 0
    expected: dict[str, list[bytes]] = {topic: [] for topic in VIEW_TOPICS}
    with BagReader(bag) as reader:
        for topic, _, data in reader.raw_messages(list(VIEW_TOPICS)):
            expected[topic].append(bytes(data))
        assert reader.message_counts["/camera/image_raw"] == 40
    assert len(expected["/tpsr/predicted_image"]) == 40
    assert len(expected["/tpsr/state_markers"]) == 41  # the map at step 0, then one per step
    for topic in VIEW_TOPICS:
        assert [bytes(x) for x in received[topic]] == expected[topic], topic
    markers = m.deserialize(expected["/tpsr/state_markers"][-1], MARKERS_TYPE).markers
    names = [marker.ns for marker in markers]
    assert names == ["trail", "state", *(["action_values"] if policy else [])]
    assert len(markers[0].points) == 7


def test_view_off_and_models_without_read_outs_publish_no_view(small, tmp_path):  # noqa: F811
    h = Harness(small["model"], None, "view:=false")
    try:
        assert h.node.viewer is None and "predicted_image_rmse" not in h.values()
    finally:
        h.close()
    model_file = open_model(small["model"])
    assert model_file.view is not None and model_file.view.pose_frame == "map"


def _rosbags_marker(d: MarkerData):
    """The same marker as a rosbags message (the generic serialiser's input)."""
    t = m.jazzy_typestore().types

    def color(c):
        return t["std_msgs/msg/ColorRGBA"](r=float(c[0]), g=float(c[1]), b=float(c[2]),
                                           a=float(c[3]))  # fmt: skip

    def point(p):
        return t["geometry_msgs/msg/Point"](x=float(p[0]), y=float(p[1]), z=float(p[2]))

    empty = np.zeros(0, dtype=np.uint8)
    return t["visualization_msgs/msg/Marker"](
        header=m.header_msg(d.stamp_ns, d.frame_id), ns=d.ns, id=d.marker_id, type=d.kind,
        action=0,
        pose=t["geometry_msgs/msg/Pose"](
            position=point(d.position),
            orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)),
        scale=t["geometry_msgs/msg/Vector3"](x=d.scale[0], y=d.scale[1], z=d.scale[2]),
        color=color(d.color), lifetime=t["builtin_interfaces/msg/Duration"](sec=0, nanosec=0),
        frame_locked=False, points=[point(p) for p in d.points],
        colors=[color(c) for c in d.colors], texture_resource="",
        texture=t["sensor_msgs/msg/CompressedImage"](header=m.header_msg(0, ""), format="",
                                                     data=empty),
        uv_coordinates=[], text="", mesh_resource="",
        mesh_file=t["visualization_msgs/msg/MeshFile"](filename="", data=empty),
        mesh_use_embedded_materials=False,
    )  # fmt: skip


def test_the_marker_writer_gives_the_generic_serialisers_bytes():
    rng = np.random.default_rng(4)
    for _ in range(40):  # every alignment: strings, point and colour counts of 0..4
        markers = [
            MarkerData(
                int(rng.integers(0, 10**12)), "tpsr"[: int(rng.integers(0, 5))],
                "trail"[: int(rng.integers(0, 6))], j, int(rng.integers(0, 12)),
                tuple(rng.normal(size=3)), tuple(rng.random(3)), tuple(rng.random(4)),
                rng.normal(size=(int(rng.integers(0, 5)), 3)),
                rng.random((int(rng.integers(0, 4)), 4)).astype(np.float32),
            )
            for j in range(int(rng.integers(0, 4)))
        ]
        msg = m.jazzy_typestore().types[MARKERS_TYPE](markers=[_rosbags_marker(d) for d in markers])
        assert marker_array_cdr(markers) == m.serialize(msg, MARKERS_TYPE)


def test_a_marker_template_writes_the_writers_bytes_of_other_values():
    rng = np.random.default_rng(5)
    for _ in range(40):  # every alignment, as above; then other stamps, positions, values
        shape = [
            MarkerData(
                0, "tpsr"[: int(rng.integers(0, 5))], "trail"[: int(rng.integers(0, 6))], j,
                int(rng.integers(0, 12)), (0.0, 0.0, 0.0), tuple(rng.random(3)),
                tuple(rng.random(4)), np.zeros((int(rng.integers(0, 5)), 3)),
                np.zeros((int(rng.integers(0, 4)), 4), dtype=np.float32),
            )
            for j in range(int(rng.integers(0, 4)))
        ]  # fmt: skip
        template = MarkerArrayTemplate(shape)
        for _ in range(3):
            stamp = int(rng.integers(0, 10**12))
            markers = [
                replace(d, stamp_ns=stamp, position=tuple(rng.normal(size=3)),
                        points=rng.normal(size=d.points.shape),
                        colors=rng.random(d.colors.shape).astype(np.float32))
                for d in shape
            ]  # fmt: skip
            written = template(
                stamp, [np.array(d.position) for d in markers], [d.points for d in markers],
                [d.colors.astype("<f4").tobytes() for d in markers],
            )  # fmt: skip
            assert written == marker_array_cdr(markers)


@pytest.mark.slow
@pytest.mark.rclpy
@pytest.mark.skipif(not rclpy_available(), reason="rclpy (ROS 2) not importable")
def test_a_replay_recorded_over_ros2_holds_the_view_track_mcap_writes(small, tmp_path, monkeypatch):  # noqa: F811
    """The whole path a user takes: play a bag into the filter node over rclpy, record the
    view topics with the recorder, and compare with `learner track --mcap`, byte for byte."""
    monkeypatch.setenv("ROS_DOMAIN_ID", str(fresh_domain(23)))
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    monkeypatch.setenv("TPSR_TRANSPORT", "rclpy")
    feed, recorded, expected_bag = small["tmp"] / "feed", tmp_path / "recorded", tmp_path / "view"
    assert learner_main(["track", str(small["model"]), str(feed), "--mcap", str(expected_bag)]) == 0
    probe = Node(NodeOptions(name="view_probe"))
    images: list[bytes] = []
    probe.create_subscription("/tpsr/predicted_image", m.IMAGE_TYPE, images.append, raw=True)
    try:
        with Launch(tmp_path / "logs", spin=probe.spin_once, timeout_s=60) as launch:
            node = launch.start(
                "filter", "tpsr_ros.filter_node", ["--ros-args", "-p", f"model:={small['model']}"]
            )
            recorder = launch.start("record", "tpsr_ros.record", ["-o", str(recorded),
                                                                  *VIEW_TOPICS[1:]])  # fmt: skip
            launch.wait("the filter's subscriptions", lambda: "pairing" in node.text())
            launch.wait("the recorder's subscriptions", lambda: all(
                f"subscribed to {topic} " in recorder.text() for topic in VIEW_TOPICS[1:]))
            player = launch.start("play", "tpsr_ros.play", [
                str(feed), "--rate", "20", "--topics", "/camera/image_raw", "/action",
                "--wait-for-subscribers", "1", "--no-clock",
            ])  # fmt: skip
            deadline = time.monotonic() + 60
            while len(images) < 40 and time.monotonic() < deadline:
                probe.spin_once(0.05)
            assert player.wait(30) == 0, player.text()
            assert recorder.stop() == 0, recorder.text()
            assert node.stop() == 0, node.text()
    finally:
        probe.close()
    def messages(bag):
        with BagReader(bag) as reader:
            return {t: [bytes(d) for _, _, d in reader.raw_messages([t])] for t in VIEW_TOPICS[1:]}

    received, expected = messages(recorded), messages(expected_bag)
    assert len(received["/tpsr/predicted_image"]) == 40
    assert received == expected


def test_every_topic_the_view_relays_is_published_with_its_type_by_a_documented_node():
    """msgs_doc's Publishers tables are held to the nodes by test_msgs_doc; the view's
    table (which the layouts are checked against) is held to them here."""
    from test_msgs_doc import DOC, index_pages, sections, table

    from tpsr_ros.view.topics import VIEW_TOPICS as RELAYED

    published: dict[str, set[str]] = {}
    for page in index_pages():
        parts = sections((DOC / page).read_text())
        if "Publishers" not in parts:
            continue
        for row in table(parts["Publishers"], ["topic", "type", "qos", "meaning"]) or []:
            published.setdefault(row[0].strip("`"), set()).add(row[1].strip("`"))
    for topic, msgtype in RELAYED.items():
        assert msgtype in published.get(topic, set()), (topic, msgtype)


def test_a_streamed_fit_has_the_in_memory_read_outs(small, tmp_path):  # noqa: F811
    """One more pass over the chunks, each tracked on from the previous chunk's last state,
    gives the read-outs of the fit in memory (to rounding: the models agree to 1e-9)."""
    bag = small["tmp"] / "train_3"
    streamed = tmp_path / "streamed.npz"
    args = ["fit", str(bag), "-o", str(streamed), "--stream", "--chunk-steps", "250",
            "--obs-centers", "40", "--ht-centers", "80", "--rank", "3"]  # fmt: skip
    assert learner_main(args) == 0
    memory, chunked = open_model(small["model"]).view, open_model(streamed).view
    assert memory is not None and chunked is not None
    for name, array in memory.to_arrays().items():
        other = chunked.to_arrays()[name]
        np.testing.assert_allclose(other, array, rtol=1e-6, atol=1e-9 * np.abs(array).max())


def test_sums_of_two_halves_merged_give_the_whole_ones():
    from tpsr_ros.core.view_readout import ViewSums

    states, acts, obs, positions, *_ = _linear_system(steps=600)
    segments = np.repeat([0, 1], 300)
    whole = ViewSums(3, states.shape[1], obs.shape[1], 2)
    whole.add(states, acts, obs, segments, positions)
    first, second = (ViewSums(3, states.shape[1], obs.shape[1], 2) for _ in range(2))
    first.add(states[:250], acts[:250], obs[:250], segments[:250], positions[:250])
    second.add(states[250:], acts[250:], obs[250:], segments[250:], positions[250:],
               before=(states[249], int(segments[249])))  # fmt: skip
    merged = first.merge(second)
    np.testing.assert_array_equal(merged.image_pairs, whole.image_pairs)
    for name in ("image_gram", "image_cross", "pose_gram", "pose_cross"):
        np.testing.assert_allclose(getattr(merged, name), getattr(whole, name), rtol=1e-12)
    np.testing.assert_allclose(merged.states.scatter, whole.states.scatter, rtol=1e-12)
    points = states[:10]
    np.testing.assert_allclose(merged.solve(points).image, whole.solve(points).image, rtol=1e-9)
