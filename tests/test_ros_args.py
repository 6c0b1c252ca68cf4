"""rcl's --ros-args grammar: splitting, parameters, remaps, log levels, errors."""

from __future__ import annotations

import pytest

from tpsr_ros.runtime.ros_args import (
    ParamOverride,
    ParamsFile,
    Remap,
    UsageError,
    parse_ros_args,
    split_ros_args,
)


def test_split_sections_and_double_dash():
    own, ros, seen = split_ros_args(
        ["-o", "bag", "--ros-args", "-p", "a:=1", "--", "/topic", "--ros-args", "-r", "x:=y"]
    )
    assert own == ["-o", "bag", "/topic"]
    assert ros == ["-p", "a:=1", "-r", "x:=y"]
    assert seen


def test_no_ros_args():
    assert split_ros_args(["a", "b"]) == (["a", "b"], [], False)


def test_parameters_are_typed_like_yaml():
    args = parse_ros_args(
        ["-p", "seed:=3", "--param", "rate:=2.5", "-p", "name:=full", "-p", "flag:=true",
         "-p", "list:=[1, 2]", "-p", "text:='3'"]
    )
    values = {p.name: p.value for p in args.parameters if isinstance(p, ParamOverride)}
    assert values == {
        "seed": 3, "rate": 2.5, "name": "full", "flag": True, "list": [1, 2], "text": "3"
    }
    assert type(values["seed"]) is int


def test_remaps_node_and_namespace():
    args = parse_ros_args(
        ["-r", "/cmd_vel:=/robot/cmd_vel", "-r", "__node:=sim2", "-r", "__ns:=/robot",
         "--remap", "other:/a:=/b"]
    )
    assert args.node_name("sim_node") == "sim2"
    assert args.namespace("sim2") == "/robot"
    assert args.topic_remaps("sim2") == [Remap("/cmd_vel", "/robot/cmd_vel")]
    assert args.topic_remaps("other") == [
        Remap("/cmd_vel", "/robot/cmd_vel"), Remap("/a", "/b", "other")
    ]


def test_log_levels_global_and_per_logger():
    args = parse_ros_args(["--log-level", "WARN", "--log-level", "sim_node:=debug"])
    assert args.log_level("sim_node") == "debug"
    assert args.log_level("other") == "warn"
    assert parse_ros_args([]).log_level("x") == "info"


def test_params_file_and_flags(tmp_path):
    path = tmp_path / "p.yaml"
    path.write_text("x: {ros__parameters: {seed: 1}}\n")
    args = parse_ros_args(["--params-file", str(path), "--disable-stdout-logs", "-e", "/e"])
    assert args.parameters == (ParamsFile(path),)
    assert "--disable-stdout-logs" in args.flags
    assert args.enclave == "/e"


@pytest.mark.parametrize(
    "tokens, fragment",
    [
        (["--bogus"], "unknown ROS argument '--bogus'"),
        (["-p"], "needs a value"),
        (["-p", "seed=3"], "not of the form name:=value"),
        (["-p", "9bad:=1"], "not a valid parameter name"),
        (["-p", "x:=[1, 2"], "cannot parse value"),
        (["-p", "x:={a: 1}"], "is a mapping"),
        (["-r", "a b:=c"], "does not map one topic"),
        (["-r", "__node:=bad-name"], "not a valid node name"),
        (["-r", "__ns:=relative"], "not an absolute namespace"),
        (["--log-level", "loud"], "unknown level"),
        (["--params-file", "/nonexistent/params.yaml"], "does not exist"),
        (["stray"], "unknown ROS argument 'stray'"),
    ],
)
def test_malformed_ros_args_are_one_line_usage_errors(tokens, fragment):
    with pytest.raises(UsageError) as info:
        parse_ros_args(tokens)
    message = str(info.value)
    assert fragment in message
    assert "\n" not in message
