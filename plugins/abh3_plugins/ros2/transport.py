"""What the bridge needs from ROS 2, and the choice between rclpy and plain DDS.

Both transports take fully qualified ROS names (``/ns/unit/vel_cmd``) and message classes
from their own ``msg`` namespace, built by keyword with the ROS field names, so the bridge
is written once. Handlers run on the transport's own thread, never inside the middleware's
callbacks; a handler's exception is logged and the transport carries on.
"""

from __future__ import annotations

import concurrent.futures
import importlib.util
import logging
import sys
from collections.abc import Callable
from typing import Any, Protocol

from abh3_plugins.ros2.settings import Settings

log = logging.getLogger(__name__)

Publish = Callable[[Any], None]
# a service handler gets the request's command string and answers through a future
ServiceHandler = Callable[[str], concurrent.futures.Future[str]]


class Transport(Protocol):
    @property
    def msg(self) -> Any:
        """The message classes by ROS name: msg.Abh3Velocity, msg.Twist, msg.Odometry…"""

    def publisher(self, name: str, typ: type) -> Publish: ...
    def subscribe(self, name: str, typ: type, handle: Callable[[Any], None]) -> None: ...
    def serve(self, name: str, handle: ServiceHandler) -> None: ...
    def start(self) -> None: ...
    def close(self) -> None: ...


def _importable(name: str) -> bool:
    if name in sys.modules:  # imported already (or stood in for)
        return True
    try:
        return importlib.util.find_spec(name) is not None
    except (ImportError, ValueError):
        return False


def rclpy_available() -> bool:
    return _importable("rclpy")


def cyclonedds_available() -> bool:
    return _importable("cyclonedds")


def decide(kind: str) -> tuple[str | None, str]:
    """The transport ``transport: kind`` will run with (``rclpy``/``dds``), and why; or None
    and what is missing. The same judgement :func:`open_transport` makes, so ``abh3 check``
    says what ``abh3 run`` will do."""
    no_dds = "needs the cyclonedds package: pip install 'abh3-supervisor[ros2]'"
    if kind == "dds":
        return ("dds", "transport: dds") if cyclonedds_available() else (None, no_dds)
    if not rclpy_available():
        if kind == "rclpy":
            return None, (
                "rclpy is not importable: source a ROS 2 install first, or use transport: dds"
            )
        if cyclonedds_available():
            return "dds", "rclpy is not importable (no sourced ROS 2), so plain DDS (cyclonedds)"
        return None, f"rclpy is not importable and the DDS transport {no_dds}"
    from abh3_plugins.ros2.rclpy_transport import interface_problem

    missing = interface_problem()
    if missing is None:
        return "rclpy", "rclpy and the built abh3_can_interface package are importable"
    if kind == "rclpy":
        return None, f"rclpy is importable but {missing}"
    if cyclonedds_available():
        return "dds", f"rclpy is importable but {missing}; so plain DDS (cyclonedds)"
    return None, f"rclpy is importable but {missing}; and the DDS transport {no_dds}"


def problem(kind: str) -> str | None:
    """Why ``transport: kind`` cannot work on this machine, or None."""
    chosen, why = decide(kind)
    return why if chosen is None else None


def open_transport(settings: Settings) -> Transport:
    """rclpy in a sourced ROS 2 install (``auto`` or ``rclpy``), else DDS via cyclonedds."""
    chosen, why = decide(settings.transport)
    if chosen == "rclpy":
        from abh3_plugins.ros2.rclpy_transport import RclpyTransport

        return RclpyTransport(settings)
    if chosen is None:
        raise RuntimeError(f"ros2: transport: {settings.transport}: {why}")
    if settings.transport == "auto" and rclpy_available():
        log.warning("ros2: %s", why)
    from abh3_plugins.ros2.dds import DdsTransport

    return DdsTransport(settings)
