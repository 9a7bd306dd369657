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


def rclpy_available() -> bool:
    return importlib.util.find_spec("rclpy") is not None


def cyclonedds_available() -> bool:
    return importlib.util.find_spec("cyclonedds") is not None


def problem(kind: str) -> str | None:
    """Why ``transport: kind`` cannot work on this machine, or None."""
    if kind == "rclpy" and not rclpy_available():
        return "rclpy is not importable: source a ROS 2 install first, or use transport: dds"
    if (kind == "dds" or (kind == "auto" and not rclpy_available())) and not cyclonedds_available():
        return "needs the cyclonedds package: pip install 'abh3-supervisor[ros2]'"
    return None


def open_transport(settings: Settings) -> Transport:
    """rclpy in a sourced ROS 2 install (``auto`` or ``rclpy``), else DDS via cyclonedds."""
    if settings.transport == "rclpy" or (settings.transport == "auto" and rclpy_available()):
        from abh3_plugins.ros2.rclpy_transport import InterfaceMissing, RclpyTransport

        try:
            return RclpyTransport(settings)
        except InterfaceMissing as exc:
            if settings.transport == "rclpy" or not cyclonedds_available():
                raise
            log.warning("ros2: rclpy found but %s; speaking DDS directly instead", exc)
    from abh3_plugins.ros2.dds import DdsTransport

    return DdsTransport(settings)
