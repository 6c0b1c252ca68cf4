"""Details a user meets on the command line: a hint for ROS arguments given without
--ros-args, bag_info on .mcap files, a player stopped early that says so, the demo's output
per environment, progress as plain lines in logs."""

from __future__ import annotations

import io
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tpsr_ros.cli import ros_args_hint
from tpsr_ros.progress import LineProgress, progress_bar

ROOT = Path(__file__).resolve().parents[1]


def _run(*args: str, **kw) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, *args], capture_output=True, text=True, timeout=60, cwd=ROOT, **kw
    )


def test_ros_arguments_without_ros_args_get_a_hint():
    proc = _run("-m", "tpsr_ros.filter_node", "-p", "model:=x")
    assert proc.returncode == 2
    assert proc.stderr.strip() == (
        "python -m tpsr_ros.filter_node: error: unrecognized arguments: -p model:=x (ROS "
        "arguments go after --ros-args, as for any ROS 2 node: python -m tpsr_ros.filter_node "
        "--ros-args -p model:=x)"
    )
    assert ros_args_hint("unrecognized arguments: --foo", "prog") == ""
    assert "--ros-args -r a:=b" in ros_args_hint("unrecognized arguments: -r a:=b", "prog")
    assert ros_args_hint("the following arguments are required: -o", "prog") == ""


@pytest.fixture(scope="module")
def bag(tmp_path_factory):
    from sim_node.config import SimConfig
    from sim_node.generate import generate_bag

    path = tmp_path_factory.mktemp("details") / "bag"
    generate_bag(path, SimConfig(environment="full"), 6, seed=0)
    return path


def test_bag_info_takes_a_bags_mcap_file_and_a_lone_mcap(bag, tmp_path):
    from tpsr_ros.bag_info import format_info

    whole = format_info(bag)
    mcap = next(bag.glob("*.mcap"))
    assert format_info(mcap) == whole  # a bag's file: the bag
    lone = tmp_path / "lone.mcap"
    lone.write_bytes(mcap.read_bytes())
    text = format_info(lone)
    assert "lone.mcap (no metadata.yaml)" in text and "Messages:          " in text
    for line in whole.splitlines():
        if "Topic: " in line:  # same topics, types and counts
            assert line.split("| QoS")[0].split("Topic: ")[1] in text
    proc = _run("-m", "tpsr_ros.bag_info", str(bag / "metadata.yaml"))
    assert proc.returncode == 1 and "is not a rosbag2 directory" in proc.stderr


@pytest.mark.slow
def test_a_player_stopped_early_says_it_was_interrupted_and_how_much_it_played(bag):
    env = {**os.environ, "TPSR_TRANSPORT": "inproc", "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen(
        [sys.executable, "-m", "tpsr_ros.play", str(bag), "--rate", "0.5"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=ROOT, env=env,
    )  # fmt: skip
    assert proc.stdout is not None
    first = proc.stdout.readline()  # the node is up (however long the imports took)
    time.sleep(2.0)  # 6 steps at half speed: 12 s
    proc.send_signal(signal.SIGINT)
    out, _ = proc.communicate(timeout=30)
    out = first + out
    assert "interrupted (SIGINT received): played " in out, out
    played = re.search(r"played (\d+) of (\d+) messages \(\d+ %\) from \S+, not the whole bag", out)
    assert played and 0 < int(played.group(1)) < int(played.group(2)), out


def test_the_demo_writes_under_its_environment_and_leaves_the_others(tmp_path, monkeypatch):
    import learner.demo as demo

    class Stop(Exception):
        pass

    def stop(*_args, **_kwargs):
        raise Stop

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(demo, "generate_bag", stop)
    earlier = tmp_path / "demo_output" / "full" / "score.txt"
    earlier.parent.mkdir(parents=True)
    earlier.write_text("kept")
    with pytest.raises(Stop):
        demo.main(["--environment", "partial"])
    assert earlier.read_text() == "kept"
    assert (tmp_path / "demo_output" / "partial" / "bags").is_dir()


def test_progress_in_a_log_is_plain_lines_and_a_bar_only_on_a_terminal():
    log = io.StringIO()
    bar = progress_bar(total=100, desc="full", unit="step", file=log, period_s=0.0)
    assert isinstance(bar, LineProgress)
    with bar:
        for _ in range(4):
            bar.update(25)
        bar.write("a message")
    text = log.getvalue()
    assert "\r" not in text
    assert "full: 25/100 step (25 %)" in text and "full: 100/100 step (100 %)" in text
    assert "a message\n" in text
    quiet = io.StringIO()
    with progress_bar(total=3, desc="x", unit="run", disable=True, file=quiet) as bar:
        bar.update(3)
    assert quiet.getvalue() == ""

    class Terminal(io.StringIO):
        def isatty(self) -> bool:
            return True

    screen = Terminal()
    with progress_bar(total=10, desc="full", unit="step", file=screen) as bar:
        bar.update(10)
    assert "\r" in screen.getvalue()  # tqdm's bar
