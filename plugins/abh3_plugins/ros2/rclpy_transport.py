"""ROS 2 through rclpy, in a sourced ROS 2 install: any RMW, ROS tooling sees a real node.

Needs the ``abh3_can_interface`` package we ship (``plugins/abh3_plugins/ros2/interface``)
built with colcon and sourced. One node (``abh3_supervisor``) in a context of its own,
spun by a multi-threaded executor on its own threads; callbacks are reentrant so a
service call that waits for the drive never holds up the topics.
"""

from __future__ import annotations

import importlib
import logging
import threading
from collections.abc import Callable
from types import SimpleNamespace
from typing import Any

from abh3_plugins.ros2.settings import QosSettings, Settings
from abh3_plugins.ros2.transport import Publish, ServiceHandler
from abh3_supervisor.plugin_api import RESPONSE_INVALID

log = logging.getLogger(__name__)
NODE_NAME = "abh3_supervisor"
SERVICE_WAIT = 5.0  # [s] longer than any unit's timeout_ms answer
MESSAGES = {
    "abh3_can_interface.msg": (
        "Abh3Velocity",
        "Abh3Current",
        "Abh3Input",
        *(f"Abh3Brd{n}" for n in range(7)),
    ),
    "std_msgs.msg": ("Int32", "Header"),
    "builtin_interfaces.msg": ("Time",),
    "geometry_msgs.msg": (
        "Vector3",
        "Twist",
        "Point",
        "Quaternion",
        "Pose",
        "PoseWithCovariance",
        "TwistWithCovariance",
        "TwistStamped",
        "Transform",
        "TransformStamped",
    ),
    "nav_msgs.msg": ("Odometry",),
    "diagnostic_msgs.msg": ("DiagnosticArray", "DiagnosticStatus", "KeyValue"),
}
# in every ROS 2 install, but not always in a minimal one: without them the bridge has
# no /tf (tf2_msgs) or no joint_states and joint_commands (sensor_msgs), and says so
OPTIONAL = {"tf2_msgs.msg": ("TFMessage",), "sensor_msgs.msg": ("JointState",)}


class InterfaceMissing(RuntimeError):
    pass


def messages() -> SimpleNamespace:
    """The ROS message classes the bridge builds, by name; the service type as ``srv``."""
    found: dict[str, Any] = {}
    try:
        for module, names in MESSAGES.items():
            imported = importlib.import_module(module)
            found.update((name, getattr(imported, name)) for name in names)
        for module, names in OPTIONAL.items():
            try:
                imported = importlib.import_module(module)
            except ImportError:
                continue
            found.update((name, getattr(imported, name)) for name in names)
        found["srv"] = importlib.import_module("abh3_can_interface.srv").Abh3Input
        found["byte"] = lambda value: bytes([value])  # rclpy's `byte` fields take bytes
    except ImportError as exc:
        raise InterfaceMissing(
            f"{exc.name or exc} is not importable: build and source the abh3_can_interface "
            "package (`abh3 ros2 build-interface --prefix DIR`, or colcon), or set "
            "transport: dds"
        ) from None
    return SimpleNamespace(**found)


def interface_problem() -> str | None:
    """Why the message packages cannot be used through rclpy here, or None: each class is
    imported and its type support loaded, as creating a publisher will."""
    try:
        classes = messages()
    except InterfaceMissing as exc:
        return str(exc)
    for name, cls in vars(classes).items():
        load = getattr(cls, "__import_type_support__", None)
        if load is None:  # `byte`, or a stand-in
            continue
        try:
            load()
        except Exception as exc:  # ImportError, UnsupportedTypeSupport: libraries not found
            return (
                f"the type support of {name} does not load ({exc}): put the interface's "
                "lib/ on LD_LIBRARY_PATH (source its setup), or set transport: dds"
            )
    return None


class RclpyTransport:
    def __init__(self, settings: Settings) -> None:
        import rclpy
        from rclpy.callback_groups import ReentrantCallbackGroup
        from rclpy.executors import MultiThreadedExecutor

        self.msg = messages()
        self._rclpy = rclpy
        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=settings.domain_id)
        self.node = rclpy.create_node(NODE_NAME, context=self.context)
        self.group = ReentrantCallbackGroup()
        self.qos = self._qos(settings.qos)
        self.executor = MultiThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._thread = threading.Thread(target=self._spin, name="ros2-rclpy", daemon=True)

    def _qos(self, q: QosSettings) -> Any:
        from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

        return QoSProfile(
            history=HistoryPolicy.KEEP_LAST,
            depth=q.depth,
            reliability=ReliabilityPolicy.RELIABLE
            if q.reliability == "reliable"
            else ReliabilityPolicy.BEST_EFFORT,
            durability=DurabilityPolicy.TRANSIENT_LOCAL
            if q.durability == "transient_local"
            else DurabilityPolicy.VOLATILE,
        )

    def publisher(self, name: str, typ: type) -> Publish:
        return self.node.create_publisher(typ, name, self.qos).publish  # type: ignore[no-any-return]

    def subscribe(self, name: str, typ: type, handle: Callable[[Any], None]) -> None:
        def guarded(sample: Any) -> None:
            try:
                handle(sample)
            except Exception:  # a bad sample must not end the bridge
                log.exception("ros2: handling a sample on %s failed", name)

        self.node.create_subscription(typ, name, guarded, self.qos, callback_group=self.group)

    def serve(self, name: str, handle: ServiceHandler) -> None:
        def on_request(request: Any, response: Any) -> Any:
            try:  # reentrant group: waiting here holds up no other callback
                response.responce = handle(request.command).result(timeout=SERVICE_WAIT)
            except Exception:
                log.exception("ros2: %s: the command failed", name)
                response.responce = RESPONSE_INVALID
            return response

        self.node.create_service(self.msg.srv, name, on_request, callback_group=self.group)

    def start(self) -> None:
        self._thread.start()

    def _spin(self) -> None:
        try:
            self.executor.spin()
        except Exception:  # rclpy raises on shutdown from another thread in some releases
            log.debug("ros2: executor ended", exc_info=True)

    def close(self) -> None:
        self.executor.shutdown(timeout_sec=5)
        self.node.destroy_node()
        self.context.try_shutdown()
        self._thread.join(timeout=5)
