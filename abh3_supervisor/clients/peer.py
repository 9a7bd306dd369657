"""Who serves a control socket: a client talks only to a supervisor run by its own user
or by root, unless told to trust another user (``--trust-server-uid``).

A socket file proves nothing about who listens on it: another user who can make the
socket's directory theirs (a ``/tmp/abh3-<uid>`` made before ours, a symbolic link) can
serve a program of their own there, which could answer an e-stop with "done". The kernel
knows who listens: ``SO_PEERCRED`` on the connected socket gives the server's process,
user and group as they were when it called ``listen`` (Linux; elsewhere nothing is known
and nothing is refused). Root is trusted as a server: it could take over any socket of
ours anyway.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import pwd
import socket
import struct
from collections.abc import Iterable
from typing import Protocol

from abh3_supervisor.errors import RunError

TRUSTED: set[int] = set()  # --trust-server-uid, for this process
_CREDENTIALS = struct.Struct("3i")  # struct ucred: pid, uid, gid


class _Socket(Protocol):
    def getsockopt(self, level: int, option: int, size: int, /) -> bytes: ...


def trust(uids: Iterable[int]) -> None:
    TRUSTED.update(uids)


def credentials(sock: _Socket | None) -> tuple[int, int, int] | None:
    """The server's (pid, uid, gid), or None where the OS does not say."""
    option = getattr(socket, "SO_PEERCRED", None)
    if option is None or sock is None:
        return None
    try:
        data = sock.getsockopt(socket.SOL_SOCKET, option, _CREDENTIALS.size)
    except OSError:
        return None
    pid, uid, gid = _CREDENTIALS.unpack(data)
    return pid, uid, gid


def check(sock: _Socket | None, shown: object) -> None:
    """:class:`RunError` unless ``sock``'s server is this user, root or trusted."""
    found = credentials(sock)
    if found is None:
        return
    uid = found[1]
    if uid in (os.geteuid(), 0) or uid in TRUSTED:
        return
    raise RunError(
        f"{shown} is served by {user(uid)}, not by this user or root: refused (anyone can "
        "serve a socket in a directory they control); if that supervisor is meant to be "
        f"used from here, give --trust-server-uid {uid}"
    )


def user(uid: int) -> str:
    with contextlib.suppress(KeyError):
        return f"user {pwd.getpwuid(uid).pw_name} (uid {uid})"
    return f"uid {uid}"


def user_id(text: str) -> int:
    """``--trust-server-uid``: a number or a user name."""
    if text.isdigit():
        return int(text)
    try:
        return pwd.getpwnam(text).pw_uid
    except KeyError:
        raise argparse.ArgumentTypeError(f"no user {text!r}") from None


def add_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--trust-server-uid",
        type=user_id,
        action="append",
        default=[],
        metavar="UID",
        help="talk to a supervisor run by this user too (a number or a name; default: only "
        "this user's or root's)",
    )
