"""The view node: relays the view topics to Foxglove over its WebSocket protocol.

    python -m tpsr_ros.view [--port P] [--ros-args -p port:=P -p host:=ADDRESS]

It subscribes raw (CDR bytes, ``raw=True``) to every topic of
:data:`~tpsr_ros.view.topics.VIEW_TOPICS` once a publisher of its type appears
(:mod:`~tpsr_ros.view.relays` picks the QoS), on whatever middleware the runtime chose,
and hands each message's bytes unchanged to a Foxglove WebSocket server
(:mod:`~tpsr_ros.view.server`), where the Foxglove app decodes them with the types'
``ros2msg`` schemas. No ROS installation is needed on either side. Once serving it
prints one line, its address ``ws://HOST:PORT``, to stdout.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from typing import Any

from tpsr_ros.cli import ArgumentParser
from tpsr_ros.core.errors import ConfigError
from tpsr_ros.io.qos import QoSProfile
from tpsr_ros.runtime import Node, NodeOptions, Subscription, param, run_node
from tpsr_ros.view.relays import plan_relays
from tpsr_ros.view.server import RelayServer, require_sdk
from tpsr_ros.view.topics import VIEW_TOPICS

__all__ = ["PROG", "ViewNode", "ViewParams", "main"]

PROG = "python -m tpsr_ros.view"
DISCOVERY_PERIOD_S = 0.5
"""Seconds between scans of the graph for publishers of the view topics."""
MAX_PORT = 65535


@dataclass(frozen=True)
class ViewParams:
    """Parameters of ``python -m tpsr_ros.view``."""

    port: int = param(
        8765,
        "TCP port of the Foxglove WebSocket server (0: any free port; the address is printed)",
        minimum=0,
        maximum=MAX_PORT,
    )
    host: str = param(
        "127.0.0.1", "address the server listens on (0.0.0.0: every interface of the machine)"
    )

    def __post_init__(self) -> None:
        if not 0 <= self.port <= MAX_PORT:
            raise ConfigError(f"port must be from 0 to {MAX_PORT}, got {self.port}")
        if not self.host.strip():
            raise ConfigError("host must not be empty (127.0.0.1: this machine only)")


def _port(text: str) -> int:
    """Read a TCP port, 0 to 65535 (an argparse type)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if not 0 <= value <= MAX_PORT:
        raise argparse.ArgumentTypeError(f"{value} is not a port from 0 to {MAX_PORT}")
    return value


class ViewNode(Node):
    """Relays the view topics' CDR bytes to a Foxglove WebSocket server."""

    default_name = "tpsr_view"
    Params = ViewParams
    description = (
        "Serve the TPSR view topics over the Foxglove WebSocket protocol "
        "(Foxglove: Open connection -> Foxglove WebSocket -> the printed ws:// address)."
    )

    @classmethod
    def argument_parser(cls, prog: str) -> ArgumentParser:
        """``--port P``, the same as ``--ros-args -p port:=P`` (and it wins over it)."""
        parser = ArgumentParser(prog=prog, description=cls.description, add_help=False)
        parser.add_argument(
            "--port",
            type=_port,
            default=None,
            metavar="P",
            help="TCP port (0: any free port); overrides the port parameter",
        )
        return parser

    @classmethod
    def preflight(cls, options: NodeOptions) -> None:
        """Refuse to start without foxglove-sdk, before joining the graph."""
        require_sdk()

    @property
    def port(self) -> int:
        """The port asked for: ``--port`` if given, else the ``port`` parameter."""
        args = self.options.args
        given = getattr(args, "port", None) if args is not None else None
        return int(self.params.port if given is None else given)

    def setup(self) -> None:
        """Start the server, advertise every view topic, then scan the graph for publishers."""
        self.topics = {self.resolve_topic(name): msgtype for name, msgtype in VIEW_TOPICS.items()}
        self.subscriptions: dict[str, Subscription] = {}
        self._qos: dict[str, QoSProfile] = {}
        self._warned: set[tuple[str, str]] = set()
        self.server = RelayServer(self.fully_qualified_name, self.params.host, self.port)
        try:
            self._relay = {t: self.server.channel(t, msgtype) for t, msgtype in self.topics.items()}
            relayed = ", ".join(f"{topic} ({t})" for topic, t in self.topics.items())
            self.logger.info(f"serving {self.server.url}; relaying {relayed}")
            # announced once spinning: a client may then stop the node with SIGINT at once
            self._announce = self.create_timer(0.001, self._print_address)
            self.discover()
            self.create_timer(DISCOVERY_PERIOD_S, self.discover)
        except BaseException:
            self.server.stop()  # the node never starts, so on_shutdown will not run
            raise

    def discover(self) -> None:
        """Subscribe to view topics whose publishers appeared (or need another QoS)."""
        relays, warnings = plan_relays(self.transport.publishers(), self.topics, self._qos)
        for key, message in warnings:
            if key not in self._warned:
                self._warned.add(key)
                self.logger.warning(message)
        for relay in relays:
            old = self.subscriptions.pop(relay.topic, None)
            if old is not None:
                old.destroy()
            self.subscriptions[relay.topic] = self.create_subscription(
                relay.topic, relay.msgtype, self._relay[relay.topic], relay.qos, raw=True
            )
            self._qos[relay.topic] = relay.qos
            again = "re" if old is not None else ""
            self.logger.info(f"{again}subscribed to {relay.topic} ({relay.msgtype}; {relay.qos})")

    def _print_address(self) -> None:
        """Print the address (the one line on stdout) from the first spin, signals handled."""
        self._announce.cancel()
        print(self.server.url, flush=True)

    def on_shutdown(self) -> None:
        """Stop the server (clients see the connection close)."""
        server: Any = getattr(self, "server", None)
        if server is not None:
            server.stop()


def main(argv: list[str] | None = None) -> None:
    """Entry point of ``python -m tpsr_ros.view`` (and ``ros2 run tpsr_ros view``)."""
    run_node(ViewNode, prog=PROG, argv=argv)

