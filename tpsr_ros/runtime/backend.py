"""Choosing the transport: ``TPSR_TRANSPORT=rclpy|dds|inproc``, else the first that works.

The default is rclpy when it can be imported (a sourced ROS 2 Jazzy), otherwise Cyclone DDS
from PyPI; the in-process bus is used only when asked for, since a node on it can talk only
to nodes in the same Python process.
"""

from __future__ import annotations

import importlib
import os
from collections.abc import Sequence

from tpsr_ros.core.errors import ConfigError, TpsrError
from tpsr_ros.runtime.transport import Transport

__all__ = ["BACKENDS", "TRANSPORT_ENV", "choose_backend", "open_transport"]

TRANSPORT_ENV = "TPSR_TRANSPORT"
BACKENDS = ("rclpy", "dds", "inproc")


def _importable(module: str) -> str | None:
    """None if ``module`` imports, else a short reason."""
    try:
        importlib.import_module(module)
    except Exception as exc:
        return f"{type(exc).__name__}: {exc}".splitlines()[0]
    return None


def choose_backend(requested: str | None = None) -> tuple[str, str | None]:
    """``(backend, note)``: the backend to use and, when a fallback was taken, why."""
    requested = (requested or os.environ.get(TRANSPORT_ENV, "")).strip().lower()
    if requested:
        if requested not in BACKENDS:
            raise ConfigError(
                f"{TRANSPORT_ENV}={requested!r} is not one of {', '.join(BACKENDS)}"
            )
        return requested, None
    rclpy_problem = _importable("rclpy")
    if rclpy_problem is None:
        return "rclpy", None
    dds_problem = _importable("cyclonedds")
    if dds_problem is None:
        return "dds", f"rclpy is not importable ({rclpy_problem}); using Cyclone DDS"
    raise TpsrError(
        "no middleware: source ROS 2 Jazzy (for rclpy) or pip install 'tpsr-ros[dds]' "
        f"(Cyclone DDS), or set {TRANSPORT_ENV}=inproc for a single-process run"
    )


def open_transport(
    backend: str,
    node_name: str,
    namespace: str,
    *,
    enclave: str = "/",
    ros_args: Sequence[str] = (),
    use_sim_time: bool = False,
) -> Transport:
    """Create the transport of one node; ``ros_args`` (the ``--ros-args`` tokens) reach rcl
    and ``use_sim_time`` rclpy's own parameter on the rclpy backend."""
    fqn = namespace.rstrip("/") + "/" + node_name
    if backend == "inproc":
        from tpsr_ros.runtime.inproc import InprocTransport

        return InprocTransport(fqn)
    if backend == "dds":
        from tpsr_ros.runtime.dds import DdsTransport

        return DdsTransport(node_name, namespace, enclave=enclave)
    if backend == "rclpy":
        from tpsr_ros.runtime.rclpy_backend import RclpyTransport

        return RclpyTransport(
            node_name, namespace, ros_args=ros_args, use_sim_time=use_sim_time
        )
    raise ConfigError(f"unknown transport {backend!r}; choose one of {', '.join(BACKENDS)}")
