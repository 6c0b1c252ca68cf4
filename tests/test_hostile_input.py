"""Hostile input: params files, -p values, bag metadata.yaml, damaged MCAP bytes."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

from tpsr_ros.core.errors import BagError
from tpsr_ros.io.bag import BagReader
from tpsr_ros.io.safe_yaml import rcl_scalar
from tpsr_ros.runtime.params import param, resolve_parameters
from tpsr_ros.runtime.ros_args import UsageError, parse_ros_args

BAGS = Path(__file__).resolve().parent.parent / "bags"
LAUGHS = "\n".join(
    ['a: &a ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]']
    + [f"{chr(98 + i)}: &{chr(98 + i)} [{','.join(['*' + chr(97 + i)] * 9)}]" for i in range(8)]
    + ["node:", "  ros__parameters:", "    steps: *i"]
)


@dataclass(frozen=True)
class Params:
    steps: int = param(10, "steps")
    rate: float = param(1.0, "rate")
    name: str = param("x", "name")
    gains: tuple[float, ...] = param((1.0,), "gains")


def _resolve(*tokens: str) -> Params:
    return resolve_parameters(Params, parse_ros_args(list(tokens)), "/node")


def _params_file(tmp_path: Path, content: str | bytes) -> str:
    path = tmp_path / "params.yaml"
    path.write_bytes(content.encode() if isinstance(content, str) else content)
    return str(path)


@pytest.mark.parametrize(
    "content, fragment",
    [
        (LAUGHS, "anchors and aliases are not supported"),
        ("a: &a [*a]\n", "anchors and aliases are not supported"),
        (b"node:\n  ros__parameters:\n    name: \xff\xfe\n", "not UTF-8 text"),
        ("node:\n  ros__parameters:\n    gains: " + "[" * 5000 + "]" * 5000 + "\n",
         "nested deeper than 32 levels"),
        ("node:\n  ros__parameters:\n    steps: " + "7" * 5001 + "\n",
         "expects an integer, got string 777"),
        ("node:\n  ros__parameters:\n    gains: [[1.0]]\n", "nested sequences"),
        ("node: [unclosed\n", "not valid YAML (line 2)"),
    ],
)
@pytest.mark.timeout(30)  # an exponential expansion (a YAML bomb) would not end: it fails
def test_hostile_params_files_are_one_line_usage_errors(tmp_path, content, fragment):
    with pytest.raises(UsageError) as info:
        _resolve("--params-file", _params_file(tmp_path, content))
    assert fragment in str(info.value) and "\n" not in str(info.value)


def test_values_are_typed_as_rcl_types_them():
    # rcl (rcl_yaml_param_parser get_value), not YAML 1.1: no sexagesimal, C integer bases
    assert rcl_scalar("1:00") == "1:00"
    assert rcl_scalar("0x1f") == 31 and rcl_scalar("017") == 15 and rcl_scalar("-3") == -3
    assert rcl_scalar("yes") is True and rcl_scalar("Off") is False and rcl_scalar("TRUE") is True
    assert rcl_scalar("true", quoted=True) == "true" and rcl_scalar("5", quoted=True) == "5"
    assert rcl_scalar("1e3") == 1000.0 and rcl_scalar(".inf") == float("inf")
    assert rcl_scalar("9" * 30) == 1e30  # beyond int64: strtol fails, strtod reads a double
    assert rcl_scalar("9" * 400) == "9" * 400  # strtod overflows too: a string
    assert rcl_scalar("1_000") == "1_000" and rcl_scalar("null") == "null"
    with pytest.raises(UsageError, match="expects an integer, got string 1:00"):
        _resolve("-p", "steps:=1:00")
    assert _resolve("-p", "steps:=0x10", "-p", "gains:=[1, 2.5]") == Params(steps=16,
                                                                             gains=(1.0, 2.5))
    for value, fragment in [
        ("[" * 5000 + "]" * 5000, "nested deeper than 32 levels"),
        ("[[1.0]]", "nested sequences"),
        ("*x", "cannot parse value"),
        ("7" * 5001, "expects an integer, got string"),
    ]:
        with pytest.raises(UsageError, match=fragment):
            _resolve("-p", f"steps:={value}")


def _bag_with_metadata(tmp_path: Path, change) -> Path:
    bag = tmp_path / "bag"
    shutil.copytree(BAGS / "full", bag)
    meta = bag / "metadata.yaml"
    meta.write_bytes(change(meta.read_bytes()))
    return bag


@pytest.mark.parametrize(
    "change, fragment",
    [
        (lambda data: data.replace(b"mcap", b"mc\xffap", 1), "not UTF-8 text"),
        (lambda data: data + b"deep: " + b"[" * 20000 + b"]" * 20000 + b"\n",
         "nested deeper than 32 levels"),
        (lambda data: data.replace(b"custom_data:", b"custom_data: [1, 2]\n  unused:", 1)
         if b"custom_data:" in data else data + b"  custom_data: [1, 2]\n",
         "custom_data is not a mapping"),
        (lambda data: b"&a x: *a\n" + data, "anchors and aliases"),
        # fuzz findings: a 5001-digit integer (int() refuses > 4300 digits: ValueError) and a
        # type that PyYAML reads as text but rosbags' YAML 1.2 reader as a float
        (lambda data: data.replace(b"serialization_format: cdr", b"serialization_format: "
                                   + b"9" * 5001, 1), "a value it cannot read"),
        (lambda data: data.replace(b"type: sensor_msgs/msg/Image", b"type: 1e-400", 1),
         "has a name or type that is not text"),
    ],
)
def test_hostile_bag_metadata_is_a_one_line_bag_error(tmp_path, change, fragment):
    bag = _bag_with_metadata(tmp_path, change)
    with pytest.raises(BagError) as info:
        BagReader(bag)
    assert fragment in str(info.value) and "\n" not in str(info.value)


def test_a_node_refuses_a_billion_laughs_params_file_in_one_line(tmp_path):
    path = _params_file(tmp_path, LAUGHS.replace("node:", "sim_node:"))
    result = subprocess.run(
        [sys.executable, "-m", "sim_node", "--ros-args", "--params-file", path],
        capture_output=True, text=True, timeout=60,
    )
    assert result.returncode == 2
    assert result.stderr.strip().count("\n") == 0 and "Traceback" not in result.stderr
    assert "anchors and aliases are not supported" in result.stderr


def _read_all(bag: Path) -> int:
    with BagReader(bag) as reader:
        return sum(1 for _ in reader.messages())


@pytest.mark.slow
def test_damaged_mcap_bytes_give_a_bag_error_never_a_traceback(tmp_path):
    # seeded mutations of the sample bag: flipped bits inside compressed chunks, records
    # claiming 2**40 bytes, zeroed lengths; each read either succeeds or says "damaged"
    import numpy as np

    source = BAGS / "full" / "full.mcap"
    original = source.read_bytes()
    rng = np.random.default_rng(17)
    outcomes = {"read": 0, "refused": 0}
    for case in range(60):
        data = bytearray(original)
        offset = int(rng.integers(8, len(data) - 8))
        kind = case % 3
        if kind == 0:
            data[offset] ^= 1 << int(rng.integers(8))
        elif kind == 1:
            data[offset : offset + 8] = (2**40).to_bytes(8, "little")
        else:
            data[offset : offset + 8] = bytes(8)
        bag = tmp_path / f"case{case}"
        bag.mkdir()
        shutil.copy(BAGS / "full" / "metadata.yaml", bag)
        (bag / "full.mcap").write_bytes(bytes(data))
        try:
            _read_all(bag)
            outcomes["read"] += 1
        except BagError as exc:
            assert "\n" not in str(exc)
            outcomes["refused"] += 1
        shutil.rmtree(bag)
    assert outcomes["refused"] > 10, outcomes  # the mutations do hit structure and chunks


@pytest.mark.slow
def test_messages_missing_from_what_the_metadata_lists_are_reported(tmp_path):
    # rosbag2's own talker bag read as 0 of 20 messages and `play` exited 0: never again
    bag = _bag_with_metadata(
        tmp_path, lambda data: data.replace(b"message_count: 3000", b"message_count: 3005", 1)
    )
    with BagReader(bag) as reader, pytest.raises(BagError, match="read 15000 of the 15005"):
        for _ in reader.messages():
            pass
    result = subprocess.run([sys.executable, "-m", "tpsr_ros.play", str(bag), "--rate", "100000"],
                            capture_output=True, text=True, timeout=120)
    assert result.returncode != 0 and "read 15000 of the 15005 messages" in result.stderr


def _summary_records(data: bytes) -> list[tuple[int, int]]:
    """(offset, opcode) of the summary section's records."""
    import struct

    footer = len(data) - 8 - 29  # the footer record, then the closing magic
    found, offset = [], struct.unpack_from("<Q", data, footer + 9)[0]
    while offset < footer:
        opcode, length = struct.unpack_from("<BQ", data, offset)
        found.append((offset, opcode))
        offset += 9 + length
    return found


@pytest.mark.parametrize("claimed", [2**31, 2**40, 2**64 - 1])
def test_a_record_claiming_gigabytes_is_refused_before_any_allocation(tmp_path, claimed):
    # the fuzzer's finding: a summary record's length read as 2**31..2**64 made rosbags
    # allocate it (MemoryError under a 2 GiB cap, 2 GiB taken without one)
    import struct

    bag = tmp_path / "bag"
    shutil.copytree(BAGS / "full", bag)
    mcap = bag / "full.mcap"
    data = bytearray(mcap.read_bytes())
    offset, _ = _summary_records(bytes(data))[0]
    data[offset + 1 : offset + 9] = struct.pack("<Q", claimed)
    mcap.write_bytes(bytes(data))
    with pytest.raises(BagError, match=rf"record at offset {offset} claims {claimed} bytes"):
        BagReader(bag)


def test_a_chunk_index_declaring_a_huge_chunk_is_refused(tmp_path):
    import struct

    bag = tmp_path / "bag"
    shutil.copytree(BAGS / "full", bag)
    mcap = bag / "full.mcap"
    data = bytearray(mcap.read_bytes())
    offset = next(o for o, opcode in _summary_records(bytes(data)) if opcode == 0x08)
    (map_length,) = struct.unpack_from("<I", data, offset + 9 + 32)
    (name_length,) = struct.unpack_from("<I", data, offset + 9 + 36 + map_length + 8)
    at = offset + 9 + 36 + map_length + 12 + name_length + 8  # uncompressed_size
    data[at : at + 8] = struct.pack("<Q", 2**40)
    mcap.write_bytes(bytes(data))
    with pytest.raises(BagError, match=r"declares a chunk of 1099511627776 bytes"):
        BagReader(bag)


def test_metadata_listing_a_file_outside_the_bag_is_refused(tmp_path):
    bag = _bag_with_metadata(
        tmp_path, lambda data: data.replace(b"- full.mcap", b"- ../full/full.mcap", 1)
    )
    with pytest.raises(BagError, match=r"lists '\.\./full/full\.mcap', which is not a file"):
        BagReader(bag)


def test_a_closed_stdout_ends_a_command_quietly():
    # `python -m tpsr_ros.bag_info BAG | head -1` printed a BrokenPipeError traceback
    process = subprocess.Popen(
        [sys.executable, "-m", "tpsr_ros.bag_info", str(BAGS / "full")],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE,
    )
    process.stdout.close()  # the reader went away before the first line
    stderr = process.stderr.read().decode()
    assert process.wait(timeout=60) == 141 and stderr == ""


def test_a_rate_too_high_for_a_timer_is_a_one_line_error():
    # fuzz finding: -p rate:=0x7fffffffffffffff made the explore timer's period 0 ns and the
    # node died of ZeroDivisionError on its first tick
    result = subprocess.run(
        [sys.executable, "-m", "sim_node", "--ros-args", "-p", "rate:=0x7fffffffffffffff"],
        capture_output=True, text=True, timeout=60, env={**os.environ, "TPSR_TRANSPORT": "inproc"},
    )
    assert result.returncode == 1 and "Traceback" not in result.stderr
    assert result.stderr.strip().splitlines()[-1].startswith(
        "python -m sim_node: error: timer period must be at least 1 ns"
    )


@pytest.mark.parametrize("descriptive", [
    {"training": {"bags": 5}},  # the fuzz finding: AttributeError 'int' has no 'get'
    {"training": {"bags": [1, "x", {"path": 3}]}},
    {"training": [1, 2], "summary": "x", "software": 7, "observation": [1]},
    {"summary": {"explained_variance": {"obs": 3, "test": {"total": "high"}},
                 "timings": {"fit": "slow"}, "singular_values": [1, "a"]}},
])
def test_learner_info_prints_whatever_descriptive_metadata_a_file_carries(descriptive):
    # load_model validates what it uses; info also prints what it does not (training data,
    # summary, software): those fields may hold anything and must not crash the command
    from learner.info import info_lines

    metadata = {"format": "tpsr-ros model", "format_version": 1, "method": "tpsr",
                "n_actions": 3, "parameters": {"rank": 2}, **descriptive}
    lines = info_lines(Path("m.npz"), metadata)
    assert lines[0] == "model: m.npz" and "parameters: rank=2" in lines


def test_learner_info_formats_well_formed_descriptive_metadata():
    from learner.info import info_lines

    metadata = {"format": "tpsr-ros model", "format_version": 1, "method": "tpsr",
                "n_actions": 3, "parameters": {"rank": 2},
                "training": {"steps": 10, "bags": [{"path": "b1"}, {"path": "b2"}]},
                "summary": {"explained_variance": {"obs": {"total": 0.91234}},
                            "timings": {"SVD": 0.5}}}
    lines = info_lines(Path("m.npz"), metadata)
    assert "bags: b1, b2" in lines and "explained variance (obs): 0.912" in lines
    assert "fit timing: SVD 0.500 s" in lines


def test_a_model_path_too_long_for_the_file_system_is_a_one_line_error(tmp_path):
    # fuzz finding: -p model:=<5001 digits> (via a params file) made pathlib's is_dir raise
    # OSError ENAMETOOLONG in the filter node's preflight
    from tpsr_ros.core.errors import ModelFormatError
    from tpsr_ros.io.model_io import load_model
    from tpsr_ros.io.policy import load_policy

    for load in (load_model, load_policy):
        with pytest.raises(ModelFormatError, match="cannot be opened: File name too long"):
            load("9" * 5001)
    with pytest.raises(ModelFormatError, match="is a directory"):
        load_model(tmp_path)
    with pytest.raises(ModelFormatError, match="does not exist"):
        load_model(tmp_path / "missing.npz")


def test_library_error_text_is_cut_to_one_line():
    from tpsr_ros.core.errors import one_line

    assert one_line(ValueError("bad\n  header\tat 3")) == "bad header at 3"
    assert one_line(OSError()) == "OSError"
    long = one_line(ValueError("x" * 500), limit=50)
    assert len(long) == 50 and long.endswith("...")


def _learner(*argv: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "learner", *argv], cwd=cwd, capture_output=True, text=True,
        timeout=120,
    )


def _one_line_error(done: subprocess.CompletedProcess[str]) -> str:
    """The error line of a command that failed cleanly (progress lines may precede it)."""
    assert done.returncode == 1 and "Traceback" not in done.stderr, done.stderr
    last = done.stderr.strip().splitlines()[-1]
    assert last.startswith("learner: error: "), done.stderr
    return last


def test_deeply_nested_generator_settings_are_a_one_line_error(tmp_path):
    """custom_data holding 5000 '[' is a BagError naming the bag, not a RecursionError."""
    import yaml

    bag = tmp_path / "bag"
    shutil.copytree(Path(__file__).parents[1] / "bags" / "full", bag)
    metadata = bag / "metadata.yaml"
    content = yaml.safe_load(metadata.read_text())
    content["rosbag2_bagfile_information"]["custom_data"]["tpsr_ros.generator"] = "[" * 5000
    metadata.write_text(yaml.safe_dump(content))
    done = _learner("fit", str(bag), "-o", str(tmp_path / "m.npz"), cwd=tmp_path)
    assert "nested too deeply" in _one_line_error(done)


def test_a_named_pose_topic_missing_from_the_bag_is_a_one_line_error(tmp_path):
    bag = Path(__file__).parents[1] / "bags" / "full"
    done = _learner("fit", str(bag), "-o", str(tmp_path / "m.npz"), "--pose-topic", "/odom",
                    cwd=tmp_path)
    assert "has no messages on --pose-topic /odom" in _one_line_error(done)
    assert not (tmp_path / "m.npz").exists()


def test_a_compressed_camera_without_a_step_period_says_to_add_one(tmp_path):
    from sim_node.robot_bag import RobotBagConfig, write_robot_bag

    bag = tmp_path / "robot"
    write_robot_bag(bag, RobotBagConfig(steps=5, encoding="jpeg"))
    done = _learner("fit", str(bag), "-o", str(tmp_path / "m.npz"), "--image-topic",
                    "/front_camera/image_raw/compressed", "--action-topic", "/cmd_vel",
                    cwd=tmp_path)
    line = _one_line_error(done)
    assert "CompressedImage" in line and "add --step-period SECONDS" in line
