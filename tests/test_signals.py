"""Three SIGINTs within 100 ms (a terminal's Ctrl-C under ``ros2 launch`` sends two) stop a
node without a traceback, on both real backends; a node launched from a process that ignores
SIGINT still stops on the launcher's; a SIGINT that comes while the node is being built (it
may already log) shuts it down gracefully once it exists."""

from __future__ import annotations

import os
import signal
import time
from typing import ClassVar

import pytest
from graph_support import BACKENDS, LOOPBACK, fresh_domain

from tpsr_ros.core.errors import DataError
from tpsr_ros.runtime import Node, run_node
from tpsr_ros.runtime.launcher import NodeProcess

NODES = [
    ("sim_node", ["--ros-args", "-p", "rate:=50"], "episode starts at"),
    ("tpsr_ros.record", ["-o", "{tmp}/bag", "/camera/image_raw"], "recording /camera"),
]


@pytest.mark.slow
@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize(("module", "args", "ready"), NODES, ids=["sim_node", "record"])
def test_repeated_sigint_stops_a_node_without_a_traceback(
    backend, module, args, ready, tmp_path
):
    env = {
        **os.environ,
        "TPSR_TRANSPORT": backend,
        "ROS_DOMAIN_ID": str(fresh_domain(53)),
        "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
        "CYCLONEDDS_URI": LOOPBACK,
    }
    argv = [a.format(tmp=tmp_path) for a in args]
    node = NodeProcess(module, module, argv, log_path=tmp_path / "node.log", env=env)
    try:
        deadline = time.monotonic() + 60
        while ready not in node.text() and node.alive() and time.monotonic() < deadline:
            time.sleep(0.05)
        assert ready in node.text(), node.text()
        for _ in range(3):
            os.kill(node.pid, signal.SIGINT)
            time.sleep(0.03)
        code = node.wait(30)
    finally:
        node.kill()
    text = node.text()
    assert "Traceback" not in text and "KeyboardInterrupt" not in text, text
    assert code in (0, 130), (code, text)


def test_a_node_launched_where_sigint_is_ignored_still_stops_on_sigint(tmp_path):
    """A script's background job ignores SIGINT, and a child inherits that; the launcher's
    SIGINT must still stop its node, not leave it to the stop timeout's kill."""
    (tmp_path / "waiting_node.py").write_text(
        "import signal, time\n"
        "print('up', signal.getsignal(signal.SIGINT) is signal.default_int_handler, flush=True)\n"
        "time.sleep(60)\n"
    )
    path = os.pathsep.join([str(tmp_path), os.environ.get("PYTHONPATH", "")])
    env = {**os.environ, "PYTHONPATH": path}
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        node = NodeProcess("waiting", "waiting_node", log_path=tmp_path / "node.log", env=env)
    finally:
        signal.signal(signal.SIGINT, previous)
    try:
        deadline = time.monotonic() + 30
        while "up" not in node.text() and node.alive() and time.monotonic() < deadline:
            time.sleep(0.02)
        assert "up True" in node.text(), node.text()
        # ended by its KeyboardInterrupt (Python then re-raises SIGINT), not killed after 10 s
        assert node.stop(timeout_s=10) == -signal.SIGINT
    finally:
        node.kill()


class _SignalledWhileStarting(Node):
    """A node that receives ``signals`` during its setup, after it has started to log
    (as ``sim_node`` logs its first episode there), and records how it was closed."""

    default_name = "signalled"
    signals: ClassVar[int] = 1
    shutdown_reasons: ClassVar[list[str | None]] = []

    def setup(self) -> None:
        self.logger.info("started")
        for _ in range(self.signals):
            os.kill(os.getpid(), signal.SIGINT)

    def on_shutdown(self) -> None:
        self.shutdown_reasons.append(self.shutdown_reason)


@pytest.mark.parametrize(("signals", "code"), [(1, 0), (2, 130)])
def test_a_signal_while_the_node_starts_shuts_it_down_once_it_exists(
    signals, code, monkeypatch
):
    """One SIGINT during the node's construction is a graceful shutdown as soon as the
    node exists (exit 0, the node closed); a second one stops waiting (130: the
    construction is interrupted, and the caller's handlers are put back)."""
    monkeypatch.setenv("TPSR_TRANSPORT", "inproc")
    monkeypatch.setattr(_SignalledWhileStarting, "signals", signals)
    monkeypatch.setattr(_SignalledWhileStarting, "shutdown_reasons", [])
    before = signal.getsignal(signal.SIGINT)
    try:
        with pytest.raises(SystemExit) as info:
            run_node(_SignalledWhileStarting, prog="signalled", argv=[])
    finally:
        after = signal.getsignal(signal.SIGINT)
        signal.signal(signal.SIGINT, before)
    assert info.value.code == code
    if signals == 1:
        assert _SignalledWhileStarting.shutdown_reasons == ["SIGINT received while starting"]
        assert after is signal.SIG_IGN  # a node ran: ignored while Python exits
    else:
        assert _SignalledWhileStarting.shutdown_reasons == []
        assert after is before


def test_a_refused_start_puts_the_callers_handlers_back(monkeypatch):
    class Refused(Node):
        default_name = "refused"

        def setup(self) -> None:
            raise DataError("no such input")

    monkeypatch.setenv("TPSR_TRANSPORT", "inproc")
    before = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    with pytest.raises(SystemExit) as info:
        run_node(Refused, prog="refused", argv=[])
    assert info.value.code == 1
    assert (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)) == before
