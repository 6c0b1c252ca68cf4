"""A Foxglove WebSocket server that forwards CDR bytes, through foxglove-sdk.

Each topic becomes a channel with message encoding ``cdr`` and its full ``ros2msg``
schema (:func:`~tpsr_ros.io.messages.message_definition`), so Foxglove decodes the
bytes exactly as it decodes a rosbag2 MCAP file. The server has its own
``foxglove.Context``: nothing is logged to the SDK's global one. foxglove-sdk is an
optional dependency (the ``view`` extra), imported when a server starts.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from typing import Any

from tpsr_ros.core.errors import TpsrError
from tpsr_ros.io.messages import message_definition

__all__ = ["MISSING_SDK", "RelayServer", "require_sdk", "ws_url"]

MISSING_SDK = "foxglove-sdk is not installed: pip install 'tpsr-ros[view]'"


def require_sdk() -> Any:
    """Import and return ``foxglove``, or raise a TpsrError saying how to install it."""
    try:
        return importlib.import_module("foxglove")
    except ImportError:
        raise TpsrError(MISSING_SDK) from None


def ws_url(host: str, port: int) -> str:
    """``ws://HOST:PORT`` (an IPv6 address in brackets)."""
    shown = f"[{host}]" if ":" in host and not host.startswith("[") else host
    return f"ws://{shown}:{port}"


class RelayServer:
    """A started Foxglove WebSocket server and the channels it advertises."""

    def __init__(self, name: str, host: str, port: int) -> None:
        """Bind ``host:port`` (0: any free port) or raise a one-line TpsrError."""
        foxglove = require_sdk()
        self._foxglove = foxglove
        self._context = foxglove.Context()
        self._channels: list[Any] = []
        self.host = host
        try:
            self._server = foxglove.start_server(
                name=name, host=host, port=port, context=self._context
            )
        except (RuntimeError, ValueError, OverflowError) as exc:
            reason = str(exc).removeprefix("FoxgloveError: ")
            raise TpsrError(f"cannot serve on {ws_url(host, port)}: {reason}") from None
        self.port = int(self._server.port)

    @property
    def url(self) -> str:
        """The address clients connect to."""
        return ws_url(self.host, self.port)

    def channel(self, topic: str, msgtype: str) -> Callable[[bytes], None]:
        """Advertise ``topic`` as ``msgtype`` in CDR; the returned call relays one message."""
        schema = self._foxglove.Schema(
            name=msgtype, encoding="ros2msg", data=message_definition(msgtype).encode()
        )
        channel = self._foxglove.Channel(
            topic, schema=schema, message_encoding="cdr", context=self._context
        )
        self._channels.append(channel)
        log: Callable[[bytes], None] = channel.log
        return log

    def stop(self) -> None:
        """Close the channels and the server (clients are disconnected)."""
        for channel in self._channels:
            channel.close()
        self._channels.clear()
        self._server.stop()
