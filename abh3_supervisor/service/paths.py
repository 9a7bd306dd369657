"""Where the control socket lives and who may open it.

Default: ``$XDG_RUNTIME_DIR/abh3/<config name>.sock`` (systemd's per-user runtime
directory: private, on a tmpfs, emptied at logout), else ``/tmp/abh3-<uid>/<config
name>.sock``. The socket's directory is what keeps other users out, so it must be private:
one this process creates is made 0700 (0750 with a group); one that already exists is
used as it is — never chmodded, it may be someone's /tmp — and refused, with the reason,
when another user owns it or anyone but its owner may write in it (a shared directory
such as /tmp, mode 1777, where anyone could replace the socket). The socket itself is
owner-only (0600; 0660 with a group) from the moment it is bound.

Everything that can fail about a path is found by :func:`bind`, before any drive is
commanded: a mistake in the path is exit 2 (:class:`Abh3Error`), another supervisor
already serving it is exit 1 (:class:`RunError`).
"""

from __future__ import annotations

import contextlib
import errno
import grp
import os
import pwd
import socket
import stat
from pathlib import Path

from abh3_supervisor.errors import Abh3Error, RunError

MAX_PATH_BYTES = 107  # sockaddr_un.sun_path holds 108 bytes with the terminating NUL


def fallback_directory() -> Path:
    """Where sockets go without a usable ``$XDG_RUNTIME_DIR`` (cron, a bare ``su``)."""
    return Path("/tmp") / f"abh3-{os.getuid()}"


def default_socket(config_file: str) -> Path:
    runtime = os.environ.get("XDG_RUNTIME_DIR")
    base = Path(runtime) / "abh3" if runtime and Path(runtime).is_dir() else None
    if base is None:
        base = fallback_directory()
    return base / f"{Path(config_file).stem or 'abh3'}.sock"


def group_id(group: str | None) -> int | None:
    if group is None:
        return None
    try:
        return grp.getgrnam(group).gr_gid
    except KeyError:
        raise Abh3Error(f"--socket-group {group}: no such group") from None


def bind(path: Path, gid: int | None) -> socket.socket:
    """The control socket bound at ``path`` (not yet listening: until the service starts,
    a client is told nobody serves), in a directory checked or made private."""
    size = len(os.fsencode(path))
    if size > MAX_PATH_BYTES:
        raise Abh3Error(
            f"control socket {path}: the path is {size} bytes; a Unix socket's may have at "
            f"most {MAX_PATH_BYTES}: give a shorter --socket PATH"
        )
    prepare_directory(path, gid)
    remove_stale(path)
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    # bound owner-only at once: no moment in which the socket is open to others
    saved = os.umask(0o117 if gid is not None else 0o177)
    try:
        sock.bind(str(path))
    except OSError as exc:
        sock.close()
        raise Abh3Error(f"control socket {path}: cannot serve there: {exc.strerror}") from None
    finally:
        os.umask(saved)
    try:
        restrict(path, gid)
    except OSError as exc:
        sock.close()
        path.unlink(missing_ok=True)
        raise Abh3Error(f"control socket {path}: cannot set its permissions: {exc}") from None
    return sock


def prepare_directory(path: Path, gid: int | None) -> None:
    """Create the socket's directory private, or check that an existing one is private."""
    directory = path.parent
    mode = 0o750 if gid is not None else 0o700
    try:
        directory.mkdir(mode=mode)
    except FileExistsError:
        _check_existing(path, gid)
        return
    except FileNotFoundError:
        raise Abh3Error(
            f"control socket {path}: {directory.parent} does not exist (only the socket's "
            "own directory is created)"
        ) from None
    except OSError as exc:
        raise Abh3Error(
            f"control socket {path}: cannot create {directory}: {exc.strerror}"
        ) from None
    try:  # ours: made exactly as meant, whatever the umask
        if gid is not None:
            os.chown(directory, -1, gid)
        os.chmod(directory, mode)
    except OSError as exc:
        raise Abh3Error(f"control socket {path}: cannot make {directory} private: {exc}") from None


def _check_existing(path: Path, gid: int | None) -> None:
    directory = path.parent
    problem = foreign(directory)
    if problem is not None:
        where = "put it in a directory of your own, or leave out --socket for the default"
        raise Abh3Error(f"control socket {path}: {problem}: {where}")
    info = directory.stat()
    mode = stat.S_IMODE(info.st_mode)
    if gid is not None and (info.st_gid != gid or not mode & 0o010):
        raise Abh3Error(
            f"control socket {path}: --socket-group members cannot reach it in {directory} "
            f"(group {_group(info.st_gid)}, mode {mode:04o}): give that directory the group and "
            "mode 0750, or a --socket in a directory that does not exist yet"
        )


def foreign(directory: Path) -> str | None:
    """Why ``directory`` cannot be trusted to hold a socket, or None: a symbolic link (the
    link itself is judged, never what it points to — another user's link in /tmp could
    point at a directory of ours now and at one of theirs later), not a directory, another
    user's, or writable by others. Opened with ``O_NOFOLLOW`` and judged by ``fstat`` of
    what was opened, so no link can slip in between looking and judging."""
    try:
        fd = os.open(directory, os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW)
    except OSError as exc:
        if exc.errno in (errno.ELOOP, errno.ENOTDIR) and directory.is_symlink():
            return f"{directory} is a symbolic link (to {os.readlink(directory)}), not a directory"
        if exc.errno == errno.ENOTDIR:
            return f"{directory} is not a directory"
        return f"{directory}: {exc.strerror}"
    try:
        info = os.fstat(fd)
    finally:
        os.close(fd)
    if info.st_uid != os.geteuid():
        return f"{directory} belongs to {_user(info.st_uid)}, not to this user"
    mode = stat.S_IMODE(info.st_mode)
    if mode & 0o022:
        return (
            f"{directory} (mode {mode:04o}) is writable by other users, who could replace the "
            "socket (it is never chmodded)"
        )
    return None


def _user(uid: int) -> str:
    with contextlib.suppress(KeyError):
        return f"user {pwd.getpwuid(uid).pw_name}"
    return f"uid {uid}"


def _group(gid: int) -> str:
    with contextlib.suppress(KeyError):
        return grp.getgrgid(gid).gr_name
    return str(gid)


def served(path: Path, timeout: float = 0.5) -> bool:
    """Someone answers there (a supervisor killed with SIGKILL leaves its socket file)."""
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as probe:
        probe.settimeout(timeout)
        try:
            probe.connect(str(path))
        except OSError:
            return False
    return True


def remove_stale(path: Path) -> None:
    """A socket file left by a supervisor that died is removed; a live one is an error."""
    if not path.exists() and not path.is_symlink():
        return
    if not stat.S_ISSOCK(path.lstat().st_mode):
        raise Abh3Error(f"control socket {path}: exists and is not a socket")
    if not served(path):
        path.unlink(missing_ok=True)  # nobody answers: left behind
        return
    raise RunError(
        f"control socket {path}: another supervisor is serving it "
        "(stop it first, or give this one --socket PATH)"
    )


def restrict(path: Path, gid: int | None) -> None:
    if gid is not None:
        os.chown(path, -1, gid)
    os.chmod(path, 0o660 if gid is not None else 0o600)
