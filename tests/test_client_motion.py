"""A client is told the truth about the motion it holds, and a client that has gone
commands nothing: taken over, e-stopped or dropped is said at once (``alive``, a ``lost``
notification, `abh3 send --hold` exit 1), and what a client sent that the service had not
carried out when it left never reaches the wire (judged from the frames sent)."""

from __future__ import annotations

import asyncio
import json
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import can
import pytest

from abh3_supervisor.clients.control import ControlClient
from abh3_supervisor.protocol import flags, frames, ids
from abh3_supervisor.service import protocol as rpc
from tests.support.served import Served

pytestmark = pytest.mark.wallclock  # real time: runtimes, sockets, processes

ROOT = Path(__file__).resolve().parent.parent
LEFT = 1  # TWO_UNITS: left is a 2021 drive at address 1, commanded from host 2


class Tap(can.Listener):
    """Every DP0 command frame the supervisor sends to the left drive, decoded."""

    def __init__(self) -> None:
        self.sent: list[frames.Dp0Command] = []

    def on_message_received(self, msg: can.Message) -> None:
        if msg.arbitration_id == ids.dp0_command_id(LEFT, 2):
            cmd = frames.decode_dp0_command(bytes(msg.data), flags.LAYOUT_2021.generation)
            assert isinstance(cmd, frames.Dp0Command)
            self.sent.append(cmd)

    def moving(self) -> list[frames.Dp0Command]:
        return [c for c in self.sent if c.cmd_ay or c.cmd_bx]


def tap(served: Served) -> Tap:
    assert served.rt is not None
    listener = Tap()
    served.on_loop(setattr, served.rt.pumps["b"], "recorder", listener)
    return listener


def until(served: Served, condition: Callable[[], bool], what: str) -> None:
    """Wait, on the loop's own state, for ``condition`` (bounded: a failure, not a hang)."""
    deadline = time.monotonic() + 5.0
    while not served.on_loop(condition):
        assert time.monotonic() < deadline, f"not within 5 s: {what}"


def exchanges(served: Served, n: int = 3) -> None:
    """``n`` more DP0 exchanges with the left drive: what was set has reached the wire."""
    assert served.rt is not None and served.loop is not None
    sup = served.rt.supervisor

    async def wait() -> bool:
        return await sup.wait_exchange("left", sup.clock() + 0.001, 2.0)

    for _ in range(n):
        assert asyncio.run_coroutine_threadsafe(wait(), served.loop).result(5)


def request(method: str, rid: int | None = 1, **params: Any) -> bytes:
    message: dict[str, Any] = {"jsonrpc": "2.0", "method": method, "params": params}
    if rid is not None:
        message["id"] = rid
    return rpc.encode(message)


class Raw:
    """A client on a plain socket: its notifications are seen as they come."""

    def __init__(self, path: Path) -> None:
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self.sock.settimeout(5)
        self.sock.connect(str(path))
        self.reader = self.sock.makefile("rb")
        self.notes: list[dict[str, Any]] = []
        self.rid = 0

    def call(self, method: str, **params: Any) -> Any:
        self.rid += 1
        self.sock.sendall(request(method, self.rid, **params))
        while True:
            message = json.loads(self.reader.readline())
            if "method" in message:
                self.notes.append(message)
            elif message.get("id") == self.rid:
                assert "result" in message, message
                return message["result"]

    def notice(self) -> dict[str, Any]:
        """The next notification (bounded by the socket's timeout)."""
        if self.notes:
            return self.notes.pop(0)
        while True:
            message: dict[str, Any] = json.loads(self.reader.readline())
            if "method" in message:
                return message

    def close(self) -> None:
        self.reader.close()
        self.sock.close()


def running(served: Served, *units: str) -> ControlClient:
    """SERVO and START on (switches stay when their client leaves)."""
    setup = ControlClient(served.path)
    for text in ("SERVO ON ON", "START ON ON"):
        assert setup.call("command", units=list(units), text=text)["response"] == ""
    return setup


# ---------------------------------------------------------------- the truth about motion


def test_motion_taken_over_is_said_at_once_and_alive_stops_claiming_it(served: Served) -> None:
    setup = running(served, "left")
    holder = Raw(served.path)
    try:
        assert holder.call("command", unit="left", text="VEL 100 0")["held"] is True
        assert holder.call("alive") == {"ok": True, "holds": ["left"], "lost": {}}
        other = setup.call("hello")["name"]
        setup.call("command", unit="left", text="VEL 200 0")  # same priority, later: it wins
        note = holder.notice()  # pushed without being asked
        assert note["method"] == "lost"
        assert note["params"] == {"unit": "left", "reason": f"taken over by {other}:left"}
        assert holder.call("alive") == {
            "ok": True,
            "holds": [],
            "lost": {"left": f"taken over by {other}:left"},
        }
        # it stays lost: the other's motion ending does not give it back
        setup.call("release")
        assert holder.call("alive")["holds"] == []
    finally:
        holder.close()
        setup.close()


def test_an_estop_ends_held_motion_for_good_and_says_so(served: Served) -> None:
    setup = running(served, "left")
    holder = Raw(served.path)
    try:
        holder.call("command", unit="left", text="VEL 100 0")
        setup.call("estop")
        note = holder.notice()
        assert note["params"] == {"unit": "left", "reason": "the emergency stop is latched"}
        setup.call("clear_estop")
        reply = holder.call("alive")  # cleared: still nothing held until commanded again
        assert reply["holds"] == [] and reply["lost"] == {"left": "the emergency stop is latched"}
        for text in ("SERVO ON ON", "START ON ON"):  # the e-stop switched both off
            setup.call("command", unit="left", text=text)
        holder.call("command", unit="left", text="VEL 120 0")  # a command after the clear
        assert holder.call("alive") == {"ok": True, "holds": ["left"], "lost": {}}
    finally:
        holder.close()
        setup.close()


def test_a_drive_that_stops_answering_drops_the_held_motion_and_says_so(served: Served) -> None:
    setup = running(served, "left")
    holder = Raw(served.path)
    try:
        holder.call("command", unit="left", text="VEL 100 0")
        setup.call("simulate", unit="left", silent=True)
        deadline = time.monotonic() + 5.0
        while (reply := holder.call("alive"))["holds"]:  # present all along: not a lapse
            assert time.monotonic() < deadline, "the silent drive's motion still held"
        why = "the drive stopped on its own (a gap in its answers), or the unit is held"
        assert reply["lost"] == {"left": why}
        note = holder.notice()  # and it was pushed as it happened
        assert note["method"] == "lost" and note["params"] == {"unit": "left", "reason": why}
    finally:
        setup.call("simulate", unit="left", silent=False)
        holder.close()
        setup.close()


def test_a_lapse_is_said_at_once(served: Served) -> None:
    """The client went quiet past the timeout (as the arbiter's timer sees it later)."""
    assert served.rt is not None and served.rt.plugins is not None
    arbiter = served.rt.plugins.arbiter
    assert arbiter is not None
    setup = running(served, "left")
    holder = Raw(served.path)
    try:
        holder.call("command", unit="left", text="VEL 100 0")
        served.on_loop(lambda: arbiter.poll(arbiter.clock() + 1.0))
        why = "lapsed: no line from this client for 0.5 s (stopped or starved)"
        assert holder.notice()["params"] == {"unit": "left", "reason": why}
        assert holder.call("alive") == {"ok": True, "holds": [], "lost": {"left": why}}
    finally:
        holder.close()
        setup.close()


def test_send_hold_ends_with_1_and_says_why_when_taken_over(served: Served) -> None:
    setup = running(served, "left")
    cmd = [sys.executable, "-m", "abh3_supervisor", "send", "VEL 100 0", "--unit", "left"]
    holding = subprocess.Popen(
        [*cmd, "--hold", "--connect", str(served.path)],
        stderr=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
        cwd=ROOT,
    )
    try:
        assert holding.stderr is not None
        assert "holding 'VEL 100 0' on left" in holding.stderr.readline()
        other = setup.call("hello")["name"]
        setup.call("command", unit="left", text="VEL 200 0")
        assert holding.wait(10) == 1
        said = holding.stderr.read()
        assert f"left: the motion held by this command ended: taken over by {other}:left" in said
    finally:
        if holding.poll() is None:
            holding.kill()
            holding.wait()
        setup.close()


# ---------------------------------------------------------------- a client that has gone


class Paused:
    """The service's loop held still (buses and all) while a client does what it does:
    what that client sent and its leaving are both there when the loop goes on."""

    def __init__(self, served: Served) -> None:
        self.served, self.go, self.held = served, threading.Event(), threading.Event()

    def __enter__(self) -> Paused:
        assert self.served.loop is not None

        def hold() -> None:
            self.held.set()
            self.go.wait(10)

        self.served.loop.call_soon_threadsafe(hold)
        assert self.held.wait(5)
        return self

    def __exit__(self, *exc: object) -> None:
        self.go.set()


def gone_client(served: Served, *lines: bytes, half: bool = False) -> None:
    """A client that sends ``lines`` and leaves (``half``: shuts its sending side and
    waits for answers) before the service has read a byte of it."""
    server = served.servers[0]
    ended: list[object] = []
    serve = server._serve

    async def counted(client: Any) -> None:
        try:
            await serve(client)
        finally:
            ended.append(client)

    served.on_loop(setattr, server, "_serve", counted)
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    with Paused(served):
        sock.connect(str(served.path))  # taken by the kernel's backlog meanwhile
        sock.sendall(b"".join(lines))
        if half:
            sock.shutdown(socket.SHUT_WR)
        else:
            sock.close()
    if half:
        sock.settimeout(5)
        while sock.recv(4096):  # its answers, until the service closes
            pass
        sock.close()
    until(served, lambda: bool(ended), "the client seen leaving")
    served.on_loop(delattr, server, "_serve")


@pytest.mark.parametrize("half", [False, True], ids=["closed", "shut-its-sending-side"])
def test_motion_from_a_client_that_has_gone_never_reaches_the_wire(
    served: Served, half: bool
) -> None:
    setup = running(served, "left")
    frames_sent = tap(served)
    try:
        gone_client(served, request("command", unit="left", text="VEL 300 0"), half=half)
        gone_client(served, request("velocity", unit="left", ay=300.0, bx=0.0), half=half)
        exchanges(served)
        assert frames_sent.sent and frames_sent.moving() == []
        assert served.rt is not None
        assert served.on_loop(lambda: served.rt.supervisor.units["left"].setpoint.ay) == 0.0
    finally:
        setup.close()


def test_switches_from_a_client_that_has_gone_are_dropped_its_estop_is_not(
    served: Served,
) -> None:
    assert served.rt is not None
    sup = served.rt.supervisor
    servo = sup.units["left"].layout.servo.both
    gone_client(served, request("command", unit="left", text="SERVO ON ON"))
    exchanges(served)
    assert served.on_loop(lambda: sup.units["left"].inputs & servo) == 0
    # its e-stop is carried out, even after lines refused (whose answers cannot reach it)
    gone_client(
        served,
        request("command", 1, unit="left", text="START ON ON"),
        request("state", 2),
        request("estop", 3),
    )
    assert served.on_loop(lambda: sup.estop) is True
    served.on_loop(sup.clear_emergency_stop)


def test_a_client_leaving_while_its_command_awaits_the_drive_lets_go_at_once(
    served: Served, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The answer waits for the drive; the client leaves meanwhile: its motion stops then,
    not when the wait ends, and the request, once it ends, moves nothing."""
    assert served.rt is not None and served.loop is not None
    sup = served.rt.supervisor
    setup = running(served, "left")
    frames_sent = tap(served)
    release = asyncio.Event()
    real = sup.confirm

    async def slow_confirm(name: str, since: float) -> str:
        await release.wait()
        return await real(name, since)

    monkeypatch.setattr(sup, "confirm", slow_confirm)
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    sock.connect(str(served.path))
    sock.sendall(request("command", unit="left", text="VEL 300 0"))
    until(served, lambda: sup.units["left"].setpoint.ay == 300.0, "the VEL taken")
    sock.close()
    arbiter = served.rt.plugins.arbiter if served.rt.plugins else None
    assert arbiter is not None
    # let go as it left (not 0.5 s later, for want of proof it is alive: a lapse)
    until(served, lambda: not [n for n in arbiter.sources if n.startswith("client")], "let go")
    assert served.on_loop(lambda: sup.units["left"].setpoint.ay) == 0.0
    assert served.on_loop(lambda: not release.is_set())  # the request is still waiting
    seen = len(frames_sent.sent)
    served.on_loop(release.set)
    until(served, lambda: len(served.servers[0].clients) == 1, "the request ended")
    exchanges(served)
    assert frames_sent.sent[seen:] and all(
        not (c.cmd_ay or c.cmd_bx) for c in frames_sent.sent[seen:]
    )
    setup.close()
