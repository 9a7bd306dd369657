"""A small blocking client of the control socket, and the one-shot commands built on it:
``abh3 status`` (health checks: exit 0 when every unit is online), ``abh3 send`` and
``abh3 estop``.
The socket is local, or on another host through SSH (``ssh://…``, :mod:`.ssh`)."""

from __future__ import annotations

import contextlib
import json
import os
import select
import socket
import sys
from pathlib import Path
from typing import Any

from abh3_supervisor.clients import peer
from abh3_supervisor.clients.ssh import Endpoint, SshTarget, Tunnel
from abh3_supervisor.config.model import ControlMode, Role, VelocityModel
from abh3_supervisor.core import readouts
from abh3_supervisor.core.commands import CurrentCommand, VelocityCommand, parse_command
from abh3_supervisor.errors import Abh3Error, CommandError, Interrupted, RunError
from abh3_supervisor.runtime import signals
from abh3_supervisor.service import protocol as rpc
from abh3_supervisor.service.paths import default_socket, fallback_directory, foreign, served


class ControlClient:
    def __init__(self, path: Endpoint, timeout: float = 5.0) -> None:
        self.path = path
        self.tunnel: Tunnel | None = None
        local = path if isinstance(path, Path) else self._forward(path)
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self.sock.settimeout(timeout)
        try:
            self.sock.connect(str(local))
        except (FileNotFoundError, ConnectionRefusedError):
            self._close_all()
            raise RunError(
                f"no supervisor serves {path} (is `abh3 run CONFIG --headless` running? "
                "give its socket with --connect PATH)"
            ) from None
        except OSError as exc:
            self._close_all()
            raise RunError(f"cannot connect to {path}: {exc.strerror or exc}") from None
        try:
            peer.check(self.sock, path)  # who listens there, before a word is sent
        except RunError:
            self._close_all()
            raise
        if self.tunnel is not None:
            self.tunnel.forget_path()
        self.reader = self.sock.makefile("rb")
        self._next = 0

    def _forward(self, target: SshTarget) -> Path:
        self.tunnel = Tunnel(target)
        try:
            self.tunnel.start()
            return self.tunnel.wait_ready()
        except BaseException:
            self.tunnel.close()
            raise

    def call(self, method: str, **params: Any) -> Any:
        self._next += 1
        rid = self._next
        message = {"jsonrpc": "2.0", "id": rid, "method": method, "params": params}
        try:
            # closed on us: what it said before closing, if anything, is read below
            with contextlib.suppress(BrokenPipeError, ConnectionResetError):
                self.sock.sendall(rpc.encode(message))
            while True:  # notifications may come between: skip to our reply
                line = self.reader.readline(rpc.MAX_LINE * 64)
                if not line:
                    raise RunError(self._lost("the supervisor closed the connection"))
                reply = json.loads(line)
                if reply.get("id") == rid:
                    break
                if reply.get("id") is None and "error" in reply:  # refused: it says why
                    why = reply["error"].get("message")
                    raise RunError(f"{self.path}: the supervisor refused this client: {why}")
        except (OSError, ValueError) as exc:
            raise RunError(self._lost(str(exc))) from None
        if "error" in reply:
            raise RunError(f"{method}: {reply['error'].get('message')}")
        return reply.get("result")

    def wait(self, timeout: float) -> None:
        """Until the service sends something (a notification) or ``timeout`` passed."""
        select.select([self.sock], [], [], timeout)

    def _lost(self, why: str) -> str:
        """Why the connection ended: through SSH, ssh itself may know better."""
        said = self.tunnel.explain() if self.tunnel is not None else None
        return said or f"{self.path}: {why}"

    def units(self, wanted: list[str]) -> dict[str, Any]:
        """The service's units as its state has them; each of ``wanted`` must be one (a
        mistake on the command line: exit 2, in every command's words)."""
        known: dict[str, Any] = self.call("state")["units"]
        for unit in wanted:
            if unit not in known:
                raise Abh3Error(f"no unit named '{unit}' (units: {', '.join(known)})")
        return known

    def close(self) -> None:
        self.reader.close()
        self._close_all()

    def _close_all(self) -> None:
        self.sock.close()
        if self.tunnel is not None:
            self.tunnel.close()


def status(path: Endpoint, as_json: bool) -> int:
    client = ControlClient(path)
    try:
        snapshot = client.call("state")
    finally:
        client.close()
    if as_json:
        print(json.dumps(snapshot, indent=1))
    else:
        for line in status_lines(snapshot):
            print(line)
    units = snapshot["units"].values()
    stopped = any((u.get("foreign") or {}).get("stopped") for u in units)
    held = any(_identity(u) for u in units)
    ok = all(u["online"] for u in units) and not snapshot["estop"] and not stopped and not held
    return 0 if ok else 1


def estop(path: Endpoint, *, clear: bool) -> int:
    """``abh3 estop``: latch (or clear) the emergency stop; 0 once the supervisor confirms
    it. Anything short of its answer is a :class:`RunError` (exit 1) saying why."""
    client = ControlClient(path)
    try:
        result = client.call("clear_estop" if clear else "estop")
        latched = client.call("state")["estop"]
    finally:
        client.close()
    if not isinstance(result, dict) or result.get("ok") is not True or latched == clear:
        raise RunError(f"{path}: the supervisor did not confirm it: {result!r}")
    if standing := result.get("standing"):  # stops another host caused, still heard
        raise RunError(
            f"{path}: emergency stop cleared, but not every stop: " + "; ".join(standing)
        )
    if clear:
        print(f"{path}: emergency stop cleared (nothing moves until START and motion are given)")
    else:
        print(
            f"{path}: EMERGENCY STOP latched: every commanded unit zero, START off "
            "(clear it with `abh3 estop --clear`)"
        )
    return 0


def enable(path: Endpoint, robots: list[str], *, on: bool) -> int:
    """``abh3 enable`` / ``abh3 disable``: SERVO and START of every wheel axis of each
    robot's drives on (off) as one act; 0 once every drive reports it (on), 1 naming the
    drive that did not follow, or why it was refused."""
    client = ControlClient(path)
    try:
        known = client.call("state")
        known_names = [*known.get("robots", {}), *known["units"]]
        for robot in robots:  # a mistake on the command line: exit 2, as for a unit
            if robot not in known_names:
                listed = ", ".join(known.get("robots", {})) or "none"
                raise Abh3Error(f"no robot or unit named '{robot}' (robots: {listed})")
        result = client.call("enable" if on else "disable", robots=robots)
    finally:
        client.close()
    if not isinstance(result, dict) or result.get("ok") is not True:
        raise RunError(f"{path}: the supervisor did not confirm it: {result!r}")
    names = ", ".join(result.get("robots", robots))
    if not on:
        print(f"{path}: {names}: SERVO and START off on every wheel axis")
        return 0
    if not_ready := result.get("not_ready"):
        raise RunError(
            f"{path}: switched on, but not every drive followed: "
            + "; ".join(f"robot {r}: {why}" for r, why in not_ready.items())
        )
    print(f"{path}: {names}: every drive reports SERVO and START on (ready)")
    return 0


def _num(value: float, digits: int = 1) -> str:
    return f"{value + 0.0:.{digits}f}"  # + 0.0: never "-0.0"


def _command(u: dict[str, Any], model: VelocityModel | None) -> str:
    if u["role"] == Role.MONITOR:
        return "cmd none (monitor)"
    sp = u["setpoint"]
    label = readouts.axes(model) if model else "AY/BX"  # a service that does not say
    if sp["kind"] == ControlMode.CURRENT:
        return f"cmd current {label} {_num(sp['ay'], 2)} {_num(sp['bx'], 2)} %"
    return f"cmd {label} {_num(sp['ay'])} {_num(sp['bx'])}"


def _feedback(fb: dict[str, Any] | None, model: VelocityModel | None) -> str:
    ab = "A/B –" if fb is None else f"A/B {_num(fb['vel_a'])} {_num(fb['vel_b'])}"
    yx = "Y/X –" if fb is None else f"Y/X {_num(fb['vel_y'])} {_num(fb['vel_x'])}"
    if model is None:
        return f"fbk {ab} {yx}"
    own, other = (yx, ab) if model is VelocityModel.TRAVEL else (ab, yx)
    return f"fbk {own}" if fb is None else f"fbk {own} ({other})"


def _switches(reported: dict[str, Any] | None, model: VelocityModel | None, now: float) -> str:
    label = readouts.axes(model) if model else "AY/BX"
    if reported is None:
        return f"servo {label} ?/? · start {label} ?/? (not reported yet)"
    servo, start = (
        "/".join("ON" if on else "off" for on in reported[key]) for key in ("servo", "start")
    )
    age = now - reported["t"]
    old = f" (reported {age:.1f} s ago)" if age > readouts.REPORT_OLD_S else ""
    return f"servo {label} {servo} · start {label} {start}{old}"


def _faults(u: dict[str, Any]) -> str:
    role, words = Role(u["role"]), u["words"]
    errors, alarms = (
        readouts.read_faults(role, words.get(w, {}).get("value")) for w in ("error", "alarm")
    )
    parts = ["errors " + " ".join(errors.names) if errors.bits else "no errors"]
    if alarms.bits:
        parts.append("alarms " + " ".join(alarms.names))
    parts += dict.fromkeys(errors.notes + alarms.notes)  # each note once
    return " · ".join(parts)


def status_lines(snapshot: dict[str, Any]) -> list[str]:
    """One line per unit, velocities labelled by the unit's model (its own pair first, the
    other model's in brackets), servo and start as the drive reports them."""
    lines = ["EMERGENCY STOP latched"] if snapshot["estop"] else []
    for name, u in snapshot["units"].items():
        state = {True: "online", False: "OFFLINE", None: "waiting"}[u["online"]]
        st = u["stats"]
        model = VelocityModel(u["velocity_model"]) if "velocity_model" in u else None
        parts = [
            f"{name}: {state} {st['rate_hz']:.1f}/{st['requested_rate_hz']:g} Hz",
            _command(u, model),
            _feedback(u["feedback"], model),
            _switches(u["reported"], model, snapshot["t"]) if "reported" in u else None,
            _faults(u),
            _verify(u.get("verify")),
            _foreign(u.get("foreign")),
            _identity(u),
        ]
        lines.append(" · ".join(p for p in parts if p is not None))
    for robot, why in (snapshot.get("robots") or {}).items():  # the robot decision's word
        lines.append(f"robot {robot}: READY" if why is None else f"robot {robot}: not ready: {why}")
    return lines


def _identity(u: dict[str, Any]) -> str | None:
    """A drive that answers in the other layout than the file says: held (docs/safety.md,
    "Identity before energy")."""
    seen, filed = u.get("identified"), u.get("protocol")
    if seen is None or seen == filed:
        return None
    return f"HELD: answers as a {seen} drive, the file says {filed} (only the probe 0x70 is sent)"


def _foreign(f: dict[str, Any] | None) -> str | None:
    """Another host on the unit's drive (core/foreign.py): ``STOPPED: another host (0x02)
    commands drive 0x01 (unit left) — 120 × DP0 command (last …)``, readers after."""
    if not f or not (f["stopped"] or f["hosts"]):
        return None
    heard = " | ".join(h["text"] for h in f["hosts"])
    return f"STOPPED: {f['stopped']} — {heard}" if f["stopped"] else heard


def _verify(v: dict[str, Any] | None) -> str | None:
    """The drive's CAN settings against the file (core/verify.py), when it was checked:
    ``drive settings ok``, ``drive settings MISMATCH: drive 0x4117 … (SERVO/START held)``,
    ``drive settings not verified (why)``, ``drive settings being read``."""
    unread = v is not None and v["state"] == "not verified" and not v["reason"]
    if v is None or v["state"] == "off" or (unread and not v.get("held")):
        return None
    if v["state"] == "mismatch":
        text = "drive settings MISMATCH: " + "; ".join(m["text"] for m in v["mismatches"])
        return text + (" (held at its idle word: verify: refuse)" if v.get("held") else "")
    held = f" — HELD: {v['held']}" if v.get("held") else ""  # verify: refuse fails closed
    if v["state"] == "not verified":
        return f"drive settings not verified ({v['reason'] or 'not read yet'}){held}"
    if v["state"] == "pending":
        return f"drive settings being read{held}"
    return f"drive settings {v['state']}"


MOTION_NEEDS_AN_OWNER = (
    "a one-shot {text!r} would stop the moment `abh3 send` ends: motion belongs to a client "
    "that is present. Use --hold (keeps it until Ctrl-C), the socket's velocity/twist "
    "methods from a program that stays connected, the TUI's command line, or `startup:` "
    "in the YAML for a setpoint the supervisor itself owns"
)
ALIVE_EVERY_S = 0.2  # well inside the service's 0.5 s: a late wake-up costs nothing


def send(path: Endpoint, text: str, units: list[str], *, every: bool, hold: bool) -> int:
    """``abh3 send``: the seed's exact answer per unit; clamp notes on stderr. A motion
    command is refused unless ``hold`` keeps this client present to own it."""
    if not units and not every:
        raise Abh3Error("name the units: --unit NAME (repeat for more) or --all")
    if not hold and _moves(text):
        raise Abh3Error(MOTION_NEEDS_AN_OWNER.format(text=text))
    client = ControlClient(path, timeout=10.0)
    try:
        known = client.units(units)
        names = units or [n for n, u in known.items() if u["role"] == "command"]
        result = client.call("command", units=names, text=text)
        answers = result.get("responses") or dict.fromkeys(names, result["response"])
        for unit, note in result.get("clamped", {}).items():
            print(f"{unit}: {note}", file=sys.stderr)
        for unit, why in (result.get("why") or {}).items():  # why it was refused
            print(f"{unit}: refused: {why}", file=sys.stderr)
        # the seed's exact answer: '' , 'Invalid Command.', 'Packet Error: N' — per unit
        for unit in names:
            print(repr(answers[unit]) if len(names) == 1 else f"{unit}: {answers[unit]!r}")
        code = 0 if result["response"] == "" else 1
        if hold and code == 0 and result.get("held"):
            code = _hold(client, text, names)
    finally:
        client.close()
    return code


def _moves(text: str) -> bool:
    try:
        command = parse_command(text)
    except CommandError:
        return False  # the service answers it as the seed does ('Invalid Command.')
    return isinstance(command, VelocityCommand | CurrentCommand) and bool(command.ay or command.bx)


def _hold(client: ControlClient, text: str, units: list[str]) -> int:
    """Stay present (proof of life every ALIVE_EVERY_S) until a stop signal; leaving then
    takes the motion with it. Ends with 1, saying why, once the motion is gone without us
    leaving — taken over by another client, the e-stop, dropped (this process was stopped
    or starved for longer than the service waits, the drive stopped on its own) — or the
    supervisor itself went away. The service pushes a ``lost`` notice the moment it
    happens: it wakes the wait at once."""
    print(f"holding {text!r} on {', '.join(units)}: Ctrl-C stops it", file=sys.stderr)
    try:
        while True:
            client.wait(ALIVE_EVERY_S)
            try:
                answer = client.call("alive")
            except RunError:
                print(
                    "the supervisor went away: its drives stop on their own command-zero timeout",
                    file=sys.stderr,
                )
                return 1
            holds, lost = answer.get("holds", units), answer.get("lost", {})
            gone = [u for u in units if u not in holds]
            for unit in gone:
                why = lost.get(unit) or "dropped by the supervisor"
                print(
                    f"{unit}: the motion held by this command ended: {why}; it is not resumed",
                    file=sys.stderr,
                )
            if gone:
                return 1
    except Interrupted as exc:
        name = signals.name(exc.signum)  # real-time signals too
        print(f"{name}: released; the motion held by this command stops now", file=sys.stderr)
    return 0


def find_sockets(connect: Endpoint | None) -> list[Endpoint]:
    """The sockets to talk to: the one given (local or ``ssh://``), else every one served
    in the default place (at least one, or a :class:`RunError` saying where it looked)."""
    if connect is not None:
        return [connect]
    here = default_socket("x").parent
    found = _served_in(here)
    if not found:
        hint = "; give its socket with --connect PATH"
        fallback = fallback_directory()
        if here != fallback and (elsewhere := _served_in(fallback, quiet=True)):
            hint = (
                f", but one is in {fallback} (started without $XDG_RUNTIME_DIR): "
                f"give --connect {elsewhere[0]}"
            )
        raise RunError(f"no supervisor is serving in {here}{hint}")
    return list(found)


def _served_in(here: Path, *, quiet: bool = False) -> list[Path]:
    """The sockets served in ``here`` when it is ours and no link (else a
    :class:`RunError`, or none when ``quiet``)."""
    if os.path.lexists(here) and (problem := foreign(here)) is not None:
        if quiet:
            return []
        raise RunError(f"{problem}: no supervisor of yours serves there; give --connect PATH")
    return [p for p in sorted(here.glob("*.sock")) if served(p, 1.0)] if here.is_dir() else []


def find_socket(connect: Endpoint | None) -> Endpoint:
    """The socket to talk to: the one given, else the only one in the default place."""
    found = find_sockets(connect)
    if len(found) == 1:
        return found[0]
    names = ", ".join(str(p) for p in found)
    raise RunError(f"several supervisors serve ({names}): pick one with --connect PATH")


def estop_every(paths: list[Endpoint]) -> int:
    """``abh3 estop`` with no ``--connect`` where several supervisors serve: each latches
    its e-stop — one that stops nothing for want of a choice is the worse mistake. 0 once
    every one confirms; each that does not is said (exit 1)."""
    failed = 0
    for path in paths:
        try:
            estop(path, clear=False)
        except RunError as exc:
            print(f"error: {exc}", file=sys.stderr)
            failed += 1
    return 1 if failed else 0
