"""Learning from robot-shaped bags (sim_node.robot_bag): the resampled steps against the
simulator's ground truth, the learner's commands end to end, the one-line refusals, and
simulator bags still giving bit-identical models through the exact-stamp pairing."""

from __future__ import annotations

import re

import numpy as np
import pytest
from cli_support import run_entry

from learner.cli import main
from sim_node import SimConfig
from sim_node.camera import Camera
from sim_node.generate import generate_bag
from sim_node.robot_bag import START_S, RobotBagConfig, write_robot_bag
from sim_node.rollout import random_rollout
from tpsr_ros.core.episodes import Trajectory, make_episodes
from tpsr_ros.core.errors import ConfigError, DataError, MessageError, ModelFormatError
from tpsr_ros.core.images import Preprocessing, preprocess_images
from tpsr_ros.core.tpsr import TPSRConfig, fit_tpsr_episodes
from tpsr_ros.io import messages as msgs
from tpsr_ros.io.bag import BagReader, BagWriter
from tpsr_ros.io.model_io import (
    load_model,
    model_fingerprint,
    model_stream_spec,
    open_model,
    read_metadata,
)
from tpsr_ros.io.npz_archive import write_archive
from tpsr_ros.io.streams import (
    FitOptions,
    fit_stream_spec,
    read_bag_streams,
    read_stream_trajectory,
)

S = 10**9
CAMERA = "/front_camera/image_raw"
SMALL = ["--obs-centers", "40", "--ht-centers", "80", "--rank", "3"]
ROBOT = ["--action-topic", "/cmd_vel", "--pose-topic", "/odom", "--step-period", "1.0"]


@pytest.fixture(scope="module")
def robot(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("robot")
    config = RobotBagConfig(steps=900, seed=5)
    bag = tmp / "bgr8"
    write_robot_bag(bag, config)
    return {"tmp": tmp, "bag": bag, "config": config}


def options(**changes) -> FitOptions:
    return FitOptions(**{"step_period": 1.0, "image_size": (8, 8), "actions": 25, **changes})


# -- the resampled steps are the simulator's steps ------------------------------------------


@pytest.mark.slow
def test_streams_read_once_give_the_spec_and_steps_of_reading_twice(robot):
    bags = [robot["bag"]]
    topics = {"pose_topic": "/odom", "reward_topic": "/reward"}
    streams = read_bag_streams(
        bags, image_topic=CAMERA, action_topic="/cmd_vel", components=options().components,
        **topics,
    )  # fmt: skip
    spec = fit_stream_spec(bags, options(), image_topic=CAMERA, action_topic="/cmd_vel")
    given = fit_stream_spec(
        bags, options(), image_topic=CAMERA, action_topic="/cmd_vel", streams=streams
    )
    assert given.as_dict() == spec.as_dict()
    once = read_stream_trajectory(bags, spec, streams=streams, **topics)
    twice = read_stream_trajectory(bags, spec, **topics)
    for name in ("stamps", "observations", "actions", "velocities", "positions", "rewards"):
        np.testing.assert_array_equal(getattr(once, name), getattr(twice, name), err_msg=name)
    assert once.velocities.shape[1] == len(spec.codebook.components) == 2  # of 3 read
    with pytest.raises(ConfigError, match="not read from these bags"):
        read_stream_trajectory([robot["bag"], robot["bag"]], spec, streams=streams)


@pytest.mark.slow
def test_resampled_steps_are_the_simulator_steps(robot):
    config = robot["config"]
    chosen = fit_stream_spec([robot["bag"]], options(), image_topic=CAMERA, action_topic="/cmd_vel")
    # frames 5-40 ms after each quarter second; commands logged 0.4 and 0.9 s into a step,
    # each dated by the next frame: the widest spans clear of both are 0.04-0.255 s and
    # 0.54-0.755 s into a step
    phase = chosen.grid.phase_ns / S
    assert 0.05 < phase < 0.245 or 0.55 < phase < 0.745, phase
    spec = fit_stream_spec(
        [robot["bag"]], options(step_offset=0.15), image_topic=CAMERA, action_topic="/cmd_vel"
    )
    assert spec.grid.phase_ns == 0.15 * S
    assert spec.codebook.components == ("linear.x", "linear.y")  # angular.z is constant
    assert spec.grid.camera_period_ns == pytest.approx(S / 4, abs=0.02 * S)
    trajectory = read_stream_trajectory(
        [robot["bag"]], spec, pose_topic="/odom", reward_topic="/reward"
    )
    run = random_rollout(SimConfig(environment="full"), config.steps, config.seed)
    # step k of the grid falls just after the frame that ends simulator step k
    steps = np.rint((trajectory.stamps - START_S * S) / S - 0.125).astype(int)
    # step 1 has no command yet (commands start in step 2); the last is before the last image
    assert steps.tolist() == list(range(2, config.steps))
    assert len(trajectory.segment_bounds()) == 1
    codes = spec.codebook.codes[trajectory.actions]
    np.testing.assert_allclose(codes, run.commands[steps - 1], atol=0.2)  # a_k
    frames = Camera(SimConfig(environment="full", image_size=40)).render(run.positions)
    expected = preprocess_images(frames[steps - 1], spec.preprocessing)  # o_k, lossless bgr8
    assert np.array_equal(trajectory.observations, expected)
    # ground truth: the odometry interpolated at the step time, a little into step k + 1
    into_next = ((trajectory.stamps - START_S * S) / S - steps)[:, None]
    before, after = run.positions[steps - 1], run.positions[steps]
    truth = before + into_next * (after - before)
    np.testing.assert_allclose(trajectory.positions, truth, atol=1e-6)
    assert np.array_equal(trajectory.rewards, run.rewards[steps - 1])  # stamped within step k


def test_jpeg_and_grey_cameras_give_nearly_the_same_observations(tmp_path):
    bags = {}
    for encoding in ("bgr8", "jpeg", "mono8"):
        bags[encoding] = tmp_path / encoding
        write_robot_bag(bags[encoding], RobotBagConfig(steps=30, seed=2, encoding=encoding))
    small = options(image_size=(16, 16), actions=4)  # 28 steps
    colour = fit_stream_spec([bags["bgr8"]], small, image_topic=CAMERA, action_topic="/cmd_vel")
    jpeg = fit_stream_spec([bags["jpeg"]], small, image_topic=CAMERA + "/compressed",
                           action_topic="/cmd_vel")
    mono = fit_stream_spec([bags["mono8"]], small, image_topic=CAMERA, action_topic="/cmd_vel")
    assert jpeg.image_type == "sensor_msgs/msg/CompressedImage"
    assert mono.preprocessing.grey and not colour.preprocessing.grey  # from the camera
    obs = {
        "bgr8": read_stream_trajectory([bags["bgr8"]], colour).observations,
        "jpeg": read_stream_trajectory([bags["jpeg"]], jpeg).observations,
        "mono8": read_stream_trajectory([bags["mono8"]], mono).observations,
    }
    assert obs["jpeg"].shape == obs["bgr8"].shape
    assert np.abs(obs["jpeg"] - obs["bgr8"]).mean() < 0.02  # jpeg is lossy, not wrong
    grey = dataclass_replace_grey(colour)
    as_grey = read_stream_trajectory([bags["bgr8"]], grey).observations
    assert np.abs(obs["mono8"] - as_grey).max() <= 0.5 / 255 + 1e-12  # camera rounds to 8 bits


def dataclass_replace_grey(spec):
    import dataclasses

    prep = spec.preprocessing
    return dataclasses.replace(spec, preprocessing=Preprocessing(prep.height, prep.width, True))


# -- the learner end to end -----------------------------------------------------------------


@pytest.mark.slow
def test_fit_info_plot_policy_need_no_options_again(robot, capsys):
    tmp, bag = robot["tmp"], robot["bag"]
    model = tmp / "m.npz"
    argv = ["fit", str(bag), "--image-topic", CAMERA, *ROBOT, "--image-size", "8",
            "--actions", "25", "-o", str(model), *SMALL]
    assert main(argv) == 0
    err = capsys.readouterr().err
    assert "steps of 1 s, offset " in err and "(chosen to keep steps clear of stamps" in err
    assert "(camera period 0.25 s, images used up to 1 s old); observations 8x8 colour;" in err
    assert re.search(r"commands: 0 of 1[78]\d\d command messages farther than", err)  # said
    assert "preset predictive (" in err
    assert load_model(model).config.normalize_ht_features  # the default preset's
    metadata = read_metadata(model)
    spec = model_stream_spec(model, metadata)
    assert spec is not None and len(spec.codebook) == 25 and spec.image_topic == CAMERA
    assert metadata["observation"]["size"] == 8 * 8 * 3
    code, out, _ = run_entry(["plot", str(model), str(bag), "-o", str(tmp / "s.png")], capsys)
    assert code == 0, out
    r2 = [float(v.rstrip(",")) for v in out.split("x ")[1].split(" y ")]
    assert (tmp / "s.png").stat().st_size > 0 and all(v <= 1 for v in r2), out  # plumbing
    code, out, err = run_entry(
        ["policy", str(model), str(bag), "-o", str(tmp / "p.npz"), "--centers", "10"],
        capsys,
    )
    assert code == 0, err
    code, out, err = run_entry(["evaluate", str(tmp / "p.npz"), "--environment", "full"], capsys)
    assert code == 0 and out.splitlines()[-1].startswith("score: "), err  # the robot's camera
    code, out, _ = run_entry(["info", str(model)], capsys)
    assert code == 0 and f"input: camera {CAMERA} (sensor_msgs/msg/Image) as 8x8 colour" in out
    assert "25 kmeans actions over linear.x, linear.y; steps of 1 s" in out


@pytest.mark.slow
def test_the_robot_bag_default_yields_to_an_explicit_option(robot, capsys):
    tmp, bag = robot["tmp"], robot["bag"]
    model = tmp / "guide_features.npz"
    argv = ["fit", str(bag), "--image-topic", CAMERA, *ROBOT, "--image-size", "8",
            "--actions", "25", "-o", str(model), *SMALL, "--no-normalize-ht-features",
            "--preset", "guide"]  # fmt: skip
    assert main(argv) == 0
    assert "normalize_ht_features=False" in capsys.readouterr().err
    assert not load_model(model).config.normalize_ht_features


@pytest.mark.slow
@pytest.mark.parametrize(("file_sets_it", "said"), [(False, True), (True, False)])
def test_the_robot_bag_default_is_said_unless_the_config_file_sets_it(
    robot, capsys, file_sets_it, said
):
    tmp, bag = robot["tmp"], robot["bag"]
    config = tmp / f"config_{file_sets_it}.yaml"
    values = "rank: 3\n" + ("normalize_ht_features: false\n" if file_sets_it else "")
    config.write_text("tpsr:\n" + "".join(f"  {line}\n" for line in values.splitlines()))
    model = tmp / f"from_config_{file_sets_it}.npz"
    argv = ["fit", str(bag), "--image-topic", CAMERA, *ROBOT, "--image-size", "8",
            "--actions", "25", "-o", str(model), "--obs-centers", "40", "--ht-centers", "80",
            "--config", str(config), "--preset", "guide"]  # fmt: skip
    assert main(argv) == 0
    err = capsys.readouterr().err
    assert "preset guide with its robot-bag settings" in err
    assert ("normalize_ht_features=False" not in err) == said
    assert load_model(model).config.normalize_ht_features == said


@pytest.mark.slow
def test_a_model_whose_input_entry_is_wrong_is_refused(robot):
    model = robot["tmp"] / "m_input.npz"
    argv = ["fit", str(robot["bag"]), "--image-topic", CAMERA, *ROBOT, "--image-size", "8",
            "--actions", "25", "-o", str(model), *SMALL]
    assert main(argv) == 0
    metadata = read_metadata(model)
    opened = open_model(model)
    assert opened.view is not None
    arrays = {
        **opened.model.to_arrays(), **opened.view.to_arrays(), **opened.model.basis.to_arrays()
    }
    for change, reason in [
        ({"codebook": {**metadata["input"]["codebook"], "codes": [[1.0, 2.0]]}},
         "has 25 actions, but its codebook 1 codes"),
        ({"image": {**metadata["input"]["image"], "height": 9}}, "its input preprocessing makes"),
        ({"grid": {**metadata["input"]["grid"], "step_period_s": -1}}, "step_period_s -1"),
        ({"action": {"topic": "/cmd_vel", "type": "std_msgs/msg/String"}}, "command type"),
    ]:
        broken = {**metadata, "input": {**metadata["input"], **change}}
        path = robot["tmp"] / "broken.npz"
        write_archive(path, arrays, broken, force=True)
        with pytest.raises(ModelFormatError, match=re.escape(reason)):
            load_model(path)


@pytest.mark.slow
def test_a_bag_without_ground_truth_plots_by_time(robot, tmp_path, capsys):
    model = robot["tmp"] / "m_nopose.npz"
    bare = tmp_path / "bare"
    with BagReader(robot["bag"]) as reader, BagWriter(bare) as writer:
        for topic in (CAMERA, "/cmd_vel"):
            writer.add_topic(topic, reader.topics[topic])
        for m in reader.messages([CAMERA, "/cmd_vel"]):
            writer.write(m.topic, m.log_time_ns, m.data)
    argv = ["fit", str(robot["bag"]), "--image-topic", CAMERA, "--action-topic", "/cmd_vel",
            "--step-period", "1", "--image-size", "4x6", "--actions", "9", "-o", str(model), *SMALL]
    assert main(argv) == 0
    spec = model_stream_spec(model, read_metadata(model))
    assert (spec.preprocessing.height, spec.preprocessing.width) == (6, 4)
    code, out, _ = run_entry(["plot", str(model), str(bare), "-o", str(tmp_path / "t.png")], capsys)
    assert code == 0 and "no ground-truth pose in the bag(s): states coloured by time" in out


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--actions", "0"], "argument --actions: 0 is not positive"),
        (["--image-size", "80"], "is larger than the camera's 40x40: resizing up adds no"),
        (["--actions", "5000"], "are fewer than the 5000 codebook entries"),
        (["--actions", "25", "--step-period", "0.05"], "steps of 0.05 s have a new image"),
        (["--actions", "25", "--action-topic", "/odom"], "topic '/odom' of bag"),
        (["--actions", "25", "--components", "linear.z"], "['linear.z'] on '/cmd_vel' is constant"),
    ],
)
def test_bad_robot_input_is_one_line(robot, capsys, extra, message):
    base = ["fit", str(robot["bag"]), "--image-topic", CAMERA, *ROBOT, "-o",
            str(robot["tmp"] / "never.npz"), *SMALL]
    code, _, err = run_entry(base + extra, capsys)
    assert code != 0 and message in err, err
    errors = [line for line in err.splitlines() if "error" in line]
    assert len(errors) == 1 and "Traceback" not in err
    assert not (robot["tmp"] / "never.npz").exists()


def test_grid_options_need_a_step_period_and_a_corrupt_jpeg_is_named(tmp_path, capsys):
    bag = tmp_path / "jpeg"
    write_robot_bag(bag, RobotBagConfig(steps=12, seed=1, encoding="jpeg"))
    topic = CAMERA + "/compressed"
    broken = tmp_path / "broken"
    with BagReader(bag) as reader, BagWriter(broken) as writer:
        for name, msgtype in reader.topics.items():
            writer.add_topic(name, msgtype)
        index = 0
        for m in reader.messages():
            data = m.data
            if m.topic == topic:
                if index == 8:  # the frame ending simulator step 3: a step uses it
                    msg = m.decode()
                    msg = type(msg)(header=msg.header, format="jpeg", data=msg.data[:50])
                    data = msgs.serialize(msg, m.msgtype)
                index += 1
            writer.write(m.topic, m.log_time_ns, data)
    code, _, err = run_entry(
        ["fit", str(tmp_path / "none"), "--image-size", "8", "-o", str(tmp_path / "x.npz")], capsys
    )
    assert code != 0 and "--image-size need --step-period" in err
    spec = fit_stream_spec(
        [broken], options(actions=4, step_offset=0.15), image_topic=topic, action_topic="/cmd_vel"
    )
    with pytest.raises(MessageError, match=rf"topic '{topic}', message 8: corrupt jpeg image"):
        read_stream_trajectory([broken], spec)
    with pytest.raises(DataError, match="model's camera topic carries"):
        other = dataclass_replace_type(spec)
        read_stream_trajectory([broken], other)


def dataclass_replace_type(spec):
    import dataclasses

    return dataclasses.replace(spec, image_type="sensor_msgs/msg/Image")


# -- simulator bags: the exact-stamp pairing, bit for bit -----------------------------------


@pytest.mark.slow
def test_simulator_bags_give_the_model_of_the_unchanged_core_path(tmp_path):
    config = SimConfig(environment="full")
    bag = tmp_path / "sim"
    generate_bag(bag, config, 600, seed=4)
    model_path = tmp_path / "sim.npz"
    assert main(["fit", str(bag), "-o", str(model_path), *SMALL, "--preset", "guide"]) == 0
    run = random_rollout(config, 600, seed=4)
    # the observations and actions every earlier version used: pixels / 255, the 25 indices
    reference = Trajectory.from_arrays(
        run.actions.astype(np.int64),
        run.images.reshape(600, -1).astype(np.float64) / 255.0,
        stamps=run.stamps_ns,
        n_actions=25,
    )
    tpsr = TPSRConfig(obs_centers=40, ht_centers=80, rank=3)
    expected = fit_tpsr_episodes(make_episodes(reference, 1, 1), config=tpsr)
    assert model_fingerprint(load_model(model_path)) == model_fingerprint(expected)
    assert "input" not in read_metadata(model_path)  # read as simulator bags always were


@pytest.mark.slow
def test_ground_truth_from_tf_equals_odometry(robot, tmp_path):
    types = msgs.jazzy_typestore().types
    tf_bag = tmp_path / "tf"
    with BagReader(robot["bag"]) as reader, BagWriter(tf_bag) as writer:
        writer.add_topic(CAMERA, reader.topics[CAMERA])
        writer.add_topic("/cmd_vel", reader.topics["/cmd_vel"])
        writer.add_topic("/tf", "tf2_msgs/msg/TFMessage")
        for m in reader.messages([CAMERA, "/cmd_vel", "/odom"]):
            if m.topic != "/odom":
                writer.write(m.topic, m.log_time_ns, m.data)
                continue
            odom = m.decode()
            p = odom.pose.pose.position

            def transform(child, dx, p=p, odom=odom):
                return types["geometry_msgs/msg/TransformStamped"](
                    header=odom.header,
                    child_frame_id=child,
                    transform=types["geometry_msgs/msg/Transform"](
                        translation=types["geometry_msgs/msg/Vector3"](x=p.x + dx, y=p.y, z=0.0),
                        rotation=odom.pose.pose.orientation,
                    ),
                )

            tf = types["tf2_msgs/msg/TFMessage"](
                transforms=[transform("camera_link", 0.3), transform("base_link", 0.0)]
            )
            writer.write_message("/tf", m.log_time_ns, tf)
    spec = fit_stream_spec([robot["bag"]], options(), image_topic=CAMERA, action_topic="/cmd_vel")
    odom = read_stream_trajectory([robot["bag"]], spec, pose_topic="/odom")
    from_tf = read_stream_trajectory([tf_bag], spec, pose_topic="/tf", require_ground_truth=True)
    np.testing.assert_allclose(from_tf.positions, odom.positions, rtol=0, atol=1e-12)
    camera = read_stream_trajectory([tf_bag], spec, pose_topic="/tf", pose_frame="camera_link")
    np.testing.assert_allclose(camera.positions[:, 0], odom.positions[:, 0] + 0.3, atol=1e-9)


def test_steps_sharing_an_image_all_get_it(robot):
    """Several steps on one image (a step period below the camera's) each get its pixels."""
    from tpsr_ros.io.streams import _decode_images

    config, bag = robot["config"], robot["bag"]
    prep = Preprocessing(height=16, width=16)
    shared = _decode_images(bag, config.image_topic, msgs.IMAGE_TYPE, np.array([0, 0, 1, 1, 2]),
                            prep)
    alone = [_decode_images(bag, config.image_topic, msgs.IMAGE_TYPE, np.array([n]), prep)[0]
             for n in (0, 1, 2)]
    assert np.array_equal(shared, np.array([alone[0], alone[0], alone[1], alone[1], alone[2]]))


def test_the_recorded_topic_of_odd_training_metadata_is_none():
    from learner.inputs import recorded_topic

    # the descriptive metadata is not validated on load: anything may stand there
    for odd in ({}, {"training": []}, {"training": None}, {"training": {"bags": [1]}}):
        assert recorded_topic(odd, "pose") is None
    good = {"training": {"bags": [{"topics": {"pose": "/odom", "pose_frame": 3}}]}}
    assert recorded_topic(good, "pose") == "/odom"
    assert recorded_topic(good, "pose_frame") is None
