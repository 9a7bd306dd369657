"""The ROS 2 bridge in one process, on an in-memory transport: validation, names, gating.

The same tests run the rclpy transport against a stand-in for rclpy (this machine has no
ROS install): it checks our use of rclpy's API as documented, not rclpy itself.
"""

from __future__ import annotations

import concurrent.futures
import math
import sys
import types as pytypes
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import pytest

pytest.importorskip("cyclonedds")
from abh3_plugins.ros2 import types
from abh3_plugins.ros2.bridge import Ros2Plugin, UnitBridge
from abh3_plugins.ros2.settings import Settings
from abh3_plugins.ros2.transport import open_transport
from abh3_supervisor.config import parse_config
from abh3_supervisor.core.state import Feedback, UnitState
from abh3_supervisor.errors import ConfigError
from abh3_supervisor.plugin_api import UnitView
from abh3_supervisor.plugin_host.host import PluginHost
from abh3_supervisor.protocol import frames
from tests.support.ros2_memory import MemoryTransport

UNITS = """
buses: {b: {interface: virtual, channel: u, simulate: true}}
units:
  - {name: left, broadcast: {mask: 0x13}, geometry: {pulses_per_rev: 1000}}
  - {name: eye, abh3_id: 3, role: monitor}
"""


@dataclass
class RecordingFeed:
    calls: list[tuple[Any, ...]] = field(default_factory=list)

    def __getattr__(self, method: str) -> Callable[..., Any]:
        def record(*args: Any) -> Any:
            self.calls.append((method, *args))
            done: concurrent.futures.Future[str] = concurrent.futures.Future()
            done.set_result("")
            return done

        return record


def bridge(settings: Settings, unit: str = "left", t: Any = None) -> tuple[UnitBridge, Any, Any]:
    cfg = parse_config(UNITS, "u.yaml")
    t = t or MemoryTransport()
    b = UnitBridge(UnitView(UnitState.initial(cfg.units[unit])), t, settings)
    feed = RecordingFeed()
    b.start(feed)  # type: ignore[arg-type]
    return b, t, feed


def test_commands_only_with_allow_commands_and_never_for_a_monitor() -> None:
    _, t, _ = bridge(Settings())
    assert "/left/vel_cmd" not in t.handlers and not t.services
    assert "/left/brd_num" in t.handlers and "/left/xa" in t.handlers  # read-only parts
    _, t, _ = bridge(Settings(allow_commands=True), "eye")
    assert "/eye/vel_cmd" not in t.handlers
    _, t, _ = bridge(Settings(allow_commands=True))
    assert {"/left/vel_cmd", "/left/cur_cmd", "/left/cmd_vel", "/left/inp_data"} <= set(t.handlers)
    assert sorted(t.services) == ["/left/enable", "/left/inp_service"]  # its robot's too


@pytest.mark.parametrize(
    ("topic", "sample"),
    [
        ("vel_cmd", types.Abh3Velocity(math.nan, 0.0)),
        ("vel_cmd", types.Abh3Velocity(0.0, math.inf)),
        ("inp_data", types.Abh3Input(1 << 9, 1 << 9)),  # bit 9 is not defined in 2021
        ("cmd_vel", types.Twist(types.Vector3(math.nan), types.Vector3())),
        ("cmd_vel", types.Twist(types.Vector3(), types.Vector3(y=math.inf))),
    ],
)
def test_bad_values_never_reach_the_feed(
    topic: str, sample: Any, caplog: pytest.LogCaptureFixture
) -> None:
    _, t, feed = bridge(Settings(allow_commands=True))
    t.handlers[f"/left/{topic}"](sample)
    t.handlers[f"/left/{topic}"](sample)
    assert feed.calls == []
    assert len([r for r in caplog.records if "refused" in r.message]) == 1  # rate-limited


@pytest.mark.parametrize(
    ("topic", "sample", "call"),
    [
        ("vel_cmd", types.Abh3Velocity(6553.6, 0.0), ("velocity", 6553.6, 0.0)),
        ("cur_cmd", types.Abh3Current(-400.0, 0.0), ("current", -400.0, 0.0)),
        ("cmd_vel", types.Twist(types.Vector3(100.0), types.Vector3()), ("twist", 100.0, 0.0)),
    ],
)
def test_a_finite_value_beyond_the_range_is_handed_on_for_the_supervisor_to_clamp(
    topic: str, sample: Any, call: tuple[str, float, float]
) -> None:
    """One rule at every entry (docs/safety.md): beyond the limits or the wire's range a
    value is clamped by the supervisor, both axes alike, as the socket's and the command
    language's are — never refused here and carried out there."""
    _, t, feed = bridge(Settings(allow_commands=True))
    t.handlers[f"/left/{topic}"](sample)
    assert feed.calls == [call]


def test_good_values_reach_the_feed_as_the_seed_means_them() -> None:
    _, t, feed = bridge(Settings(allow_commands=True))
    t.handlers["/left/vel_cmd"](types.Abh3Velocity(300.0, -20.0))
    t.handlers["/left/vel_cmd"](types.Abh3Velocity(-6553.6, 6553.4))  # the whole int16 range
    t.handlers["/left/cur_cmd"](types.Abh3Current(12.5, 0.0))
    t.handlers["/left/cmd_vel"](types.Twist(types.Vector3(0.2), types.Vector3(z=0.5)))
    t.handlers["/left/inp_data"](types.Abh3Input(-1, 0x3))  # int32 on the wire
    assert feed.calls == [
        ("velocity", 300.0, -20.0),
        ("velocity", -6553.6, 6553.4),
        ("current", 12.5, 0.0),
        ("twist", 0.2, 0.5),
        ("inputs", -1, 0x3),
    ]


def test_inp_service_runs_the_command_language_and_refuses_junk() -> None:
    _, t, feed = bridge(Settings(allow_commands=True))
    service = t.services["/left/inp_service"]
    assert service("SERVO ON ON").result() == ""
    assert service("X" * 1000).result() == "Invalid Command."  # never parsed
    assert feed.calls == [("command", "SERVO ON ON")]


def test_brd_num_in_the_mask_only_and_status_request_publishes_only_answers() -> None:
    b, t, feed = bridge(Settings(status="request"))
    t.handlers["/left/brd_num"](types.Int32(2))  # outside 0x13: ignored, as the seed
    t.handlers["/left/brd_num"](types.Int32(7))
    assert feed.calls == []
    brd0 = frames.Brd0(error=0x400000, alarm=0x80000000)
    b.status(0, brd0)  # polled, not asked: not published with status: request
    assert t.published["/left/brd0_data"] == []
    t.handlers["/left/brd_num"](types.Int32(0))
    assert feed.calls == [("request_status", 0)]
    b.status(0, brd0)
    assert t.published["/left/brd0_data"] == [types.Abh3Brd0(0x400000, -(2**31))]  # int32
    assert "/left/brd2_data" not in t.published  # only the mask's publishers


def test_status_poll_publishes_everything_and_odometry_follows_the_pulses() -> None:
    b, t, _ = bridge(Settings(odom_frame="map", base_frame="robot"))
    b.status(4, frames.Brd4(0, 0), 0.0)
    b.feedback(Feedback(0.001, 0.0, 0.0, 0.0, 0.0))  # odom comes with the DP0 replies
    b.status(4, frames.Brd4(1000, 1000), 0.02)  # one motor revolution forward
    assert [m.pulse_a for m in t.published["/left/brd4_data"]] == [0, 1000]
    assert len(t.published["/left/odom"]) == 1
    b.feedback(Feedback(0.021, 0.0, 0.0, 0.0, 0.0))  # standing: the counts' pose exactly
    odom = t.published["/left/odom"][-1]
    assert odom.pose.pose.position.x == pytest.approx(1 / 10 * 0.1 * math.pi)  # r · wheel · π
    assert (odom.header.frame_id, odom.child_frame_id) == ("map", "robot")
    assert odom.pose.pose.orientation.w == 1.0


def test_names_follow_the_namespace_and_remapping() -> None:
    s = Settings(
        namespace="/robot/{unit}", remap={"cmd_vel": "/cmd_vel", "left/odom": "wheel_odom"}
    )
    assert s.name("left", "vel_cmd") == "/robot/left/vel_cmd"
    assert s.name("left", "cmd_vel") == "/cmd_vel"
    assert s.name("left", "odom") == "/robot/left/wheel_odom"
    assert s.name("right", "odom") == "/robot/right/odom"
    assert Settings(namespace="/").name("only", "vel_cmd") == "/vel_cmd"  # the seed's names


def problems(ros2: str, units: str = UNITS) -> str:
    with pytest.raises(ConfigError) as err:
        PluginHost(parse_config(units + "plugins:\n  ros2:\n" + ros2, "r.yaml"))
    return str(err.value)


def test_bad_settings_are_reported_with_file_line_and_key() -> None:
    message = problems(
        "    namespace: robot\n    qos: {reliability: sometimes}\n"
        "    remap: {vel_cmdd: x, odom: 'bad name'}\n"
    )
    assert "r.yaml:8: plugins.ros2.namespace: 'robot' (unit left) is not an absolute" in message
    assert "plugins.ros2.qos.reliability: 'sometimes' is not one of" in message
    assert "remap.vel_cmdd: not a name of the bridge; did you mean 'vel_cmd'?" in message
    assert "plugins.ros2.remap.odom: 'bad name' is not a ROS name" in message


def test_two_units_may_share_an_input_but_never_an_output() -> None:
    assert "units left and eye would both publish /vel_fbk_ab" in problems("    namespace: /\n")
    assert "would both publish /fbk" in problems("    remap: {vel_fbk_ab: /fbk}\n")
    ok = parse_config(UNITS + "plugins:\n  ros2: {remap: {cmd_vel: /cmd_vel}}\n", "r.yaml")
    PluginHost(ok)  # one /cmd_vel for both drives of a robot is fine
    assert "'/left-x' (unit left) is not an absolute ROS name" in problems(
        "    namespace: /{unit}-x\n"
    )


def test_a_plugin_that_could_not_start_ignores_events() -> None:
    plugin = Ros2Plugin()  # abh3_start failed (logged by the host): later hooks are no-ops
    plugin.abh3_status("left", 0, frames.Brd0(0, 0))
    plugin.abh3_stop()


# ---------------------------------------------------------------- rclpy, stood in for


class FakeNode:
    def __init__(self) -> None:
        self.publishers: dict[str, list[Any]] = {}
        self.subscriptions: dict[str, Callable[[Any], None]] = {}
        self.services: dict[str, tuple[Any, Callable[[Any, Any], Any]]] = {}
        self.destroyed = False

    def create_publisher(self, typ: type, name: str, qos: Any) -> Any:
        sent = self.publishers.setdefault(name, [])
        return pytypes.SimpleNamespace(publish=sent.append)

    def create_subscription(
        self, typ: type, name: str, callback: Callable[[Any], None], qos: Any, **kw: Any
    ) -> None:
        assert "callback_group" in kw
        self.subscriptions[name] = callback

    def create_service(self, srv: Any, name: str, callback: Any, **kw: Any) -> None:
        self.services[name] = (srv, callback)

    def destroy_node(self) -> None:
        self.destroyed = True


@pytest.fixture
def fake_rclpy(monkeypatch: pytest.MonkeyPatch) -> Iterator[FakeNode]:
    node = FakeNode()
    rclpy = pytypes.ModuleType("rclpy")
    shut: list[bool] = []
    rclpy.Context = lambda: pytypes.SimpleNamespace(try_shutdown=lambda: shut.append(True))  # type: ignore[attr-defined]
    rclpy.init = lambda context, domain_id: None  # type: ignore[attr-defined]
    rclpy.create_node = lambda name, context: node  # type: ignore[attr-defined]
    groups = pytypes.ModuleType("rclpy.callback_groups")
    groups.ReentrantCallbackGroup = object  # type: ignore[attr-defined]
    executors = pytypes.ModuleType("rclpy.executors")

    class Executor:
        def __init__(self, context: Any) -> None:
            self.nodes: list[Any] = []

        def add_node(self, n: Any) -> None:
            self.nodes.append(n)

        def spin(self) -> None:
            pass

        def shutdown(self, timeout_sec: float) -> None:
            pass

    executors.MultiThreadedExecutor = Executor  # type: ignore[attr-defined]
    qos = pytypes.ModuleType("rclpy.qos")
    for policy in ("DurabilityPolicy", "HistoryPolicy", "ReliabilityPolicy"):
        setattr(
            qos,
            policy,
            pytypes.SimpleNamespace(
                KEEP_LAST=1, RELIABLE=1, BEST_EFFORT=2, VOLATILE=2, TRANSIENT_LOCAL=1
            ),
        )
    qos.QoSProfile = lambda **kw: kw  # type: ignore[attr-defined]
    modules: dict[str, Any] = {
        "rclpy": rclpy,
        "rclpy.callback_groups": groups,
        "rclpy.executors": executors,
        "rclpy.qos": qos,
    }

    @dataclass
    class Request:
        command: str = ""

    @dataclass
    class Response:
        responce: str = ""

    srv = pytypes.ModuleType("abh3_can_interface.srv")
    srv.Abh3Input = pytypes.SimpleNamespace(Request=Request, Response=Response)  # type: ignore[attr-defined]
    modules["abh3_can_interface.srv"] = srv
    for package in (
        "abh3_can_interface",
        "std_msgs",
        "builtin_interfaces",
        "geometry_msgs",
        "nav_msgs",
        "diagnostic_msgs",
    ):
        modules[f"{package}.msg"] = types  # our DDS classes take the same keywords
    for name, module in modules.items():
        monkeypatch.setitem(sys.modules, name, module)
    yield node
    assert node.destroyed and shut


def test_rclpy_transport_carries_the_same_bridge(fake_rclpy: FakeNode) -> None:
    settings = Settings(transport="rclpy", allow_commands=True)
    t = open_transport(settings)
    assert type(t).__name__ == "RclpyTransport"
    b, _, feed = bridge(settings, t=t)
    t.start()
    fake_rclpy.subscriptions["/left/vel_cmd"](types.Abh3Velocity(100.0, 0.0))
    fake_rclpy.subscriptions["/left/vel_cmd"](types.Abh3Velocity(math.nan, 0.0))
    srv, call = fake_rclpy.services["/left/inp_service"]
    reply = call(srv.Request("START ON ON"), srv.Response())
    assert reply.responce == ""
    assert feed.calls == [("velocity", 100.0, 0.0), ("command", "START ON ON")]
    b.status(1, frames.Brd1(io=0xC3, control=0x08070070))
    assert fake_rclpy.publishers["/left/brd1_data"] == [types.Abh3Brd1(0x08070070, 0xC3)]
    t.close()
