"""``--connect ssh://[user@]host[:port]/path/to.sock``: a supervisor on another machine,
reached through SSH — the operator's existing, trusted channel. There is no network
protocol of ours and no listener in the supervisor: the client starts OpenSSH's own
Unix-socket forwarding (``ssh -N -L LOCAL.sock:REMOTE.sock``) for the one connection it
makes, and the supervisor sees one more local client, with the rights of the SSH login.

The local end is a socket in a private directory (0700, made for it) that exists only
until the client has connected: the directory is removed at once, so no other process
can use the forwarding and nothing is left on disk, whatever way the client ends. ssh
runs with ``BatchMode`` (keys or an agent, never a password prompt), ``ExitOnForwardFailure``,
and no connection sharing; it tells us the forwarding listens through ``LocalCommand``
(run by ssh once its forwardings are set up), it is ended when the client closes, and —
through ``setpriv --pdeathsig`` where util-linux has it — also when the client dies
without closing (``kill -9``). Its messages become one line saying what went wrong:
the host cannot be reached, the login was refused, the remote socket is missing.

``ABH3_SSH`` replaces the ``ssh`` command (split like a shell would, e.g.
``ABH3_SSH="ssh -F ~/robot/ssh_config"``), as ``GIT_SSH_COMMAND`` does for git; everything
else — keys, known hosts, ``ProxyJump`` — comes from the user's ssh configuration.
"""

from __future__ import annotations

import contextlib
import os
import select
import shlex
import shutil
import signal
import subprocess
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import IO
from urllib.parse import unquote, urlsplit

from abh3_supervisor.errors import Abh3Error, RunError

SCHEME = "ssh://"
READY = "abh3-ssh-forwarding-ready"
READY_TIMEOUT_S = 30.0  # ConnectTimeout (10 s) and the login fit well inside
STOP_S = 2.0
OPTIONS = (
    "BatchMode=yes",  # never a prompt nobody would see: keys or an agent
    "ExitOnForwardFailure=yes",
    "ConnectTimeout=10",
    "ServerAliveInterval=5",  # a network gone ends the link within ~15 s (the TUI says so)
    "ServerAliveCountMax=3",
    "ControlMaster=no",  # a connection of its own: a shared master would not run LocalCommand
    "ControlPath=none",
    "RemoteCommand=none",
    "StreamLocalBindMask=0177",
    "PermitLocalCommand=yes",
    f"LocalCommand=echo {READY}",
)


@dataclass(frozen=True)
class SshTarget:
    """A control socket on another host, as ``ssh://[user@]host[:port]/path``."""

    host: str
    path: str
    user: str | None = None
    port: int | None = None

    def __str__(self) -> str:
        user = f"{self.user}@" if self.user else ""
        host = f"[{self.host}]" if ":" in self.host else self.host
        port = f":{self.port}" if self.port else ""
        return f"{SCHEME}{user}{host}{port}{self.path}"

    @property
    def login(self) -> str:
        return f"{self.user}@{self.host}" if self.user else self.host


Endpoint = Path | SshTarget  # where a client connects: a local socket, or one over SSH


def parse_target(text: str) -> SshTarget:
    """``ssh://[user@]host[:port]/absolute/path.sock``; :class:`Abh3Error` says what is
    wrong with it."""
    try:
        parts = urlsplit(text)
        port = parts.port
    except ValueError as exc:
        raise Abh3Error(f"{text}: {exc}") from None
    host, path = parts.hostname or "", unquote(parts.path)
    example = "ssh://[user@]host[:port]/path/to.sock"
    if not host or host.startswith("-"):
        raise Abh3Error(f"{text}: no host (expected {example})")
    if parts.query or parts.fragment or parts.password is not None:
        raise Abh3Error(f"{text}: only {example}")
    if not path.startswith("/") or path == "/":
        raise Abh3Error(f"{text}: give the socket's absolute path on {host} ({example})")
    if any(c in path for c in ":%") or not path.isprintable():
        # ssh's -L syntax splits at ':' and expands '%' tokens in socket paths
        raise Abh3Error(f"{text}: ssh cannot forward a path with ':', '%' or control characters")
    return SshTarget(host, path, unquote(parts.username) if parts.username else None, port)


def endpoint(text: str) -> Endpoint:
    """The ``--connect`` argument type: a local socket path or an ``ssh://`` target."""
    import argparse

    if not text.startswith(SCHEME):
        return Path(text)
    try:
        return parse_target(text)
    except Abh3Error as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


class Tunnel:
    """``ssh -N -L`` for one connection: :meth:`start`, :meth:`wait_ready` (the local
    socket's path), connect, :meth:`forget_path`, and :meth:`close` at the end;
    :meth:`explain` turns what ssh said into one line when the connection fails."""

    def __init__(self, target: SshTarget) -> None:
        self.target = target
        self.proc: subprocess.Popen[bytes] | None = None
        self._dir: Path | None = None
        # what ssh says; kept past its end, closed with the tunnel
        self._errors: IO[bytes] = tempfile.TemporaryFile()  # noqa: SIM115

    def start(self) -> None:
        """Start ssh (on the thread that stays: the parent-death signal follows it)."""
        runtime = os.environ.get("XDG_RUNTIME_DIR")
        base = runtime if runtime and os.path.isdir(runtime) else None
        self._dir = Path(tempfile.mkdtemp(prefix="abh3-ssh-", dir=base))  # 0700, ours
        local = self._dir / "s.sock"
        command = shlex.split(os.environ.get("ABH3_SSH", "ssh")) or ["ssh"]
        if shutil.which(command[0]) is None:
            self.close()
            raise RunError(
                f"{self.target}: {command[0]} not found: SSH connections need OpenSSH's "
                "client (apt-get install openssh-client)"
            )
        guard = ["setpriv", "--pdeathsig", "TERM", "--"] if shutil.which("setpriv") else []
        args = [*guard, *command, "-N", "-T", "-x", "-a"]
        for option in OPTIONS:
            args += ["-o", option]
        args += ["-L", f"{local}:{self.target.path}"]
        args += ["-p", str(self.target.port)] if self.target.port else []
        args += ["-l", self.target.user] if self.target.user else []
        try:
            self.proc = subprocess.Popen(
                [*args, "--", self.target.host],
                stdin=subprocess.DEVNULL,
                stdout=subprocess.PIPE,
                stderr=self._errors,
                start_new_session=True,  # the terminal's Ctrl-C is ours: we end it ourselves
                env={**os.environ, "SHELL": "/bin/sh"},  # LocalCommand runs with $SHELL
            )
        except OSError as exc:
            self.close()
            raise RunError(f"{self.target}: cannot start {command[0]}: {exc.strerror}") from None

    def wait_ready(self) -> Path:
        """Until ssh listens on the local socket (its path), or why it could not."""
        assert self.proc is not None and self.proc.stdout is not None and self._dir is not None
        deadline = time.monotonic() + READY_TIMEOUT_S
        out = self.proc.stdout
        while (left := deadline - time.monotonic()) > 0:
            ready, _, _ = select.select([out], [], [], left)
            if not ready:
                break
            line = out.readline()
            if not line:  # ssh ended: it said why on stderr
                self.proc.wait()
                raise RunError(self.explain() or f"{self.target}: ssh ended without a word")
            if line.strip() == READY.encode():
                return self._dir / "s.sock"
        raise RunError(f"{self.target}: ssh did not connect within {READY_TIMEOUT_S:g} s")

    def forget_path(self) -> None:
        """Connected: the local socket and its directory go (the connection stays)."""
        if self._dir is not None:
            shutil.rmtree(self._dir, ignore_errors=True)
            self._dir = None

    def explain(self) -> str | None:
        """What went wrong, from ssh's own words, in one line (None: it said nothing)."""
        with contextlib.suppress(OSError, ValueError):
            self._errors.seek(0)
            said = self._errors.read().decode(errors="replace")
            lines = [ln.strip() for ln in said.splitlines() if ln.strip()]
            if lines:
                return f"{self.target}: {_meaning(lines, self.target)}"
        return None

    def close(self) -> None:
        """ssh ended (asked, then made to), the local directory removed. Idempotent."""
        proc, self.proc = self.proc, None
        if proc is not None:
            if proc.poll() is None:
                with contextlib.suppress(ProcessLookupError):
                    proc.send_signal(signal.SIGTERM)
                try:
                    proc.wait(STOP_S)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()
            if proc.stdout is not None:
                proc.stdout.close()
        self.forget_path()
        self._errors.close()


# what ssh says (LogLevel ERROR), and what it means for someone attaching
_UNREACHABLE = (
    "Could not resolve hostname",
    "Connection refused",
    "Connection timed out",
    "No route to host",
    "Network is unreachable",
    "Connection closed by",
    "Connection reset by",
    "Timeout, server",
)


def _meaning(lines: list[str], target: SshTarget) -> str:
    text = " ".join(lines)
    for line in lines:
        if "open failed" in line:  # the channel to the remote socket
            why = line.split("open failed:", 1)[1].strip()
            if "prohibited" in why:
                return (
                    f"the SSH server on {target.host} does not forward to Unix sockets "
                    "(sshd_config: AllowStreamLocalForwarding, DisableForwarding)"
                )
            why = why.removeprefix("connect failed:").strip()
            # sshd does not say why it could not connect (its log does): both causes
            return (
                f"cannot open {target.path} on {target.host} (ssh: {why}): no supervisor "
                f"serves it, or {target.login} may not use it (the socket is its owner's "
                "and its --socket-group's)"
            )
    if "Host key verification failed" in text or "HOST IDENTIFICATION HAS CHANGED" in text:
        return (
            f"{target.host}'s host key is unknown or has changed: check it with a plain "
            f"`ssh {target.login}` first (it is never accepted unasked)"
        )
    if "Permission denied" in text:
        line = next(ln for ln in lines if "Permission denied" in ln)
        reason = line[line.index("Permission denied") :].rstrip(".")
        return (
            f"{target.login}: login refused ({reason}): a key or an agent is needed, "
            "passwords cannot be asked (BatchMode)"
        )
    for line in lines:
        if any(sign in line for sign in _UNREACHABLE):
            return f"cannot reach {target.host}: {line.removeprefix('ssh: ')}"
    return f"ssh: {lines[-1].removeprefix('ssh: ')}"
