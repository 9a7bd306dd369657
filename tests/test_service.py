"""The control endpoint: protocol, arbitration, read-only, e-stop, permissions, fuzzing."""

from __future__ import annotations

import asyncio
import json
import os
import socket
import stat
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from abh3_supervisor.clients.control import ControlClient, status_lines
from abh3_supervisor.errors import Abh3Error, RunError
from abh3_supervisor.service import paths
from abh3_supervisor.service import protocol as rpc
from abh3_supervisor.service.server import CLIENT_PRIORITY, CLIENT_TIMEOUT_S
from tests.support.headless import headless_demo
from tests.support.served import Served
from tests.support.wire_monitor import WireMonitor

pytestmark = pytest.mark.wallclock  # real time: runtimes, sockets, processes


def raw(path: Path, *lines: bytes) -> list[dict[str, Any]]:
    """Send raw lines; read one reply per line (JSON-RPC notifications get none)."""
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
        sock.settimeout(5)
        sock.connect(str(path))
        sock.sendall(b"".join(lines))
        reader = sock.makefile("rb")
        return [json.loads(reader.readline()) for _ in lines]


def test_hello_state_and_commands_with_the_seeds_answers(served: Served) -> None:
    client = ControlClient(served.path)
    try:
        hello = client.call("hello")
        assert hello["protocol"] == rpc.PROTOCOL and hello["units"] == ["left", "right"]
        assert client.call("command", unit="left", text="SERVO ON ON") == {
            "response": "",
            "responses": {"left": ""},
            "clamped": {},
            "held": False,
            "why": {},
        }
        assert client.call("command", units=["left"], text="FOO")["responses"] == {
            "left": "Invalid Command."
        }
        # a VEL to a robot not switched on is refused in its answer (the robot decision)
        assert client.call("command", unit="right", text="VEL 10 0")["response"] == (
            "Invalid Command."
        )
        for text in ("SERVO ON ON", "START ON ON"):
            assert client.call("command", units=["left", "right"], text=text)["response"] == ""
        # motion is this client's, held while it is here; beyond the limit it says so
        held = client.call("command", units=["left", "right"], text="VEL 7000 -10")
        assert held["response"] == "" and held["held"] is True
        assert held["clamped"] == {
            u: "clamped: VEL 7000 -10 → 6553.4 -9.362 (wire range -6553.6 … 6553.4)"
            for u in ("left", "right")
        }
        assert client.call("alive") == {"ok": True, "holds": ["left", "right"], "lost": {}}
        state = client.call("state")
        left = state["units"]["left"]
        assert "AY_SERVO_ON" in left["inputs"]["names"] and left["protocol"] == "2021"
        assert state["units"]["right"]["protocol"] == "2023"
        assert all(line.startswith(("left:", "right:", "robot ")) for line in status_lines(state))
        with pytest.raises(RunError, match="no unit named 'middle'"):
            client.call("command", unit="middle", text="SERVO ON ON")
    finally:
        client.close()


def test_a_clients_motion_is_an_arbitrated_input_that_lets_go_when_it_leaves(
    served: Served,
) -> None:
    client = ControlClient(served.path)
    for text in ("SERVO ON ON", "START ON ON"):
        client.call("command", units=["left", "right"], text=text)
    reply = client.call("velocity", unit="right", ay=120.0, bx=-30.0)
    assert reply == {"ok": True, "fresh_for_s": CLIENT_TIMEOUT_S}
    assert served.rt is not None
    sup = served.rt.supervisor
    arbiter = served.rt.plugins.arbiter if served.rt.plugins else None
    assert arbiter is not None
    source = served.on_loop(lambda: arbiter.sources["client1:right"])  # one per unit
    assert (source.units, source.priority, source.timeout) == (
        ("right",),
        CLIENT_PRIORITY,
        CLIENT_TIMEOUT_S,
    )
    assert served.on_loop(
        lambda: (sup.units["right"].setpoint.ay, sup.units["right"].setpoint.bx)
    ) == (
        120.0,
        -30.0,
    )
    with pytest.raises(RunError, match="'ay' must be a finite number"):
        client.call("velocity", unit="right", ay="fast", bx=0)
    client.close()  # leaving lets go: its unit stops at once

    def settled() -> bool:
        return "client1:right" not in arbiter.sources

    for _ in range(1000):  # the loop notices the closed socket; no timing involved
        if served.on_loop(settled):
            break
    assert served.on_loop(lambda: sup.units["right"].setpoint.ay) == 0.0


def test_read_only_clients_see_but_cannot_command(served: Served) -> None:
    replies = raw(
        served.ro_path,
        b'{"jsonrpc":"2.0","id":1,"method":"hello"}\n',
        b'{"jsonrpc":"2.0","id":2,"method":"command","params":{"unit":"left","text":"SERVO ON ON"}}\n',
        b'{"jsonrpc":"2.0","id":3,"method":"estop"}\n',
    )
    assert replies[0]["result"]["read_only"] is True
    assert replies[1]["error"]["code"] == rpc.READ_ONLY == replies[2]["error"]["code"]
    assert served.rt is not None and not served.rt.supervisor.estop


def test_estop_from_a_client_reaches_every_unit(served: Served, wire: WireMonitor) -> None:
    assert served.rt is not None
    rt, sup = served.rt, served.rt.supervisor
    client = ControlClient(served.path)
    for text in ("SERVO ON ON", "START ON ON", "VEL 100 100"):
        client.call("command", units=["left", "right"], text=text)
    client.call("estop")
    wire.estop()

    async def next_exchanges() -> bool:
        since = sup.clock()
        return all(await asyncio.gather(*(sup.wait_exchange(u, since, 1) for u in sup.units)))

    assert served.loop is not None
    assert asyncio.run_coroutine_threadsafe(next_exchanges(), served.loop).result(5)
    for drive in rt.sims["b"].drives.values():  # what the drives were last told
        assert drive.cmd_raw == (0, 0) and not drive.inputs & drive.layout.start.both
    with pytest.raises(RunError, match="emergency stop is latched"):
        client.call("twist", units=["left"], linear_x=0.1, angular_z=0.0)
    assert client.call("command", unit="left", text="START ON ON")["response"] == (
        "Packet Error: 3"
    )
    wire.clear()
    client.call("clear_estop")
    client.close()


def subscribed(path: Path, *, events: bool, state_hz: float) -> tuple[socket.socket, Any]:
    """A raw client of ``path`` subscribed (its echo read): the socket and its reader."""
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    sock.settimeout(5)
    sock.connect(str(path))
    reader = sock.makefile("rb")
    params = {"events": events, "state_hz": state_hz}
    sock.sendall(rpc.encode({"jsonrpc": "2.0", "id": 1, "method": "subscribe", "params": params}))
    assert json.loads(reader.readline())["result"] == params
    return sock, reader


def test_events_and_state_are_pushed_to_subscribers(served: Served) -> None:
    sock, reader = subscribed(served.path, events=True, state_hz=20)
    with sock:
        sock.sendall(b'{"jsonrpc":"2.0","method":"estop"}\n')  # a notification: no reply
        states, events = 0, list[dict[str, Any]]()
        while not states or not any("EMERGENCY STOP" in e["text"] for e in events):
            message = json.loads(reader.readline())
            if message["method"] == "state":
                states += 1
                assert set(message["params"]["units"]) == {"left", "right"}
            else:
                assert message["method"] == "event"
                events.append(message["params"])
        assert all(e["level"] in {"INFO", "WARNING", "ERROR", "CRITICAL"} for e in events)


# ---------------------------------------------------------------- hostile input

JUNK = st.one_of(
    st.binary(max_size=300).map(lambda b: b.replace(b"\n", b" ") + b"\n"),
    st.recursive(
        st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=20),
        lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=4),
        max_leaves=12,
    ).map(lambda v: json.dumps({"jsonrpc": "2.0", "id": 7, "method": "command", "params": v}).encode() + b"\n"),
    st.builds(
        lambda m, p: json.dumps({"jsonrpc": "2.0", "id": 7, "method": m, "params": p}).encode() + b"\n",
        st.sampled_from(["twist", "velocity", "current", "command", "subscribe", "x", ""]),
        st.dictionaries(
            st.sampled_from(["unit", "units", "ay", "bx", "linear_x", "angular_z", "text", "state_hz"]),
            st.none() | st.booleans() | st.floats() | st.text(max_size=10) | st.lists(st.text(max_size=5)),
            max_size=5,
        ),
    ),
)  # fmt: skip


def test_malformed_messages_get_an_error_never_a_crash(served: Served) -> None:
    @settings(max_examples=150, deadline=None)
    @given(lines=st.lists(JUNK, min_size=1, max_size=5))
    def attack(lines: list[bytes]) -> None:
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
            sock.settimeout(5)
            sock.connect(str(served.path))
            reader = sock.makefile("rb")
            for line in lines:
                sock.sendall(line)
                if not line.strip():
                    continue  # blank lines are skipped, as between messages
                reply = json.loads(reader.readline())
                while "method" in reply:  # a notification (after a subscribe): not a reply
                    reply = json.loads(reader.readline())
                assert ("error" in reply) != ("result" in reply)
                if "error" in reply:
                    assert isinstance(reply["error"]["code"], int) and reply["error"]["message"]

    attack()
    client = ControlClient(served.path)  # and it still serves
    assert client.call("hello")["protocol"] == rpc.PROTOCOL
    client.close()


def test_an_over_long_line_is_refused(served: Served) -> None:
    reply = raw(served.path, b"x" * (rpc.MAX_LINE + 10) + b"\n")[0]
    assert reply["error"]["code"] == rpc.INVALID_REQUEST


# ---------------------------------------------------------------- who may connect


def test_the_socket_is_private_to_its_owner(served: Served) -> None:
    assert stat.S_IMODE(served.path.stat().st_mode) == 0o600
    assert stat.S_IMODE(served.path.parent.stat().st_mode) == 0o700
    if os.getuid() != 0:
        return  # only root can become another user to try
    os.chmod(served.path.parent.parent, 0o755)  # pytest's tmp dirs are private themselves
    pid = os.fork()
    if pid == 0:  # the child becomes nobody and tries
        code = 1
        try:
            os.setgid(65534)
            os.setuid(65534)
            with socket.socket(socket.AF_UNIX) as sock:
                sock.connect(str(served.path))
        except PermissionError:
            code = 3
        finally:
            os._exit(code)
    _, status = os.waitpid(pid, 0)
    assert os.waitstatus_to_exitcode(status) == 3  # refused by the file's permissions


def test_a_live_socket_is_not_taken_over_and_a_stale_one_is_removed(
    served: Served, tmp_path: Path
) -> None:
    with pytest.raises(RunError, match="another supervisor is serving it"):
        paths.remove_stale(served.path)
    stale = tmp_path / "stale.sock"
    sock = socket.socket(socket.AF_UNIX)
    sock.bind(str(stale))
    sock.close()  # bound, never listening: what a killed supervisor leaves
    paths.remove_stale(stale)
    assert not stale.exists()
    not_a_socket = tmp_path / "file.sock"
    not_a_socket.write_text("x")
    with pytest.raises(Abh3Error, match="not a socket"):
        paths.remove_stale(not_a_socket)


def test_status_and_send_against_a_headless_run(tmp_path: Path) -> None:
    import subprocess
    import sys

    root = Path(__file__).parent.parent
    sock = tmp_path / "run" / "demo.sock"
    with headless_demo(sock) as run:

        def abh3(*args: str) -> subprocess.CompletedProcess[str]:
            cmd = [sys.executable, "-m", "abh3_supervisor", *args, "--connect", str(sock)]
            return subprocess.run(cmd, capture_output=True, text=True, cwd=root, timeout=30)

        status = abh3("status")
        assert status.returncode == 0, status.stderr
        assert status.stdout.startswith("left: online")
        sent = abh3("send", "SELECT 3 3", "--unit", "left")
        assert (sent.returncode, sent.stdout) == (0, "''\n")
        bad = abh3("send", "SELECT ² 7", "--unit", "left")
        assert (bad.returncode, bad.stdout) == (1, "'Invalid Command.'\n")
        state = json.loads(abh3("status", "--json").stdout)
        assert {"AY_SELECT0", "AY_SELECT1"} <= set(state["units"]["left"]["inputs"]["names"])
    rest = run.log
    assert rest.count("stop frame confirmed by the drive") == 2
    assert not sock.exists()  # removed on the way out
    gone = subprocess.run(
        [sys.executable, "-m", "abh3_supervisor", "status", "--connect", str(sock)],
        capture_output=True,
        text=True,
        cwd=root,
    )
    assert gone.returncode == 1 and "no supervisor serves" in gone.stderr


def test_clients_at_one_rate_share_each_state_snapshot(
    served: Served, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The snapshot is built on the bus loop: once per tick for every client at a rate,
    not once per client (two TUIs cost what one does)."""
    from abh3_supervisor.service import state_push
    from abh3_supervisor.service.snapshot import unit_json as real

    built: list[str] = []  # a unit's part of a pushed state, each time one is built

    def counted(sup: Any, unit: Any) -> bytes:
        built.append(unit.name)
        return real(sup, unit)

    monkeypatch.setattr(state_push, "unit_json", counted)
    clients = [subscribed(served.path, events=False, state_hz=20) for _ in range(2)]
    socks, readers = [c[0] for c in clients], [c[1] for c in clients]
    try:
        received = 0
        for _ in range(20):  # 20 ticks' worth for each client
            for reader in readers:
                while json.loads(reader.readline()).get("method") != "state":
                    pass
                received += 1
        assert received == 40
        # one build of both units per tick (and the first of each), not one per client
        assert built.count("left") == built.count("right") <= 20 + 4
    finally:
        for sock in socks:
            sock.close()


def test_client_text_cannot_forge_a_log_line_or_drive_a_terminal(
    served: Served, caplog: pytest.LogCaptureFixture
) -> None:
    """A client's audit and command text reach every log escaped and capped: a newline
    cannot start a line of its own, an escape sequence cannot reach the reader's terminal."""
    from abh3_supervisor.core.eventlog import EventLog
    from abh3_supervisor.core.supervisor import OperatorAction
    from abh3_supervisor.core.text import MAX_LOGGED, clean

    assert served.rt is not None
    sup = served.rt.supervisor
    actions: list[OperatorAction] = []
    served.on_loop(sup.subscribe, lambda e: actions.append(e) if isinstance(e, OperatorAction) else None)  # fmt: skip
    forged = "x\n\u001b[2J12:00:00.000 CRITICAL fake line\u202e"
    client = ControlClient(served.path)
    try:
        client.call("audit", action=forged + "y" * 5000)
        with caplog.at_level("INFO"):
            client.call("command", unit="left", text=forged)
    finally:
        client.close()
    line = EventLog(sup).line(actions[-1])
    assert line is not None
    for text in (line[1], *(r.getMessage() for r in caplog.records)):
        assert "\n" not in text and "\u001b" not in text and "\u202e" not in text
    assert "x\\n\\x1b[2J12:00:00.000 CRITICAL fake line\\u202e" in line[1]
    cut = len(forged) + 5000 - MAX_LOGGED
    assert line[1].endswith(f"… (+{cut} characters)") and len(actions[-1].action) < 2 * MAX_LOGGED
    assert clean("plain text") == "plain text"


def test_verify_again_and_the_identitys_string_form_over_the_socket(served: Served) -> None:
    """A client re-checks a drive's CAN settings against the YAML (audited), and the
    parameter identity says which TelABH3 string form the drive answers."""
    client = ControlClient(served.path, timeout=10)
    try:
        checked = client.call("verify", unit="left")
        assert checked["state"] == "ok" and checked["mismatches"] == []
        assert {row["address"] for row in checked["rows"]} >= {0x4102, 0x4103, 0x4117}
        identity = client.call("param_identity", unit="left", address=2)
        assert identity["text"] == "2.3.0.1"
        assert identity["form"].startswith("CP000095") and "telabh3:" in identity["form"]
        with pytest.raises(RunError, match="no unit named 'middle'"):
            client.call("verify", unit="middle")
    finally:
        client.close()


def test_a_client_holds_motion_on_each_unit_and_is_told_when_it_lapsed(served: Served) -> None:
    """One source per client and unit: a VEL on right does not take left's away; `alive`
    says which units' motion the client still owns (`abh3 send --hold` stops on a loss)."""
    assert served.rt is not None and served.rt.plugins is not None
    sup, arbiter = served.rt.supervisor, served.rt.plugins.arbiter
    assert arbiter is not None
    client = ControlClient(served.path)
    try:
        for text in ("SERVO ON ON", "START ON ON"):
            client.call("command", units=["left", "right"], text=text)
        assert client.call("command", unit="left", text="VEL 100 0")["held"] is True
        assert client.call("command", unit="right", text="VEL 50 0")["held"] is True
        setpoints = served.on_loop(lambda: (sup.units["left"].setpoint.ay, sup.units["right"].setpoint.ay))  # fmt: skip
        assert setpoints == (100.0, 50.0)
        assert sorted(client.call("alive")["holds"]) == ["left", "right"]
        # the client goes quiet past the timeout (as the arbiter's timer would see it later)
        served.on_loop(lambda: arbiter.poll(arbiter.clock() + 2 * CLIENT_TIMEOUT_S))
        assert client.call("alive")["holds"] == []
        assert served.on_loop(lambda: sup.units["left"].setpoint.ay) == 0.0
    finally:
        client.close()


def test_pushes_give_way_while_the_buses_run_late(served: Served) -> None:
    """A bus step that came late (its pump says so) slows every subscriber's pushes, and
    the pushed state says by how much, as the ``state`` method does, on either socket."""
    assert served.rt is not None
    lateness = iter([0.5, 0.05])  # the first told before any push: old news (view_pace.py)
    served.on_loop(setattr, served.rt.pumps["b"], "take_late", lambda: next(lateness, 0.0))
    served.on_loop(setattr, served.pace, "held", lambda: False)  # whatever CI's quota does
    sock, reader = subscribed(served.path, events=False, state_hz=20)
    with sock:
        pushed: list[dict[str, Any] | None] = []
        while len(pushed) < 4:
            message = json.loads(reader.readline())
            assert message["method"] == "state"
            pushed.append(message["params"]["slowed"])
    slowed = {"by": 2, "late_ms": 50.0, "quota": False}
    assert pushed == [None, None, slowed, slowed]  # slowed from the push after it was told
    for path in (served.path, served.ro_path):
        client = ControlClient(path)
        assert client.call("state")["slowed"] == slowed
        client.close()


def test_a_refused_command_says_why_beside_the_seeds_answer(served: Served) -> None:
    client = ControlClient(served.path)
    try:
        result = client.call("command", unit="left", text="VEL 10 0")
        assert result["response"] == "Invalid Command."
        assert result["why"]["left"].startswith("robot 'left' may not move: left: SERVO A")
        result = client.call("command", unit="left", text="RESET ON")  # RESET takes two
        assert result["response"] == "Invalid Command."
        assert result["why"]["left"].startswith("not understood: ")
    finally:
        client.close()
