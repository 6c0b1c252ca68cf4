"""The DDS backend's large-message configuration and its host check."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.graph_support import LOOPBACK
from tpsr_ros.runtime import dds, dds_discovery
from tpsr_ros.runtime.dds_tuning import (
    SOCKET_RCVBUF_NEEDED,
    config_is_loopback,
    large_message_config,
    socket_buffer_problem,
)


@pytest.mark.parametrize(
    ("uri", "expected"),
    [
        (LOOPBACK, True),
        ("<CycloneDDS><Domain><General><Interfaces><NetworkInterface name='lo'/>"
         "</Interfaces></General></Domain></CycloneDDS>", True),
        ("<General><NetworkInterfaceAddress>127.0.0.1</NetworkInterfaceAddress></General>", True),
        ("<General><Interfaces><NetworkInterface address='192.168.1.5'/>"
         "<NetworkInterface address='127.0.0.1'/></Interfaces></General>", False),
        ("<CycloneDDS><Domain><Tracing/></Domain></CycloneDDS>", False),  # Cyclone picks
        ("file:///nonexistent/cyclonedds.xml", False),
    ],
)
def test_config_is_loopback_only_when_every_interface_is(uri: str, expected: bool) -> None:
    assert config_is_loopback(uri) is expected


def test_config_is_loopback_reads_file_uris(tmp_path: Path) -> None:
    config = tmp_path / "cyclonedds.xml"
    config.write_text(LOOPBACK)
    assert config_is_loopback(f"file://{config}")
    assert config_is_loopback(str(config))
    config.write_text(LOOPBACK.replace("127.0.0.1", "10.1.2.3"))
    assert not config_is_loopback(f"file://{config}")


def test_domain_config_puts_the_users_uri_after_our_tuning(monkeypatch) -> None:
    monkeypatch.setenv("CYCLONEDDS_URI", LOOPBACK)
    text = dds.domain_config()
    assert text.index("SocketReceiveBufferSize") < text.index("MaxMessageSize")
    assert text.index("MaxMessageSize") < text.index(LOOPBACK)  # the user's settings win
    monkeypatch.setenv("CYCLONEDDS_URI", LOOPBACK.replace("127.0.0.1", "10.1.2.3"))
    assert "MaxMessageSize" not in dds.domain_config()  # real network: Cyclone's datagrams
    monkeypatch.delenv("CYCLONEDDS_URI")
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    assert "MaxMessageSize" in dds.domain_config()
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "SUBNET")
    assert dds.domain_config().startswith(large_message_config(loopback=False))


def test_socket_buffer_problem_names_the_setting(tmp_path: Path) -> None:
    rmem = tmp_path / "rmem_max"
    rmem.write_text("212992\n")
    message = socket_buffer_problem(rmem)
    assert message is not None and "net.core.rmem_max is 212992" in message
    assert "sysctl -w net.core.rmem_max=" in message and "\n" not in message
    rmem.write_text(f"{SOCKET_RCVBUF_NEEDED}\n")
    assert socket_buffer_problem(rmem) is None
    assert socket_buffer_problem(tmp_path / "missing") is None


def test_the_node_warns_at_start_up_when_the_limit_is_low(monkeypatch, tmp_path, capfd) -> None:
    from tests.graph_support import fresh_domain
    from tpsr_ros.runtime import Node, NodeOptions

    rmem = tmp_path / "rmem_max"
    rmem.write_text("212992\n")
    monkeypatch.setattr(dds_discovery, "socket_buffer_problem", lambda: socket_buffer_problem(rmem))
    monkeypatch.setenv("CYCLONEDDS_URI", LOOPBACK)
    transport = dds.DdsTransport("tuning_probe", domain_id=fresh_domain(19))
    Node(NodeOptions(name="tuning_probe"), transport=transport).close()
    lines = [line for line in capfd.readouterr().err.splitlines() if "rmem_max" in line]
    assert len(lines) == 1 and lines[0].startswith("[WARN]")
    assert "net.core.rmem_max is 212992 bytes" in lines[0]
