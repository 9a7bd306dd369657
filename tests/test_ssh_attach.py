"""Attaching from another machine through SSH: `abh3 status`, `send`, `param` and `tui
--connect ssh://user@host:port/path.sock` against an OpenSSH server this test starts on
127.0.0.1 only (its own host key, client key and authorized_keys in a temporary
directory; the client's options through ``ABH3_SSH``). Errors — the host unreachable, the
login refused, the remote socket missing — are one line each and a non-zero exit.

Needs Debian's openssh-server (`.ci/run` installs it): skipped without it, except in CI
(``CI=true``), where its absence fails the test with the reason.
"""

from __future__ import annotations

import contextlib
import getpass
import os
import select
import shutil
import signal
import socket
import subprocess
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from abh3_supervisor.protocol import flags
from benchmarks.bursts import recorded_run
from tests.support import cli
from tests.support.safe_word import commands_to
from tests.support.terminal import in_a_terminal

pytestmark = pytest.mark.wallclock  # real time: runtimes, sockets, processes

ROOT = Path(__file__).resolve().parent.parent
SBIN = os.pathsep.join([os.environ.get("PATH", ""), "/usr/sbin", "/sbin"])


@dataclass
class Sshd:
    port: int
    user: str
    ssh_config: Path  # the client's: key, known hosts
    wrong_config: Path  # the same with a key the server does not know


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port: int = probe.getsockname()[1]
        return port


def _keygen(path: Path) -> None:
    subprocess.run(
        ["ssh-keygen", "-q", "-t", "ed25519", "-N", "", "-f", str(path)], check=True, timeout=30
    )


@pytest.fixture(scope="module")
def sshd() -> Iterator[Sshd]:
    exe = shutil.which("sshd", path=SBIN)
    missing = [n for n, p in (("sshd", exe), ("ssh", shutil.which("ssh"))) if p is None]
    if missing:
        why = f"{' and '.join(missing)} not installed (apt-get install openssh-server)"
        if os.environ.get("CI", "").lower() in ("1", "true", "yes"):  # as test_ros2_real
            pytest.fail(f"the SSH tests cannot run in CI: {why}", pytrace=False)
        pytest.skip(why)
    assert exe is not None
    if os.geteuid() == 0:
        os.makedirs("/run/sshd", mode=0o755, exist_ok=True)  # sshd's privilege separation
    with tempfile.TemporaryDirectory(dir="/tmp") as tmp:
        d = Path(tmp)
        for name in ("host_key", "client_key", "wrong_key"):
            _keygen(d / name)
        shutil.copy(d / "client_key.pub", d / "authorized_keys")
        port = _free_port()
        (d / "sshd_config").write_text(
            f"Port {port}\nListenAddress 127.0.0.1\nHostKey {d}/host_key\n"
            f"AuthorizedKeysFile {d}/authorized_keys\nPidFile none\nUsePAM no\n"
            "StrictModes no\nPasswordAuthentication no\nKbdInteractiveAuthentication no\n"
            "PermitRootLogin prohibit-password\nAllowStreamLocalForwarding yes\n"
        )
        host_key = (d / "host_key.pub").read_text().split()[:2]
        (d / "known_hosts").write_text(f"[127.0.0.1]:{port} {' '.join(host_key)}\n")
        for name, key in (("ssh_config", "client_key"), ("wrong_config", "wrong_key")):
            (d / name).write_text(
                f"Host *\n  IdentityFile {d}/{key}\n  IdentitiesOnly yes\n"
                f"  UserKnownHostsFile {d}/known_hosts\n  GlobalKnownHostsFile /dev/null\n"
                "  StrictHostKeyChecking yes\n"
            )
        server = subprocess.Popen(
            [exe, "-D", "-e", "-f", str(d / "sshd_config")],
            stderr=subprocess.PIPE,
            text=True,
        )
        assert server.stderr is not None
        try:
            ready, _, _ = select.select([server.stderr], [], [], 30)
            line = server.stderr.readline() if ready else ""
            assert f"listening on 127.0.0.1 port {port}" in line, line
            yield Sshd(port, getpass.getuser(), d / "ssh_config", d / "wrong_config")
        finally:
            server.terminate()
            server.wait(10)


def abh3(sshd: Sshd, *args: str, config: Path | None = None) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "ABH3_SSH": f"ssh -F {config or sshd.ssh_config}"}
    return cli.abh3(*args, env=env)


def url(sshd: Sshd, path: Path | str, port: int | None = None) -> str:
    return f"ssh://{sshd.user}@127.0.0.1:{port or sshd.port}{path}"


def one_error_line(out: subprocess.CompletedProcess[str]) -> str:
    assert out.returncode == 1, out.stderr
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ssh://"), out.stderr
    return lines[0]


def test_status_send_and_param_through_ssh(sshd: Sshd) -> None:
    with tempfile.TemporaryDirectory(dir="/tmp") as tmp:
        with recorded_run(Path(tmp)) as (sock, record):
            remote = url(sshd, sock)
            status = abh3(sshd, "status", "--connect", remote)
            assert status.returncode == 0, status.stderr
            assert status.stdout.startswith("left: online")
            sent = abh3(sshd, "send", "SELECT 3 3", "--unit", "left", "--connect", remote)
            assert (sent.returncode, sent.stdout) == (0, "''\n"), sent.stderr
            identity = abh3(sshd, "param", "--connect", remote, "identity", "left")
            assert identity.returncode == 0, identity.stderr
            assert "FIRMWARE_VERSION   2.3.0.1" in identity.stdout
            assert not list(Path(os.environ["XDG_RUNTIME_DIR"]).glob("abh3-ssh-*"))
        # what the drive was told: SELECT 3 3 on its DP0 commands, sent through SSH
        layout = flags.LAYOUT_2021
        selects = [layout.data_select(c.inputs) for c in commands_to(record, 1, layout.generation)]
        assert selects[0] != (3, 3) and selects[-1] == (3, 3)  # the stop keeps data select


def test_what_went_wrong_is_one_line(sshd: Sshd, tmp_path: Path) -> None:
    missing = one_error_line(abh3(sshd, "status", "--connect", url(sshd, "/tmp/abh3-none.sock")))
    assert "cannot open /tmp/abh3-none.sock on 127.0.0.1" in missing
    assert "no supervisor serves it" in missing
    refused = one_error_line(
        abh3(sshd, "status", "--connect", url(sshd, "/tmp/x.sock"), config=sshd.wrong_config)
    )
    assert f"{sshd.user}@127.0.0.1: login refused (Permission denied (publickey))" in refused
    unreachable = one_error_line(
        abh3(sshd, "status", "--connect", url(sshd, "/tmp/x.sock", port=_free_port()))
    )
    assert "cannot reach 127.0.0.1: connect to host 127.0.0.1 port" in unreachable
    assert "Connection refused" in unreachable
    bad = abh3(sshd, "send", "SELECT 1 1", "--all", "--connect", "ssh://127.0.0.1:22")
    assert bad.returncode == 2 and "give the socket's absolute path" in bad.stderr


def _ssh_for(remote: str) -> list[int]:
    """The ssh processes forwarding to ``remote`` (whoever started them)."""
    found = []
    for proc in Path("/proc").iterdir():
        with contextlib.suppress(OSError):
            args = (proc / "cmdline").read_bytes().split(b"\0")
            if proc.name.isdigit() and any(a.endswith(f":{remote}".encode()) for a in args):
                found.append(int(proc.name))
    return found


def test_the_tui_through_ssh_and_its_ssh_gone_with_it(sshd: Sshd) -> None:
    """The TUI attaches through SSH and shows the drives; `kill -9` of the TUI takes its
    ssh with it (parent-death signal); the next client attaches as before."""
    with tempfile.TemporaryDirectory(dir="/tmp") as tmp, recorded_run(Path(tmp)) as (sock, _):
        os.environ["ABH3_SSH"] = f"ssh -F {sshd.ssh_config}"  # the pty child's
        try:
            pid, fd = in_a_terminal(["tui", "--connect", url(sshd, sock)])
        finally:
            del os.environ["ABH3_SSH"]
        assert _ssh_for(str(sock)), "no ssh forwarding to the socket"
        os.kill(pid, signal.SIGKILL)
        os.waitpid(pid, 0)
        os.close(fd)
        deadline = time.monotonic() + 10
        while _ssh_for(str(sock)):  # polling other processes: nothing to wait on
            assert time.monotonic() < deadline, "ssh outlived the TUI"
            select.select([], [], [], 0.05)
        status = abh3(sshd, "status", "--json", "--connect", str(sock))
        assert status.returncode == 0, status.stderr
