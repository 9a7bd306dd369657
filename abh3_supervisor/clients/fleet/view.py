"""The fleet as one text: a header line per robot, a row per unit under it. Rich only (no
Textual), from the model and a time: testable alone.

Only what was seen is claimed: a robot with no status is "no status seen", a value
never reported is "?", a unit not live is greyed with the age of what is shown and
says why (stale, retained copy, robot offline).
"""

from __future__ import annotations

from rich.text import Text

from abh3_supervisor.clients.fleet.model import FleetModel, Robot, Unit

ERROR_MARK, ALARM_MARK = "✖", "▲"
EVENTS_SHOWN = 8
STATE_STYLE = {"online": "bold green", "offline": "bold", "connection_broken": "bold red"}
STATE_TEXT = {"online": "ONLINE", "offline": "offline", "connection_broken": "CONNECTION BROKEN"}
COLUMNS = (  # header, width
    ("unit", 12),
    ("drive", 8),
    ("servo", 7),
    ("start", 7),
    ("command ay/bx", 15),
    ("measured a/b", 15),
    ("owner", 14),
    ("e-stop", 7),
    ("verify", 8),
    ("age", 0),
)


# health's mqtt.not_heard: the kind, what the fleet cannot give, how loudly it is said
NOT_HEARD = (
    ("estop", "e-stops", "bold red"),
    ("instant_actions", "VDA 5050 instantActions (a stopPause is an e-stop)", "bold red"),
    ("twist", "twists", "yellow"),
)
SELECTED = "▶ "  # the selected robot's line starts with it (the app scrolls to it)


def age(seconds: float) -> str:
    return f"{seconds:.1f} s" if seconds < 10 else f"{seconds:.0f} s"


def onoff(value: bool | None) -> str:
    return "?" if value is None else "ON" if value else "off"


def num(value: float | None) -> str:
    return "?" if value is None else f"{value + 0.0:.1f}"  # + 0.0: never "-0.0"


def robot_state(robot: Robot) -> tuple[str, str]:
    if robot.state is None:
        return "no status seen", "bold yellow"
    return STATE_TEXT[robot.state], STATE_STYLE[robot.state]


def unit_cells(unit: Unit) -> list[str]:
    drive = "?" if unit.online is None else "online" if unit.online else "OFFLINE"
    return [
        unit.name,
        drive,
        f"{onoff(unit.servo[0])} {onoff(unit.servo[1])}",
        f"{onoff(unit.start[0])} {onoff(unit.start[1])}",
        f"{num(unit.commanded[0]):>7}{num(unit.commanded[1]):>7}",
        f"{num(unit.measured[0]):>7}{num(unit.measured[1]):>7}",
        unit.owner or "–",
        "LATCHED" if unit.estop else "–",
        unit.verify or "–",
    ]


def why_not_live(robot: Robot, unit: Unit) -> str:
    if not robot.online:
        return "robot not online"
    if unit.retained:
        return "retained copy, by its clock"
    return "stale"


def render(
    model: FleetModel,
    now: float,
    selected: str | None,
    broker: str,
    last_command: str | None,
    *,
    connected: bool = True,
) -> Text:
    """The whole view; ``selected`` the fleet_id the robot keys act on; ``connected``
    False: the broker is lost, so no robot's status is current (each says so)."""
    text = head(model, broker, last_command, connected=connected)
    text.append_text(body(model, now, selected, connected=connected))
    return text


def head(model: FleetModel, broker: str, last_command: str | None, *, connected: bool) -> Text:
    """What stays in sight however long the list: the broker, the last command's outcome,
    messages ignored."""
    text = Text(no_wrap=True, overflow="crop")
    text.append(broker + "\n", "bold" if connected else "bold red")
    if last_command:
        style = "bold red" if "REFUSED" in last_command or "refused" in last_command else "bold"
        text.append(last_command + "\n", style)
    problems = model.malformed + model.wrong_version
    if problems:
        text.append(
            f"{model.malformed} malformed, {model.wrong_version} of another version "
            f"(ignored); last: {model.problem}\n",
            "yellow",
        )
    return text


def body(model: FleetModel, now: float, selected: str | None, *, connected: bool) -> Text:
    """Every robot and its units, then the selected robot's recent events."""
    text = Text(no_wrap=True, overflow="crop")
    if not model.robots:
        text.append("\nNo robot seen on this broker under this prefix yet.\n", "dim")
        return text
    header = " ".join(f"{h:<{w}}" if w else h for h, w in COLUMNS)
    text.append("\n    " + header + "\n", "bold")
    for robot in model.sorted_robots():
        _robot(text, model, robot, now, robot.fleet_id == selected, connected)
    if selected in model.robots:
        _events(text, model.robots[selected], now)
    return text


def _events(text: Text, robot: Robot, now: float) -> None:
    """The selected robot's recent events, newest last, aged by our clock."""
    if not robot.events:
        return
    text.append(f"\nrecent events of {robot.fleet_id}:\n", "bold")
    for event in list(robot.events)[-EVENTS_SHOWN:]:
        unit = f"{event.unit}: " if event.unit else ""
        text.append(f"  {age(now - event.received):>7} ago  {event.kind:<22} {unit}{event.text}\n")


def _health(robot: Robot, model: FleetModel, now: float) -> list[tuple[str, str]]:
    """Trouble in its last health (a bus not ok, messages its plugin dropped, commands it
    cannot hear)."""
    if robot.health is None or not model.health_live(robot, now):
        return []
    notes: list[tuple[str, str]] = []
    buses = robot.health.get("buses", {})
    for name, bus in sorted(buses.items()):
        state = bus.get("state") if isinstance(bus, dict) else None
        if state != "ok":
            notes.append((f"bus {name}: {state}", "bold red"))
    mqtt = robot.health.get("mqtt", {})
    dropped = mqtt.get("dropped")
    if isinstance(dropped, int) and dropped:
        notes.append((f"{dropped} messages dropped by its plugin", "yellow"))
    not_heard = mqtt.get("not_heard")
    not_heard = not_heard if isinstance(not_heard, list) else []
    for kind, what, style in NOT_HEARD:
        if kind in not_heard:
            notes.append((f"it does not hear the fleet's {what}: the broker refused them", style))
    return notes


def _robot(
    text: Text, model: FleetModel, robot: Robot, now: float, selected: bool, connected: bool
) -> None:
    label, style = robot_state(robot)
    text.append(SELECTED if selected else "  ")
    text.append(robot.fleet_id, "reverse" if selected else "bold")
    text.append("  ")
    if connected:
        text.append(label, style)
    else:  # what the broker last said: it may have published a will since
        text.append(f"{label} (last known: broker lost)", "dim")
    details = [f"host {robot.host}" if robot.host else "", f"pid {robot.pid}" if robot.pid else ""]
    details.append(f"v{robot.version}" if robot.version else "")
    seen = "never live" if robot.last_seen is None else f"{age(now - robot.last_seen)} ago"
    details += [f"seen {seen}", "attach: a" if robot.attach else ""]
    text.append("  " + "  ".join(d for d in details if d), "dim" if not robot.online else "")
    for note, note_style in _health(robot, model, now):
        text.append("  " + note, note_style)
    if robot.malformed or robot.wrong_version:
        text.append(f"  {robot.malformed} malformed, {robot.wrong_version} wrong version", "yellow")
    text.append("\n")
    for name in model.unit_names(robot):
        unit = robot.units.get(name)
        text.append("    ")
        if unit is None:
            text.append(f"{name:<{COLUMNS[0][1]}} never seen\n", "dim")
            continue
        live = model.live(robot, unit, now)
        cells = unit_cells(unit)
        for (_, width), cell in zip(COLUMNS, cells, strict=False):
            text.append(f"{cell[:width]:<{width}} ", _cell_style(cell, live, unit))
        shown = age(model.age(unit, now))
        if live:
            text.append(shown + "\n")
        else:
            text.append(f"{shown} ({why_not_live(robot, unit)})\n", "dim")
        _faults(text, unit, live)


def _cell_style(cell: str, live: bool, unit: Unit) -> str:
    if not live:
        return "dim"
    if cell in ("OFFLINE", "LATCHED"):
        return "bold red"
    return ""


def _faults(text: Text, unit: Unit, live: bool) -> None:
    notes: list[tuple[str, str]] = [(f"{ERROR_MARK} {e}", "bold red") for e in unit.errors]
    notes += [(f"{ALARM_MARK} {a}", "yellow") for a in unit.alarms]
    if unit.foreign_host is not None:
        host = unit.foreign_host
        notes.append(
            (f"another host on the bus: address {host.get('address')}, "
             f"{host.get('frames')} frames", "bold red")
        )  # fmt: skip
    if not notes:
        return
    text.append("        ")
    for note, style in notes:
        text.append(note + " ", style if live else "dim")
    text.append("\n")
