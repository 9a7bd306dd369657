"""A small blocking client of the control socket, and the one-shot commands built on it:
``abh3 status`` (health checks: exit 0 when every unit is online) and ``abh3 send``."""

from __future__ import annotations

import json
import socket
from pathlib import Path
from typing import Any

from abh3_supervisor.config.model import ControlMode, Role, VelocityModel
from abh3_supervisor.core import readouts
from abh3_supervisor.errors import RunError
from abh3_supervisor.service import protocol as rpc
from abh3_supervisor.service.paths import default_socket


class ControlClient:
    def __init__(self, path: Path, timeout: float = 5.0) -> None:
        self.path = path
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self.sock.settimeout(timeout)
        try:
            self.sock.connect(str(path))
        except (FileNotFoundError, ConnectionRefusedError):
            self.sock.close()
            raise RunError(
                f"no supervisor serves {path} (is `abh3 run CONFIG --headless` running? "
                "give its socket with --connect PATH)"
            ) from None
        except OSError as exc:
            self.sock.close()
            raise RunError(f"cannot connect to {path}: {exc.strerror or exc}") from None
        self.reader = self.sock.makefile("rb")
        self._next = 0

    def call(self, method: str, **params: Any) -> Any:
        self._next += 1
        rid = self._next
        message = {"jsonrpc": "2.0", "id": rid, "method": method, "params": params}
        try:
            self.sock.sendall(rpc.encode(message))
            while True:  # notifications may come between: skip to our reply
                line = self.reader.readline(rpc.MAX_LINE * 64)
                if not line:
                    raise RunError(f"{self.path}: the supervisor closed the connection")
                reply = json.loads(line)
                if reply.get("id") == rid:
                    break
        except (OSError, ValueError) as exc:
            raise RunError(f"{self.path}: {exc}") from None
        if "error" in reply:
            raise RunError(f"{method}: {reply['error'].get('message')}")
        return reply.get("result")

    def close(self) -> None:
        self.reader.close()
        self.sock.close()


def status(path: Path, as_json: bool) -> int:
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
    return 0 if all(u["online"] for u in units) and not snapshot["estop"] else 1


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
        ]
        lines.append(" · ".join(p for p in parts if p is not None))
    return lines


def send(path: Path, text: str, units: list[str]) -> int:
    client = ControlClient(path, timeout=10.0)
    try:
        names = units or [
            n for n, u in client.call("state")["units"].items() if u["role"] == "command"
        ]
        response = client.call("command", units=names, text=text)["response"]
    finally:
        client.close()
    print(repr(response))  # the seed's exact answer: '' , 'Invalid Command.', 'Packet Error: N'
    return 0 if response == "" else 1


def find_socket(connect: Path | None) -> Path:
    """The socket to talk to: the one given, else the only one in the default place."""
    if connect is not None:
        return connect
    here = default_socket("x").parent
    found = [p for p in sorted(here.glob("*.sock")) if _served(p)] if here.is_dir() else []
    if len(found) == 1:
        return found[0]
    if not found:
        raise RunError(f"no supervisor is serving in {here}; give its socket with --connect PATH")
    names = ", ".join(str(p) for p in found)
    raise RunError(f"several supervisors serve ({names}): pick one with --connect PATH")


def _served(path: Path) -> bool:
    """Someone answers there (a supervisor killed with SIGKILL leaves its socket file)."""
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as probe:
        probe.settimeout(1.0)
        try:
            probe.connect(str(path))
        except OSError:
            return False
    return True
