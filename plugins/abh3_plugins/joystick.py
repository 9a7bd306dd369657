"""``joystick``: drive a robot from a Linux game controller, like the seed's testCMD.

Reads the kernel's joystick device API (``/dev/input/js0``: the axis and button numbers
the ROS ``joy`` node uses). As testCMD: travel = ``gainX`` × axis 4, turn = ``gainA`` ×
axis 0 (axes normalised to −1…1, up/left positive). On top of the seed:

* **deadman** (on by default): motion only while ``deadman_button`` is held; releasing it
  sends zero at once;
* **turbo**: ``turbo_button`` scales by ``turbo_scale`` instead of ``scale``;
* **hot-plug**: a vanished device means zero at once; it is reopened when it returns;
* the current command is re-sent every ``repeat_s`` while held, so the input stays fresh
  (a stick held still produces no events);
* a **robot** (``robot:``, or the robots of the ``units:`` named) is driven as a whole, and
  the twist stops at the fastest the robot may go (both parts scaled alike); without
  ``gainX``/``gainA`` a robot's ``limits`` (linear_mps, angular_radps) are full stick.
"""

from __future__ import annotations

import errno
import logging
import math
import os
import select
import struct
import threading
from dataclasses import dataclass, field
from typing import Any, Protocol

from abh3_plugins import teleop_target
from abh3_supervisor.plugin_api import (
    Config,
    Feed,
    InputFeed,
    InputSource,
    RobotConfig,
    Section,
    SupervisorView,
    hookimpl,
)
from abh3_supervisor.plugin_api import schema as js

log = logging.getLogger(__name__)
ABH3_API_VERSION = "1.0"  # the plugin API (abh3_supervisor.plugin_api) this is written for
JS_EVENT = struct.Struct("<IhBB")  # time ms, value, type, number (linux/joystick.h)
JS_BUTTON, JS_AXIS, JS_INIT = 0x01, 0x02, 0x80
AXIS_MAX = 32767.0


@dataclass(frozen=True, slots=True)
class JsEvent:
    kind: int  # JS_BUTTON or JS_AXIS (the init flag stripped)
    number: int
    value: int


class DeviceLost(Exception):
    """The device went away (unplugged, read error)."""


class JoystickDevice(Protocol):
    def read(self, timeout: float) -> list[JsEvent]: ...
    def close(self) -> None: ...


class LinuxJoystick:
    """The kernel joystick API; raises :class:`DeviceLost` when the device disappears."""

    def __init__(self, path: str) -> None:
        self.fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)

    def read(self, timeout: float) -> list[JsEvent]:
        ready, _, _ = select.select([self.fd], [], [], timeout)
        if not ready:
            return []
        try:
            data = os.read(self.fd, JS_EVENT.size * 64)
        except BlockingIOError:
            return []
        except OSError as exc:
            raise DeviceLost(str(exc)) from exc
        if not data:
            raise DeviceLost("end of file")
        events = []
        for offset in range(0, len(data) - len(data) % JS_EVENT.size, JS_EVENT.size):
            _, value, kind, number = JS_EVENT.unpack_from(data, offset)
            events.append(JsEvent(kind & ~JS_INIT, number, value))
        return events

    def close(self) -> None:
        os.close(self.fd)


@dataclass
class Mapping:
    """Axes and buttons → twist; the pure part, tested with synthetic events."""

    travel_axis: int = 4
    turn_axis: int = 0
    gain_x: float = 1.0
    gain_a: float = 1.0
    deadman_button: int | None = 4
    turbo_button: int | None = 5
    scale: float = 0.5
    turbo_scale: float = 1.0
    fastest: tuple[float, float] = (math.inf, math.inf)  # the robot's (linear, angular)
    axes: dict[int, float] = field(default_factory=dict)
    buttons: dict[int, bool] = field(default_factory=dict)

    def feed(self, event: JsEvent) -> None:
        if event.kind == JS_AXIS:
            self.axes[event.number] = -event.value / AXIS_MAX  # as the joy node: up/left > 0
        elif event.kind == JS_BUTTON:
            self.buttons[event.number] = bool(event.value)

    def reset(self) -> None:
        self.axes.clear()
        self.buttons.clear()

    @property
    def enabled(self) -> bool:
        return self.deadman_button is None or self.buttons.get(self.deadman_button, False)

    def twist(self) -> tuple[float, float] | None:
        """(linear.x, angular.z), or None while the deadman is released."""
        if not self.enabled:
            return None
        turbo = self.turbo_button is not None and self.buttons.get(self.turbo_button, False)
        k = self.turbo_scale if turbo else self.scale
        twist = (
            k * self.gain_x * self.axes.get(self.travel_axis, 0.0),
            k * self.gain_a * self.axes.get(self.turn_axis, 0.0),
        )
        return teleop_target.limit(twist, self.fastest)


class JoystickSource(InputSource):
    def __init__(
        self,
        units: tuple[str, ...],
        priority: int,
        timeout: float,
        mapping: Mapping,
        open_device: Any,
        repeat_s: float = 0.05,
        retry_s: float = 1.0,
    ) -> None:
        super().__init__("joystick", units, priority, timeout)
        self.mapping, self.open_device = mapping, open_device
        self.repeat_s, self.retry_s = repeat_s, retry_s
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self, feed: InputFeed) -> None:
        self._thread = threading.Thread(target=self.run, args=(feed,), daemon=True, name="joystick")
        self._thread.start()

    def run(self, feed: Feed) -> None:
        device: JoystickDevice | None = None
        missing_logged = False
        while not self._stop.is_set():
            if device is None:
                try:
                    device = self.open_device()
                    log.info("joystick: device open")
                    missing_logged = False
                except OSError as exc:
                    if not missing_logged:
                        log.warning(
                            "joystick: no device (%s); retrying every %.0f s",
                            os.strerror(exc.errno or errno.ENODEV),
                            self.retry_s,
                        )
                        missing_logged = True
                    self._stop.wait(self.retry_s)
                    continue
            try:
                self.step(device, feed)
            except DeviceLost as exc:
                log.warning("joystick: device lost (%s): zero", exc)
                feed.release()
                self.mapping.reset()
                device.close()
                device = None
        if device is not None:
            device.close()

    def step(self, device: JoystickDevice, feed: Feed) -> None:
        """Read what is there (up to ``repeat_s``) and send the current command."""
        was_enabled = self.mapping.enabled
        for event in device.read(self.repeat_s):
            self.mapping.feed(event)
        twist = self.mapping.twist()
        if twist is not None:
            feed.twist(*twist)
        elif was_enabled:
            feed.release()  # deadman let go: zero on the very next command frame

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2)


def _full_stick(robots: tuple[RobotConfig, ...], key: str) -> float:
    """The default gain: the robots' limit ``key`` where every one sets it, else the
    seed's 1.0."""
    limits = [getattr(r.limits, key) for r in robots]
    return min(limits) if limits and None not in limits else 1.0


class JoystickPlugin:
    def __init__(self) -> None:
        self.units: tuple[str, ...] = ()
        self.device = "/dev/input/js0"
        self.mapping = Mapping()
        self.priority, self.timeout = 10, 0.5

    @hookimpl
    def abh3_config_schema(self) -> dict[str, Any]:
        button = js.integer(0, 255)
        return js.mapping(
            {
                "robot": js.text("the robot the joystick drives (a robot's or a unit's name)"),
                "units": js.names("robots or units (each drives its whole robot)"),
                "device": js.text(default="/dev/input/js0"),
                "travel_axis": js.integer(0, 255, default=4),
                "turn_axis": js.integer(0, 255, default=0),
                "gainX": js.number(-100.0, 100.0, "m/s at full stick (or the robot's limit)", 1.0),
                "gainA": js.number(-100.0, 100.0, "rad/s at full stick (or the robot's)", 1.0),
                "deadman": js.boolean(default=True),
                "deadman_button": {**button, "default": 4},
                "turbo_button": {**button, "default": 5},
                "scale": js.number(0.0, 1.0, default=0.5),
                "turbo_scale": js.number(0.0, 1.0, default=1.0),
                "priority": js.integer(-100, 100, default=10),
                "timeout": js.number(0.05, 10.0, "s", 0.5),
            },
        ) | {"anyOf": [{"required": ["units"]}, {"required": ["robot"]}]}

    @hookimpl
    def abh3_configure(self, section: Section, config: Config) -> None:
        section.only(
            {
                *teleop_target.KEYS,
                "device",
                "travel_axis",
                "turn_axis",
                "gainX",
                "gainA",
                "deadman",
                "deadman_button",
                "turbo_button",
                "scale",
                "turbo_scale",
                "priority",
                "timeout",
            }
        )
        robots = teleop_target.robots(section, config, "joystick")
        self.units = teleop_target.units(robots)
        gain_x, gain_a = (_full_stick(robots, key) for key in ("linear_mps", "angular_radps"))
        self.device = section.text("device", self.device)
        deadman = section.boolean("deadman", True)
        self.mapping = Mapping(
            travel_axis=section.integer("travel_axis", 4, 0, 255),
            turn_axis=section.integer("turn_axis", 0, 0, 255),
            gain_x=section.number("gainX", gain_x, -100.0, 100.0),
            gain_a=section.number("gainA", gain_a, -100.0, 100.0),
            deadman_button=section.integer("deadman_button", 4, 0, 255) if deadman else None,
            turbo_button=section.integer("turbo_button", 5, 0, 255),
            scale=section.number("scale", 0.5, 0.0, 1.0),
            turbo_scale=section.number("turbo_scale", 1.0, 0.0, 1.0),
            fastest=teleop_target.fastest(robots, config),
        )
        self.priority = section.integer("priority", 10, -100, 100)
        self.timeout = section.number("timeout", 0.5, 0.05, 10.0)

    @hookimpl
    def abh3_input_sources(self, register: Any, supervisor: SupervisorView) -> None:
        device = self.device
        register(
            JoystickSource(
                self.units, self.priority, self.timeout, self.mapping, lambda: LinuxJoystick(device)
            )
        )
