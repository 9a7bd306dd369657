"""The control socket survives every client and every path: hostile lines get a JSON-RPC
error and the connection goes on; a client past the limit is told why; a socket path that
cannot be served is exit 2 before the first CAN frame; a directory not made by the
supervisor is never chmodded, and a shared one is refused."""

from __future__ import annotations

import asyncio
import json
import os
import socket
import stat
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import can
import pytest

from abh3_supervisor.clients.control import ControlClient
from abh3_supervisor.clients.link import Link, LinkError
from abh3_supervisor.errors import RunError
from abh3_supervisor.service import protocol as rpc
from abh3_supervisor.service.server import MAX_CLIENTS
from tests.support.served import Served

ROOT = Path(__file__).resolve().parent.parent


def request(method: str, rid: int, **params: Any) -> bytes:
    return rpc.encode({"jsonrpc": "2.0", "id": rid, "method": method, "params": params})


def replies(sock: socket.socket, reader: Any, *lines: bytes) -> list[dict[str, Any]]:
    """Each line sent, its one reply read (skipping notifications)."""
    out = []
    for line in lines:
        sock.sendall(line)
        reply = json.loads(reader.readline())
        while "method" in reply:
            reply = json.loads(reader.readline())
        out.append(reply)
    return out


# ---------------------------------------------------------------- the wire, sans I/O


def test_a_line_too_long_is_reported_once_and_the_next_line_is_whole() -> None:
    splitter = rpc.LineSplitter(limit=10)
    assert splitter.feed(b"abc\ndef") == [b"abc"]
    assert splitter.feed(b"ghijklmnopq") == [None]  # past the limit: said at once
    assert splitter.feed(b"rest of it\nnext\n") == [b"next"]  # its rest dropped
    assert splitter.feed(b"0123456789\n" + b"x" * 11 + b"\nok\n") == [b"0123456789", None, b"ok"]
    assert splitter.feed(b"\n \n\t\n" * 1000 + b"last\n") == [b"last"]  # blank: none


@pytest.mark.parametrize(
    ("line", "code"),
    [
        (b'{"jsonrpc":"2.0","id":' + b"1" * 5000 + b',"method":"hello"}', rpc.PARSE_ERROR),
        (b"[" * 50_000, rpc.PARSE_ERROR),
        (b'{"jsonrpc":"2.0","id":1,"method":"hello\xff"}', rpc.PARSE_ERROR),
        (b"\x00{\x00}\x00", rpc.PARSE_ERROR),  # UTF-16 to json's guess: not UTF-8 JSON
        (b'{"jsonrpc":"2.0","id":[1],"method":"hello"}', rpc.INVALID_REQUEST),
        (b'{"jsonrpc":"2.0","id":1,"method":"hello","params":[]}', rpc.INVALID_PARAMS),
    ],
)
def test_whatever_a_line_holds_parsing_says_what_is_wrong(line: bytes, code: int) -> None:
    with pytest.raises(rpc.RpcError) as caught:
        rpc.parse_request(line)
    assert caught.value.code == code and len(caught.value.message) < 200


def test_numbers_beyond_a_float_are_refused_not_raised() -> None:
    for value in (10**400, -(10**400), float("inf"), True, "1"):
        with pytest.raises(rpc.RpcError, match="'ay' must be a finite number"):
            rpc.number({"ay": value}, "ay")
    assert rpc.number({"ay": 10**20}, "ay") == 1e20


# ---------------------------------------------------------------- a live service


HOSTILE = [
    b'{"jsonrpc":"2.0","id":' + b"9" * 5000 + b',"method":"hello"}\n',  # int digit limit
    request("velocity", 11, unit="left", ay=10**400, bx=0),  # parses; no float holds it
    b"[" * 60_000 + b"\n",  # nesting
    b'{"jsonrpc":"2.0","id":12,"method":"state","params":{"x":"\xc3\x28"}}\n',  # bad UTF-8
    request("subscribe", 13, events="yes", state_hz=10**300),
    request("command", 14, unit=[[["left"]]], text=5),
    request("param_read", 15, unit="left", address=10**4000),
    request("twist", 16, units={"left": 1}, linear_x=None, angular_z=[]),
    request("key", 17, source=["x"], key={"k": 1}),
    request("x" * 60_000, 18),
]


@pytest.mark.wallclock
def test_hostile_lines_each_get_an_error_and_the_connection_goes_on(served: Served) -> None:
    assert served.rt is not None
    sup = served.rt.supervisor
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
        sock.settimeout(10)
        sock.connect(str(served.path))
        reader = sock.makefile("rb")
        answers = replies(sock, reader, *HOSTILE)
        for line, reply in zip(HOSTILE, answers, strict=True):
            assert "error" in reply, (line[:60], reply)
            assert reply["error"]["code"] in {
                rpc.PARSE_ERROR,
                rpc.INVALID_PARAMS,
                rpc.INVALID_REQUEST,
                rpc.METHOD_NOT_FOUND,
            }
            assert len(reply["error"]["message"]) < 300  # a client's text is not echoed whole
        assert [r["id"] for r in answers] == [None, 11, None, None, 13, 14, 15, 16, 17, 18]
        # a line over the reader's limit: one error, the rest of it dropped, then whole again
        sock.sendall(b'{"jsonrpc":"2.0","id":20,"method":"' + b"y" * (rpc.MAX_LINE + 10))
        sock.sendall(b'"}\n' + request("hello", 21))
        over, hello = (json.loads(reader.readline()) for _ in range(2))
        assert over["error"]["code"] == rpc.INVALID_REQUEST and "65536" in over["error"]["message"]
        assert hello["id"] == 21 and hello["result"]["units"] == ["left", "right"]
        # and it still commands: the drive is told, not only the log
        reply = replies(sock, reader, request("command", 22, unit="left", text="SELECT 3 3"))[0]
        assert reply["result"]["response"] == ""
    assert served.loop is not None
    since = served.on_loop(sup.clock)
    next_exchange = sup.wait_exchange("left", since, 1)
    assert asyncio.run_coroutine_threadsafe(next_exchange, served.loop).result(5)
    drive = served.rt.sims["b"].drives[1]
    assert drive.inputs & drive.layout.select_mask  # what the drive was told


@pytest.mark.wallclock
def test_a_flood_of_pipelined_requests_is_answered_in_order(served: Served) -> None:
    """2000 requests in one write: each answered, none lost, the order kept (they are
    spread over loop turns, a few at a time, and the reading pauses while they wait);
    a megabyte of blank lines is no request at all."""
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
        sock.settimeout(20)
        sock.connect(str(served.path))
        reader = sock.makefile("rb")
        sock.sendall(b"".join(request("alive", i) for i in range(2000)))
        ids = [json.loads(reader.readline())["id"] for _ in range(2000)]
        assert ids == list(range(2000))
        sock.sendall(b"\n" * (1 << 20) + request("hello", 2000))
        assert json.loads(reader.readline())["id"] == 2000


@pytest.mark.wallclock
def test_a_fault_of_ours_is_an_internal_error_and_the_connection_goes_on(
    served: Served, monkeypatch: pytest.MonkeyPatch
) -> None:
    server = served.servers[0]

    async def broken(client: Any, params: dict[str, Any]) -> Any:
        raise KeyError("a bug")

    monkeypatch.setitem(server._methods, "keys", broken)
    client = ControlClient(served.path)
    try:
        with pytest.raises(RunError, match="internal error"):
            client.call("keys")
        assert client.call("hello")["units"] == ["left", "right"]
    finally:
        client.close()


@pytest.mark.wallclock
def test_past_the_client_limit_a_client_is_told_why(served: Served) -> None:
    held = [socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) for _ in range(MAX_CLIENTS)]
    try:
        for sock in held:
            sock.connect(str(served.path))
        for _ in range(10_000):  # the service's own count: each look is a loop turn
            if served.on_loop(lambda: len(served.servers[0].clients)) == MAX_CLIENTS:
                break
        assert len(served.servers[0].clients) == MAX_CLIENTS
        with pytest.raises(RunError, match="refused this client: too many clients") as caught:
            ControlClient(served.path).call("state")
        assert f"at most {MAX_CLIENTS} at once" in str(caught.value)

        async def attach() -> None:
            link = await Link.open(served.path)
            try:
                with pytest.raises(LinkError, match="refused this client: too many"):
                    await link.call("hello")
                assert "too many clients" in await link.closed
            finally:
                await link.close()

        asyncio.run(attach())
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as raw:
            raw.settimeout(5)
            raw.connect(str(served.path))
            line = raw.makefile("rb").readline()
            assert json.loads(line)["error"]["code"] == rpc.REFUSED
            assert raw.recv(1) == b""  # then closed for writing: nothing more comes
    finally:
        for sock in held:
            sock.close()
    for _ in range(10_000):  # until the service has seen them leave
        if served.on_loop(lambda: len(served.servers[0].clients)) == 0:
            break
    client = ControlClient(served.path)  # once they left, clients are taken again
    try:
        assert client.call("hello")["protocol"] == rpc.PROTOCOL
    finally:
        client.close()


# ---------------------------------------------------------------- socket paths


def run(
    sock: Path, record: Path, *extra: str, timeout: float = 60
) -> subprocess.CompletedProcess[str]:
    cmd = [sys.executable, "-m", "abh3_supervisor", "run", "configs/demo.yaml", "--headless"]
    cmd += ["--duration", "1", "--status-interval", "0", "--record", str(record)]
    cmd += ["--socket", str(sock), *extra]
    return subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, timeout=timeout)


def frames(record: Path) -> int:
    return sum(1 for _ in can.LogReader(str(record))) if record.exists() else 0


def refused_before_any_frame(out: subprocess.CompletedProcess[str], record: Path) -> str:
    assert out.returncode == 2, out.stderr
    assert "Traceback" not in out.stderr
    assert frames(record) == 0  # nothing reached the bus: the path was checked first
    errors = [line for line in out.stderr.splitlines() if line.startswith("error: ")]
    assert len(errors) == 1, out.stderr
    return errors[0]


@pytest.mark.wallclock
def test_a_path_over_the_unix_limit_is_exit_2_before_the_first_frame(tmp_path: Path) -> None:
    long = Path(tempfile.mkdtemp(dir="/tmp")) / ("x" * 120 + ".sock")
    error = refused_before_any_frame(run(long, tmp_path / "r.log"), tmp_path / "r.log")
    assert "bytes; a Unix socket's may have at most 107" in error


@pytest.mark.wallclock
def test_a_missing_or_unwritable_directory_is_exit_2(tmp_path: Path) -> None:
    missing = tmp_path / "no" / "such" / "dir" / "s.sock"
    error = refused_before_any_frame(run(missing, tmp_path / "a.log"), tmp_path / "a.log")
    assert f"{tmp_path / 'no' / 'such'} does not exist" in error
    sysfs = Path("/sys/abh3-test.sock")  # a directory no user may create files in
    error = refused_before_any_frame(run(sysfs, tmp_path / "b.log"), tmp_path / "b.log")
    assert error.startswith(f"error: control socket {sysfs}: ")


@pytest.mark.wallclock
def test_a_shared_directory_is_refused_and_never_chmodded(tmp_path: Path) -> None:
    shared = Path(tempfile.mkdtemp(dir="/tmp"))
    os.chmod(shared, 0o1777)  # as /tmp itself
    error = refused_before_any_frame(run(shared / "x.sock", tmp_path / "r.log"), tmp_path / "r.log")
    assert "(mode 1777) is writable by other users" in error and "never chmodded" in error
    assert stat.S_IMODE(shared.stat().st_mode) == 0o1777
    assert not (shared / "x.sock").exists()


@pytest.mark.wallclock
@pytest.mark.skipif(os.geteuid() != 0, reason="only root can give a directory to another user")
def test_a_directory_of_another_user_is_refused_and_left_as_it_is(tmp_path: Path) -> None:
    theirs = Path(tempfile.mkdtemp(dir="/tmp"))
    os.chown(theirs, 65534, 65534)
    os.chmod(theirs, 0o755)
    error = refused_before_any_frame(run(theirs / "x.sock", tmp_path / "r.log"), tmp_path / "r.log")
    assert "belongs to user nobody, not to this user" in error
    info = theirs.stat()
    assert (info.st_uid, stat.S_IMODE(info.st_mode)) == (65534, 0o755)


@pytest.mark.wallclock
def test_a_private_directory_of_ours_is_used_as_it_is(tmp_path: Path) -> None:
    """One the supervisor did not make keeps its mode (0755: others may look, not write);
    the socket in it is owner-only from the moment it is bound."""
    ours = Path(tempfile.mkdtemp(dir="/tmp"))
    os.chmod(ours, 0o755)
    out = run(ours / "x.sock", tmp_path / "r.log")
    assert out.returncode == 0, out.stderr
    assert stat.S_IMODE(ours.stat().st_mode) == 0o755
    assert frames(tmp_path / "r.log") > 0
    assert f"serving the control socket {ours / 'x.sock'}" in out.stderr
