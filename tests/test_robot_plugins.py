"""The keyboard and joystick plugins drive a robot as a whole: ``robot:`` (or robot and
unit names in ``units:``), their source targets every drive of it, every drive gets its
speed in the same scheduler turn with the robot's signs, and their fastest twist is the
robot's."""

from __future__ import annotations

from typing import Any

import pytest

from abh3_plugins.joystick import JS_AXIS, JS_BUTTON, JoystickSource, JsEvent
from abh3_plugins.keyboard import KeyboardSource
from abh3_supervisor.config import parse_config
from abh3_supervisor.core.inputs import InputSource, Twist
from abh3_supervisor.core.twist_limits import fastest_twist
from abh3_supervisor.errors import ConfigError
from abh3_supervisor.plugin_host.host import PluginHost
from tests.support.rig import Rig
from tests.support.robots import SKID, TWO_DRIVES, first_moving, motor, sent

LIMITED = TWO_DRIVES.replace(
    "    track_m: 0.5\n", "    track_m: 0.5\n    limits: {linear_mps: 0.5, angular_radps: 1.0}\n"
)


def source_of(config: str, plugin: str, section: str) -> tuple[Rig, InputSource]:
    """The plugin's input source, as `abh3 run` registers it, on a fake-clock rig."""
    cfg = parse_config(f"{config}plugins:\n  {plugin}: {section}\n", "t.yaml")
    rig = Rig(cfg)
    host = PluginHost(cfg)
    found: list[InputSource] = []
    configured = host.pm.get_plugin(plugin)
    assert configured is not None
    configured.abh3_input_sources(register=found.append, supervisor=rig.sup)
    return rig, found[0]


@pytest.mark.parametrize(
    ("config", "section", "expect"),
    [
        (TWO_DRIVES, "{robot: rover}", lambda m: {"l": (m, 0.0), "r": (-m, 0.0)}),
        (TWO_DRIVES, "{units: [r]}", lambda m: {"l": (m, 0.0), "r": (-m, 0.0)}),
        (SKID, "{units: [skid]}", lambda m: {"front": (m, -m), "rear": (m, -m)}),
    ],
)
def test_the_keyboard_drives_the_whole_robot_in_one_turn(
    config: str, section: str, expect: Any
) -> None:
    rig, source = source_of(config, "keyboard", section)
    assert isinstance(source, KeyboardSource)
    robot = next(iter(rig.config.robots.values()))
    assert source.units == robot.units  # the robot's drives, every one
    for unit in robot.units:
        for text in ("SERVO ON ON", "START ON ON"):
            rig.sup.apply_text(unit, text)
    rig.sup.arbiter.add(source)
    seen = sent(rig.sup)
    twist = source.teleop.key("i")  # forward, at the default 0.2 m/s
    assert twist is not None and twist == pytest.approx((0.2, 0.0))
    rig.sup.arbiter.submit(source.name, Twist(*twist), rig.timeline.now)
    rig.run(0.1)
    first = first_moving(seen, robot.units)
    assert first is not None
    assert len({s.t for s in first.values()}) == 1  # one turn: the same instant of the schedule
    wheel = robot.wheels[0]
    for unit, pair in expect(motor(0.2, wheel.diameter_m, wheel.gear_ratio)).items():
        assert (first[unit].ay, first[unit].bx) == pytest.approx(pair, abs=0.2)


def test_the_keyboards_speeds_stop_at_the_robots_fastest() -> None:
    rig, source = source_of(LIMITED, "keyboard", "{robot: rover, speed: 2.0}")
    assert isinstance(source, KeyboardSource)
    robot = rig.config.robots["rover"]
    assert fastest_twist(robot, rig.config.units) == pytest.approx((0.5, 1.0))
    assert source.teleop.key("i") == pytest.approx((0.5, 0.0))  # 2.0 asked: the robot's 0.5
    for _ in range(20):
        source.teleop.key("q")  # all speeds ×1.1, twenty times
    assert source.teleop.key("u") == pytest.approx((0.5, 1.0))


def test_the_joystick_full_stick_is_the_robots_limits_and_never_more() -> None:
    _, source = source_of(LIMITED, "joystick", "{robot: rover}")
    assert isinstance(source, JoystickSource)
    assert source.units == ("l", "r")
    m = source.mapping
    assert (m.gain_x, m.gain_a) == (0.5, 1.0)  # the robot's limits: full stick
    for event in (JsEvent(JS_BUTTON, 4, 1), JsEvent(JS_BUTTON, 5, 1), JsEvent(JS_AXIS, 4, -32767)):
        m.feed(event)
    assert m.twist() == pytest.approx((0.5, 0.0))
    # gains beyond the robot: the twist scaled back whole, so the stick's curve is kept
    _, source = source_of(LIMITED, "joystick", "{robot: rover, gainX: 2.0, gainA: 2.0}")
    assert isinstance(source, JoystickSource)
    m = source.mapping
    for event in (JsEvent(JS_BUTTON, 4, 1), JsEvent(JS_BUTTON, 5, 1)):
        m.feed(event)
    m.feed(JsEvent(JS_AXIS, 4, -32767))
    m.feed(JsEvent(JS_AXIS, 0, -16384))  # half left: asks 2.0 m/s and 1.0 rad/s
    linear, angular = m.twist() or (0.0, 0.0)
    assert linear == pytest.approx(0.5) and angular == pytest.approx(0.25, abs=1e-3)


@pytest.mark.parametrize("plugin", ["keyboard", "joystick"])
def test_a_robot_they_do_not_know_is_a_config_error_with_a_hint(plugin: str) -> None:
    for section, said in (
        (
            "{robot: rovr}",
            "plugins.{p}.robot: no robot or unit named 'rovr' (robots: rover; units: l, r); did you mean 'rover'?",
        ),
        (
            "{speed: 0.2}" if plugin == "keyboard" else "{scale: 0.5}",
            "plugins.{p}.units: missing: name the robot",
        ),
    ):
        cfg = parse_config(f"{TWO_DRIVES}plugins:\n  {plugin}: {section}\n", "t.yaml")
        with pytest.raises(ConfigError) as info:
            PluginHost(cfg)
        assert len(info.value.problems) == 1 and said.format(p=plugin) in info.value.problems[0]
