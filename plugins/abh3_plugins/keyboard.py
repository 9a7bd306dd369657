"""``keyboard``: headless teleop from the terminal, like ROS teleop_twist_keyboard.

    u i o      i/,: forward/back   j/l: turn left/right   u o m .: arcs
    j k l      k or space: stop    q/z: all speeds ×1.1/×0.9
    m , .      w/x: linear ×1.1/×0.9   e/c: angular ×1.1/×0.9
    ctrl+e: EMERGENCY STOP (every unit; latched until cleared from a client)

Each key press sends a twist to the configured robot (``robot:``, or the robots of the
``units:`` named: each as a whole, all its drives together); hold a key (the terminal
repeats it) to keep moving: silence longer than ``timeout`` means zero. The speeds stop
at the fastest the robot may go (its ``limits``, its drives' velocity limits). The terminal is
put in cbreak mode (no echo, Ctrl-C still stops the program) and restored on the way out.

Inside the TUI the terminal is the TUI's (see :mod:`abh3_supervisor.plugin_host.terminal`): this
plugin never reads it then, the TUI hands it the keys. The TUI's own keys win; a teleop
key the TUI uses moves to its alternative (``q`` → ``Q``, ``e`` → ``C``).
"""

from __future__ import annotations

import logging
import math
import os
import select
import sys
import termios
import threading
import tty
from collections.abc import Collection
from typing import Any

from abh3_plugins import teleop_target
from abh3_supervisor.plugin_api import (
    Config,
    InputFeed,
    InputSource,
    Section,
    SupervisorView,
    hookimpl,
    terminal,
)
from abh3_supervisor.plugin_api import schema as js

log = logging.getLogger(__name__)
ABH3_API_VERSION = "1.0"  # the plugin API (abh3_supervisor.plugin_api) this is written for
MOVES = {
    "i": (1, 0),
    "o": (1, -1),
    "j": (0, 1),
    "l": (0, -1),
    "u": (1, 1),
    ",": (-1, 0),
    ".": (-1, 1),
    "m": (-1, -1),
    "k": (0, 0),
    " ": (0, 0),
}
SPEEDS = {
    "q": (1.1, 1.1),
    "z": (0.9, 0.9),
    "w": (1.1, 1.0),
    "x": (0.9, 1.0),
    "e": (1.0, 1.1),
    "c": (1.0, 0.9),
}
# ctrl+e in cbreak mode, as the TUI's e-stop (inside the TUI, the TUI's own binding has it)
ESTOP_KEY = "\x05"
# where a teleop key goes when the terminal's owner uses the key itself
ALTERNATIVES = {"q": "Q", "e": "C"}
MEANING = {
    "i": "forward",
    "o": "forward, turning right",
    "j": "turn left",
    "l": "turn right",
    "u": "forward, turning left",
    ",": "back",
    ".": "back, turning left",
    "m": "back, turning right",
    "k": "stop",
    " ": "stop",
    "q": "all speeds ×1.1",
    "z": "all speeds ×0.9",
    "w": "linear speed ×1.1",
    "x": "linear speed ×0.9",
    "e": "angular speed ×1.1",
    "c": "angular speed ×0.9",
}


class Teleop:
    """Key → twist, the pure part (no terminal). ``fastest``: the speeds never pass it
    (linear m/s, angular rad/s: the robot's, teleop_target.fastest)."""

    def __init__(
        self, speed: float, turn: float, fastest: tuple[float, float] = (math.inf, math.inf)
    ) -> None:
        self.fastest = fastest
        self.speed, self.turn = min(speed, fastest[0]), min(turn, fastest[1])

    def key(self, ch: str) -> tuple[float, float] | None:
        if ch in SPEEDS:
            fs, ft = SPEEDS[ch]
            self.speed = min(self.speed * fs, self.fastest[0])
            self.turn = min(self.turn * ft, self.fastest[1])
            log.info("keyboard: speed %.2f m/s, turn %.2f rad/s", self.speed, self.turn)
            return None
        if ch in MOVES:
            x, th = MOVES[ch]
            return x * self.speed, th * self.turn
        return None


class KeyboardSource(InputSource):
    def __init__(
        self,
        units: tuple[str, ...],
        priority: int,
        timeout: float,
        teleop: Teleop,
        stream: Any = None,
    ) -> None:
        super().__init__("keyboard", units, priority, timeout)
        self.teleop = teleop
        self.stream = stream if stream is not None else sys.stdin
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._saved: Any = None
        self._feed: InputFeed | None = None
        self._keys: dict[str, str] = {}  # typed key → teleop key, under a terminal owner

    def start(self, feed: InputFeed) -> None:
        owner = terminal.owner()
        if owner is not None:  # one reader per terminal: the owner hands keys over
            self._feed = feed
            log.info("keyboard: the terminal is %s's; it passes the teleop keys on", owner)
            return
        try:  # pytest's captured stdin, a pipe wrapper: no descriptor, no terminal
            fd = self.stream.fileno()
        except (OSError, ValueError):
            fd = -1
        if fd < 0 or not os.isatty(fd):
            log.warning("keyboard: standard input is not a terminal; teleop is off")
            return
        self._saved = termios.tcgetattr(fd)
        tty.setcbreak(fd)  # keys one by one, no echo; Ctrl-C still raises SIGINT
        self._thread = threading.Thread(
            target=self._run, args=(feed, fd), daemon=True, name="keyboard"
        )
        self._thread.start()
        print(__doc__.split("\n\n")[1], file=sys.stderr)

    def _run(self, feed: InputFeed, fd: int) -> None:
        while not self._stop.is_set():
            ready, _, _ = select.select([fd], [], [], 0.1)
            if not ready:
                continue
            ch = os.read(fd, 1).decode(errors="ignore")
            if ch == ESTOP_KEY:
                feed.emergency_stop()
                continue
            twist = self.teleop.key(ch)
            if twist is not None:
                feed.twist(*twist)

    def key_map(self, taken: Collection[str]) -> dict[str, str]:
        """Teleop keys the owner does not use, each under its alternative if it does."""
        self._keys = {}
        for key in MEANING:
            typed = key if key not in taken else ALTERNATIVES.get(key)
            if typed is not None and typed not in taken:
                self._keys[typed] = key
        return {typed: MEANING[key] for typed, key in self._keys.items()}

    def press(self, key: str) -> None:
        feed, teleop_key = self._feed, self._keys.get(key)
        if feed is None or teleop_key is None:
            return
        twist = self.teleop.key(teleop_key)
        if twist is not None:
            feed.twist(*twist)

    def stop(self) -> None:
        self._feed = None
        self._stop.set()
        if self._thread is not None:
            self._thread.join(1)
        if self._saved is not None:
            termios.tcsetattr(self.stream.fileno(), termios.TCSADRAIN, self._saved)
            self._saved = None


class KeyboardPlugin:
    def __init__(self) -> None:
        self.units: tuple[str, ...] = ()
        self.settings: dict[str, float] = {}
        self.fastest = (math.inf, math.inf)

    @hookimpl
    def abh3_config_schema(self) -> dict[str, Any]:
        return js.mapping(
            {
                "robot": js.text("the robot the keyboard drives (a robot's or a unit's name)"),
                "units": js.names("robots or units (each drives its whole robot)"),
                "speed": js.number(0.0, 10.0, "m/s", 0.2, lo_open=True),
                "turn": js.number(0.0, 20.0, "rad/s", 0.5, lo_open=True),
                "priority": js.integer(-100, 100, default=0),
                "timeout": js.number(0.05, 10.0, "s", 0.6),
            },
        ) | {"anyOf": [{"required": ["units"]}, {"required": ["robot"]}]}

    @hookimpl
    def abh3_configure(self, section: Section, config: Config) -> None:
        section.only({*teleop_target.KEYS, "speed", "turn", "priority", "timeout"})
        robots = teleop_target.robots(section, config, "keyboard")
        self.units = teleop_target.units(robots)
        self.fastest = teleop_target.fastest(robots, config)
        self.settings = {
            "speed": section.number("speed", 0.2, 0.0, 10.0, lo_open=True),
            "turn": section.number("turn", 0.5, 0.0, 20.0, lo_open=True),
            "priority": section.integer("priority", 0, -100, 100),
            # a held key repeats only after the terminal's delay (often 0.25–0.5 s)
            "timeout": section.number("timeout", 0.6, 0.05, 10.0),
        }

    @hookimpl
    def abh3_input_sources(self, register: Any, supervisor: SupervisorView) -> None:
        s = self.settings
        register(
            KeyboardSource(
                self.units,
                int(s["priority"]),
                s["timeout"],
                Teleop(s["speed"], s["turn"], self.fastest),
            )
        )
