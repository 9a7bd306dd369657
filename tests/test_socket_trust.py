"""Whose socket it is: the socket's directory is refused when it is a symbolic link or
another user's (judged without following links), and a client refuses a server run by
another user (root aside) unless told to trust it — the kernel says who listens."""

from __future__ import annotations

import asyncio
import json
import os
import shutil
import signal
import socket
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest

from abh3_supervisor.clients import control, peer
from abh3_supervisor.clients.control import ControlClient
from abh3_supervisor.clients.link import Link, LinkError
from abh3_supervisor.errors import Abh3Error, RunError
from abh3_supervisor.service import paths
from tests.support.cli import abh3

NOBODY = 65534
as_root = pytest.mark.skipif(os.geteuid() != 0, reason="only root can act as another user")


# ---------------------------------------------------------------- the directory


@pytest.mark.wallclock
def test_a_symlinked_socket_directory_is_refused_even_when_it_points_at_our_own(
    tmp_path: Path,
) -> None:
    """Another user's link in /tmp may point at a private directory of ours today and at
    one of theirs tomorrow: the link itself is refused, whatever it points at."""
    ours = Path(tempfile.mkdtemp(dir="/tmp"))  # private, ours: it would pass every check
    link = Path(tempfile.mkdtemp(dir="/tmp")) / "abh3-x"
    link.symlink_to(ours)
    with pytest.raises(Abh3Error, match="is a symbolic link"):
        paths.prepare_directory(link / "x.sock", None)
    record = tmp_path / "r.log"
    cmd = ["run", "configs/demo.yaml", "--headless", "--duration", "1", "--record", str(record)]
    out = abh3(*cmd, "--socket", str(link / "x.sock"))
    assert out.returncode == 2, out.stderr
    assert f"{link} is a symbolic link (to {ours}), not a directory" in out.stderr
    assert not record.exists() or record.stat().st_size == 0  # nothing reached the bus
    assert not (ours / "x.sock").exists()


@as_root
def test_the_fallback_directory_of_another_owner_is_refused(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """No $XDG_RUNTIME_DIR: /tmp/abh3-<uid>, made by someone else first, is theirs."""
    monkeypatch.delenv("XDG_RUNTIME_DIR")
    fallback = paths.default_socket("robot.yaml")
    assert fallback == Path(f"/tmp/abh3-{os.getuid()}/robot.sock")
    theirs = Path(tempfile.mkdtemp(dir="/tmp"))  # the same check, on a path of the test's
    os.chown(theirs, NOBODY, NOBODY)
    os.chmod(theirs, 0o700)
    with pytest.raises(Abh3Error, match="belongs to user nobody, not to this user"):
        paths.prepare_directory(theirs / "robot.sock", None)


def test_clients_do_not_look_for_supervisors_in_a_symlinked_default_directory(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    runtime = Path(tempfile.mkdtemp(dir="/tmp"))
    elsewhere = Path(tempfile.mkdtemp(dir="/tmp"))
    (runtime / "abh3").symlink_to(elsewhere)
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(runtime))
    with pytest.raises(RunError, match="is a symbolic link"):
        control.find_socket(None)


def test_nothing_served_in_the_default_place_names_one_served_in_the_fallback(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A supervisor started without $XDG_RUNTIME_DIR (cron) serves in /tmp/abh3-<uid>; a
    client of a shell that has it set looks there too before it says nobody serves."""
    runtime, fallback = Path(tempfile.mkdtemp(dir="/tmp")), Path(tempfile.mkdtemp(dir="/tmp"))
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(runtime))
    monkeypatch.setattr(control, "fallback_directory", lambda: fallback)
    with pytest.raises(RunError, match="give its socket with --connect PATH"):
        control.find_sockets(None)
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as listener:
        listener.bind(str(fallback / "demo.sock"))
        listener.listen(1)
        with pytest.raises(RunError) as told:
            control.find_sockets(None)
    assert str(told.value) == (
        f"no supervisor is serving in {runtime / 'abh3'}, but one is in {fallback} (started "
        f"without $XDG_RUNTIME_DIR): give --connect {fallback / 'demo.sock'}"
    )
    shutil.rmtree(runtime)
    shutil.rmtree(fallback)


# ---------------------------------------------------------------- who serves


@pytest.fixture
def foreign_server(tmp_path: Path) -> Iterator[Path]:
    """A socket bound here and served by a process of user nobody: it answers every line
    with a result that claims success (as a fake would answer an e-stop)."""
    path = Path(tempfile.mkdtemp(dir="/tmp")) / "fake.sock"
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    listener.bind(str(path))
    ready_r, ready_w = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child: nobody from here on, listening (the kernel notes who)
        try:
            os.setgid(NOBODY)
            os.setuid(NOBODY)
            listener.listen(4)
            os.write(ready_w, b"x")
            while True:
                conn, _ = listener.accept()
                with conn, conn.makefile("rb") as lines:
                    for line in lines:
                        rid = json.loads(line).get("id")
                        result = {"ok": True, "protocol": 1, "estop": True}
                        conn.sendall(json.dumps({"jsonrpc": "2.0", "id": rid, "result": result}).encode() + b"\n")  # fmt: skip
        finally:
            os._exit(0)
    listener.close()
    os.close(ready_w)
    assert os.read(ready_r, 1) == b"x"
    os.close(ready_r)
    try:
        yield path
    finally:
        os.kill(pid, signal.SIGKILL)
        os.waitpid(pid, 0)
        peer.TRUSTED.clear()
        shutil.rmtree(path.parent, ignore_errors=True)


@pytest.mark.wallclock
@as_root
def test_a_server_of_another_user_is_refused_before_a_word_is_sent(foreign_server: Path) -> None:
    with pytest.raises(RunError, match="is served by user nobody \\(uid 65534\\)") as refused:
        ControlClient(foreign_server)
    assert "--trust-server-uid 65534" in str(refused.value)

    async def attach() -> None:
        await Link.open(foreign_server)

    with pytest.raises(LinkError, match="is served by user nobody"):
        asyncio.run(attach())
    out = abh3("estop", "--connect", str(foreign_server))  # a fake "done" is never heard
    assert out.returncode == 1 and "EMERGENCY STOP" not in out.stdout, out.stdout
    assert "is served by user nobody (uid 65534), not by this user or root: refused" in out.stderr


@pytest.mark.wallclock
@as_root
def test_a_server_of_a_trusted_user_is_talked_to(foreign_server: Path) -> None:
    peer.trust([NOBODY])
    client = ControlClient(foreign_server)
    try:
        assert client.call("hello")["protocol"] == 1
    finally:
        client.close()
    out = abh3("status", "--json", "--connect", str(foreign_server), "--trust-server-uid", "nobody")
    assert "is served by" not in out.stderr and json.loads(out.stdout)["estop"] is True


def test_our_own_and_roots_servers_are_trusted() -> None:
    a, b = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
    with a, b:
        found = peer.credentials(a)
        assert found is not None and found[:2] == (os.getpid(), os.geteuid())
        peer.check(a, "pair")  # ours: no error
