"""The package under the real ROS 2 tools: ``colcon build --symlink-install``, ``ros2 run``,
``ros2 param set/get/describe`` and ``ros2 launch`` of the closed loop.

Runs where a real ``ros2`` command with ``launch_ros`` is on PATH and importable: a sourced
ROS 2 Jazzy, or the Jazzy command-line tools (ros2cli, launch, launch_ros, osrf_pycommon,
rosidl_runtime_py; all pure Python) installed from source into a venv that has the PyPI
rclpy wheels and this package's dependencies::

    VENV/bin/pip install -e '.[dds,test,ros]'   # plus the tools' sources, then
    PATH=VENV/bin:$PATH AMENT_PREFIX_PATH=VENV VENV/bin/python -m pytest -m ros2cli \
        tests/test_ros2cli.py

and is skipped (saying why) elsewhere: `make test` has no ROS 2 command-line tools.
"""

from __future__ import annotations

import importlib.util
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from graph_support import fresh_domain
from test_colcon import _copy_tracked_files

ROOT = Path(__file__).resolve().parent.parent


def _real_ros2() -> str | None:
    """Why the real tools are missing, or None."""
    if shutil.which("ros2") is None:
        return "no ros2 command on PATH (see this module's docstring)"
    for module in ("ros2cli", "launch_ros", "rclpy"):
        if importlib.util.find_spec(module) is None:
            return f"{module} is not importable"
    if shutil.which("colcon") is None:
        return "no colcon on PATH"
    return None


pytestmark = [
    pytest.mark.ros2cli,
    pytest.mark.slow,
    pytest.mark.skipif(_real_ros2() is not None, reason=str(_real_ros2())),
]


@pytest.fixture(scope="module")
def ros2(tmp_path_factory):
    """A colcon workspace of this repository built with --symlink-install, and the
    environment its install/setup.bash gives."""
    workspace = tmp_path_factory.mktemp("ros2cli") / "ws"
    _copy_tracked_files(workspace / "src" / "tpsr-ros")
    build = subprocess.run(
        ["colcon", "build", "--symlink-install", "--event-handlers", "console_direct-"],
        cwd=workspace, capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert build.returncode == 0, build.stdout[-3000:] + build.stderr[-3000:]
    dump = subprocess.run(
        ["bash", "-c", "source install/setup.bash && env -0"],
        cwd=workspace, capture_output=True, timeout=60, check=True,
    ).stdout  # fmt: skip
    env = dict(item.split("=", 1) for item in dump.decode().split("\0") if "=" in item)
    env.update(
        ROS_DOMAIN_ID=str(fresh_domain(71)),
        ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
        TPSR_TRANSPORT="rclpy",
        PYTHONUNBUFFERED="1",
    )
    return {"workspace": workspace, "env": env}


def run(ros2, *argv: str, timeout: float = 60) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        list(argv), env=ros2["env"], capture_output=True, text=True, timeout=timeout,
        cwd=ros2["workspace"],
    )  # fmt: skip


def start(ros2, *argv: str, log: Path) -> subprocess.Popen[bytes]:
    """A process in its own group (signalled as a terminal's Ctrl-C signals one)."""
    return subprocess.Popen(
        list(argv), env=ros2["env"], stdout=log.open("wb"), stderr=subprocess.STDOUT,
        cwd=ros2["workspace"], start_new_session=True,
    )  # fmt: skip


def stop(process: subprocess.Popen[bytes], timeout: float = 30) -> int:
    if process.poll() is None:
        os.killpg(process.pid, signal.SIGINT)
        try:
            process.wait(timeout)
        except subprocess.TimeoutExpired:
            os.killpg(process.pid, signal.SIGKILL)
    return int(process.wait())


def wait_for(condition, timeout: float = 30) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(0.2)
    return False


def test_ros2_run_names_the_executable(ros2):
    result = run(ros2, "ros2", "run", "tpsr_ros", "sim_node", "--help")
    assert result.returncode == 0 and "usage: ros2 run tpsr_ros sim_node" in result.stdout
    bad = run(ros2, "ros2", "run", "tpsr_ros", "sim_node", "--ros-args", "-p", "rate:=-1")
    assert bad.returncode != 0 and "ros2 run tpsr_ros sim_node: error:" in bad.stderr


def test_ros2_param_set_get_describe_and_sim_time(ros2, tmp_path):
    sim = start(ros2, "ros2", "run", "tpsr_ros", "sim_node", "--ros-args", "-p", "rate:=5",
                "-p", "use_sim_time:=true", log=tmp_path / "sim.log")  # fmt: skip
    try:
        spin = ("--spin-time", "3")
        assert wait_for(lambda: "/sim_node" in run(ros2, "ros2", "node", "list", *spin).stdout)
        set_rate = run(ros2, "ros2", "param", "set", "/sim_node", "rate", "20")
        assert "Set parameter successful" in set_rate.stdout, set_rate
        assert "Double value is: 20.0" in run(ros2, "ros2", "param", "get", "/sim_node",
                                               "rate").stdout  # fmt: skip
        described = run(ros2, "ros2", "param", "describe", "/sim_node", "rate", "environment")
        assert "Additional constraints: > 0" in described.stdout, described.stdout
        assert "one of: full, partial, distractors" in described.stdout
        sim_time = run(ros2, "ros2", "param", "get", "/sim_node", "use_sim_time").stdout
        assert "Boolean value is: True" in sim_time, sim_time
    finally:
        code = stop(sim)
    assert code == 0 and "Traceback" not in (tmp_path / "sim.log").read_text()


def test_disable_stdout_logs_silences_the_console(ros2, tmp_path):
    log = tmp_path / "quiet.log"
    sim = start(ros2, "ros2", "run", "tpsr_ros", "sim_node", "--ros-args",
                "--disable-stdout-logs", log=log)  # fmt: skip
    time.sleep(4)
    assert stop(sim) == 0
    assert "episode starts at" not in log.read_text(), log.read_text()


def test_a_misspelt_launch_param_is_refused(ros2, tmp_path):
    launch_file = tmp_path / "typo.launch.xml"
    launch_file.write_text(
        "<launch><node pkg='tpsr_ros' exec='sim_node' name='sim_node' on_exit='shutdown'>"
        "<param name='stpes' value='5'/></node></launch>"
    )
    result = run(ros2, "ros2", "launch", str(launch_file), timeout=60)
    assert "unknown parameter 'stpes'" in result.stdout + result.stderr, result


def test_the_closed_loop_launch_stops_everything_when_a_node_exits(ros2, tmp_path):
    started = time.monotonic()
    result = run(ros2, "ros2", "launch", "tpsr_ros", "closed_loop.launch.xml",
                 f"model:={tmp_path / 'missing.npz'}", f"policy:={tmp_path / 'missing.npz'}",
                 f"bag:={tmp_path / 'bag'}", timeout=120)  # fmt: skip
    output = result.stdout + result.stderr
    assert "filter_node: error:" in output, output
    assert time.monotonic() - started < 60  # not until someone presses Ctrl-C
    assert result.returncode != 0 or "process has finished cleanly" in output


def test_the_closed_loop_runs_under_ros2_launch(ros2, tmp_path):
    data = tmp_path / "train"
    py = sys.executable
    for argv in (
        [py, "-m", "sim_node.generate", "--environment", "full", "--steps", "1500", "-o",
         str(data), "--quiet"],
        [py, "-m", "learner", "fit", str(data), "--ht-centers", "200", "--obs-centers", "200",
         "-o", str(tmp_path / "m.npz")],
        [py, "-m", "learner", "policy", str(tmp_path / "m.npz"), str(data), "-o",
         str(tmp_path / "p.npz")],
    ):  # fmt: skip
        done = run(ros2, *argv, timeout=300)
        assert done.returncode == 0, done.stderr[-2000:]
    log = tmp_path / "launch.log"
    launch = start(ros2, "ros2", "launch", "tpsr_ros", "closed_loop.launch.xml",
                   f"model:={tmp_path / 'm.npz'}", f"policy:={tmp_path / 'p.npz'}",
                   f"bag:={tmp_path / 'loop'}", "episode_steps:=20", log=log)  # fmt: skip
    try:
        assert wait_for(lambda: "episode starts at" in log.read_text(), 90), log.read_text()
        time.sleep(10)  # 20 lockstep steps take well under a second
    finally:
        stop(launch)
    text = log.read_text()
    assert "Traceback" not in text, text
    from tpsr_ros.io.bag import BagReader

    with BagReader(tmp_path / "loop") as reader:
        states = sum(1 for _ in reader.messages(["/tpsr/state"]))
        missing = reader.custom_data.get("recorder.missing_by_stamps")
    assert states >= 20 and missing == "0", (states, missing)
