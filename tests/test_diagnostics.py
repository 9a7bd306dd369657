"""``/diagnostics``: what each unit's and bus's status says, and how fast it says it.

On a fake clock (Timeline) with the simulated drives: the supervisor's events feed the
publisher as the plugin's hooks do (health and error/alarm changes publish at once), and
the periodic tick runs every 10 ms of fake time. No DDS here: the messages are the DDS
types the bridge publishes, collected in a list.
"""

from __future__ import annotations

import errno
import itertools
from typing import Any

import pytest

from abh3_plugins.ros2 import types
from abh3_plugins.ros2.diagnostics import DiagnosticsPublisher
from abh3_supervisor.config import parse_config
from abh3_supervisor.core.diagnostics import Health, Level, unit_status
from abh3_supervisor.core.supervisor import FlagChange
from abh3_supervisor.protocol import flags
from abh3_supervisor.scheduler import bus_health as bh
from abh3_supervisor.scheduler.core import HealthEvent
from tests.support.rig import TWO_UNITS, Rig

STEP = 0.01  # fake seconds between ticks


class Watch:
    """A rig whose /diagnostics go to a list, stamped with the fake time they went out."""

    def __init__(self, hz: float = 1.0) -> None:
        self.rig = Rig(parse_config(TWO_UNITS, "two.yaml"))
        self.sent: list[tuple[float, Any]] = []
        clock = self.rig.timeline.clock
        self.diag = DiagnosticsPublisher(
            Health(self.rig.sup),
            lambda m: self.sent.append((clock(), m)),
            types,
            hz,
            wall_ns=lambda: int(clock() * 1e9),
        )

        def hooks(event: object) -> None:  # what the plugin's abh3_health/abh3_flags do
            if isinstance(event, HealthEvent) or (
                isinstance(event, FlagChange) and event.word in ("error", "alarm")
            ):
                self.diag.changed(clock())

        self.rig.sup.subscribe(hooks)

    def run(self, seconds: float) -> None:
        end = self.rig.timeline.now + seconds
        while self.rig.timeline.now < end - 1e-9:
            self.rig.run(STEP)
            self.diag.tick(self.rig.timeline.now)

    def first(self, name: str, level: Level, since: float) -> tuple[float, Any] | None:
        for t, array in self.sent:
            if t < since:
                continue
            for status in array.status:
                if status.name.endswith(name) and status.level == level:
                    return t, status
        return None

    def latest(self, name: str) -> Any:
        statuses = [s for s in self.sent[-1][1].status if s.name.endswith(name)]
        assert len(statuses) == 1
        return statuses[0]


def values(status: Any) -> dict[str, str]:
    return {kv.key: kv.value for kv in status.values}


def test_all_ok_at_one_hertz_with_every_unit_and_bus() -> None:
    w = Watch()
    w.run(5.0)
    names = [s.name for s in w.sent[-1][1].status]
    assert names == [
        "abh3_supervisor: bus b",
        "abh3_supervisor: unit left",
        "abh3_supervisor: unit right",
        "abh3_supervisor: robot left",  # the robot decision: one status per robot
        "abh3_supervisor: robot right",
    ]
    robot = w.latest("robot left")  # nobody switched it on
    assert robot.level == Level.WARN and robot.message.startswith("not ready: left: SERVO A")
    assert [w.latest(n).level for n in ("bus b", "unit left", "unit right")] == [Level.OK] * 3
    periodic = [t for t, _ in w.sent if t >= 2.0]  # after the units came online
    assert all(0.99 <= b - a <= 1.01 for a, b in itertools.pairwise(periodic))
    left = values(w.latest("unit left"))
    assert float(left["command rate achieved [Hz]"]) == pytest.approx(50, rel=0.05)
    assert left["command rate requested [Hz]"] == "50"
    assert left["timeouts"] == "0"
    assert float(left["main supply [V]"]) > 0 and float(left["control supply [V]"]) > 0
    bus = values(w.latest("bus b"))
    assert bus["units online"] == "2/2"
    # the load measured between reports is the one planned for these rates
    assert float(bus["load [%]"]) == pytest.approx(float(bus["planned load [%]"]), rel=0.1)
    assert float(bus["frames/s"]) == pytest.approx(2 * (50 + 50) + 2 * (14 + 8), rel=0.1)
    stamp = w.sent[-1][1].header.stamp
    assert stamp.sec + stamp.nanosec / 1e9 == pytest.approx(w.sent[-1][0], abs=1e-6)


def test_an_error_bit_is_error_by_name_within_a_second() -> None:
    w = Watch()
    w.run(3.0)
    injected = w.rig.timeline.now
    w.rig.drive("left").inject_error(flags.FAULT.mask("A_OVERCURRENT"))
    w.run(2.0)
    seen = w.first("unit left", Level.ERROR, injected)
    assert seen is not None
    t, status = seen
    assert t - injected < 1.0
    assert "A_OVERCURRENT" in status.message
    assert values(status)["error bits"] == "A_OVERCURRENT"
    assert w.latest("unit right").level == Level.OK


def test_an_alarm_is_a_warning() -> None:
    w = Watch()
    w.run(3.0)
    w.rig.drive("right").inject_alarm(flags.FAULT.mask("CAN_COMM_ERROR"))
    w.run(2.0)
    right = w.latest("unit right")
    assert right.level == Level.WARN and "CAN_COMM_ERROR" in right.message


def test_a_unit_going_silent_is_stale_at_once_and_the_bus_says_so() -> None:
    w = Watch()
    w.run(3.0)
    silent_at = w.rig.timeline.now
    w.rig.drive("right").silent = True
    w.run(3.0)
    seen = w.first("unit right", Level.STALE, silent_at)
    assert seen is not None
    timeout = w.rig.config.units["right"].timeout_ms / 1000
    assert seen[0] - silent_at < timeout + 0.1  # offline, published when it happened
    assert "offline" in seen[1].message
    bus = w.latest("bus b")
    assert bus.level == Level.WARN and bus.message == "1 of 2 units answer"
    w.rig.drive("left").silent = True
    w.run(2.0)
    assert w.latest("bus b").level == Level.ERROR


def test_before_the_first_answer_a_unit_is_stale() -> None:
    w = Watch()
    w.diag.tick(0.0)
    assert w.latest("unit left").level == Level.STALE
    assert w.latest("unit left").message == "no answer yet"


def test_a_unit_that_cannot_keep_its_rate_is_a_warning() -> None:
    w = Watch()
    w.rig.drive("left").extra_delay = 0.05  # replies 50 ms late: 20 exchanges/s of 50
    w.run(4.0)
    left = w.latest("unit left")
    assert left.level == Level.WARN
    assert left.message.startswith("command rate") and left.message.endswith("of 50 Hz")


def test_diagnostics_off_publishes_only_changes() -> None:
    w = Watch(hz=0.0)
    w.run(3.0)
    count = len(w.sent)
    w.run(3.0)
    assert len(w.sent) == count  # nothing changed: nothing sent


def test_unit_status_reads_both_generations_flag_words() -> None:
    rig = Rig(parse_config(TWO_UNITS, "two.yaml"))
    rig.run(2.0)
    unit = rig.sup.units["right"]  # 2023
    unit.words["error"] = flags.FAULT.mask("MAIN_UNDERVOLTAGE")
    status = unit_status(unit, rig.scheduler, rig.timeline.now)
    assert status.level == Level.ERROR and "MAIN_UNDERVOLTAGE" in status.message
    assert dict(status.values)["protocol"] == "2023"


def test_the_message_bytes_match_rosbags_stock_diagnostic_msgs() -> None:
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    t = ts.types
    ours = types.DiagnosticArray(
        types.Header(types.Time(12, 345), ""),
        [
            types.DiagnosticStatus(
                2, "abh3_supervisor: unit left", "error", "abh3 b/1", [types.KeyValue("k", "v")]
            )
        ],
    )
    theirs = t["diagnostic_msgs/msg/DiagnosticArray"](
        t["std_msgs/msg/Header"](t["builtin_interfaces/msg/Time"](12, 345), ""),
        [
            t["diagnostic_msgs/msg/DiagnosticStatus"](
                2,
                "abh3_supervisor: unit left",
                "error",
                "abh3 b/1",
                [t["diagnostic_msgs/msg/KeyValue"]("k", "v")],
            )
        ],
    )
    assert ours.serialize() == bytes(
        ts.serialize_cdr(theirs, "diagnostic_msgs/msg/DiagnosticArray")
    )
    assert types.DiagnosticArray.__idl_typename__ == "diagnostic_msgs::msg::dds_::DiagnosticArray_"


def test_an_interface_in_trouble_is_the_bus_status() -> None:
    """What the interface reports (bus-off, error-passive) comes first: bus-off is ERROR
    even while the units have not yet timed out, error-passive a WARN."""
    w = Watch()
    w.run(2.0)
    health = w.rig.sup.bus_health["b"]
    health.on_send_error(errno.ENETDOWN, "Network is down", w.rig.timeline.now)
    w.run(1.1)
    bus = w.latest("bus b")
    assert bus.level == Level.ERROR and bus.message.startswith("bus-off")
    assert values(bus)["interface"] == "bus-off"
    passive = bytes([0, bh.CRTL_TX_PASSIVE, 0, 0, 0, 0, 140, 0])
    health.on_error_frame(bh.ERR_CRTL, passive, w.rig.timeline.now)
    w.run(1.1)
    assert w.latest("bus b").level == Level.WARN


def test_a_unit_held_by_verify_refuse_is_a_warning_that_says_why() -> None:
    """verify: refuse fails closed, and /diagnostics says so (not "online")."""
    from abh3_supervisor.config.model import VerifyMode
    from abh3_supervisor.core.verify import State, Verification

    w = Watch()
    w.run(1.0)
    left = w.rig.sup.units["left"]
    left.verify = Verification(State.NOT_VERIFIED, VerifyMode.REFUSE, reason="no answer")
    w.diag.changed(w.rig.timeline.now)
    w.run(1.5)
    status = w.latest("unit left")
    assert status.level == Level.WARN
    assert status.message.startswith("held at its idle word: its drive's CAN settings could not")
