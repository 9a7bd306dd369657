"""A small blocking client of the control socket, and the one-shot commands built on it:
``abh3 status`` (health checks: exit 0 when every unit is online) and ``abh3 send``."""

from __future__ import annotations

import json
import socket
from pathlib import Path
from typing import Any

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


def status_lines(snapshot: dict[str, Any]) -> list[str]:
    lines = ["EMERGENCY STOP latched"] if snapshot["estop"] else []
    for name, u in snapshot["units"].items():
        state = {True: "online", False: "OFFLINE", None: "waiting"}[u["online"]]
        fb, sp, st = u["feedback"], u["setpoint"], u["stats"]
        vel = "–" if fb is None else f"A/B {fb['vel_a']:.1f} {fb['vel_b']:.1f}"
        errors = " ".join(u["words"].get("error", {}).get("names", [])) or "no errors"
        lines.append(
            f"{name}: {state} {st['rate_hz']:.1f}/{st['requested_rate_hz']:g} Hz, "
            f"cmd {sp['kind']} {sp['ay']:.1f} {sp['bx']:.1f}, fbk {vel}, {errors}"
        )
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
