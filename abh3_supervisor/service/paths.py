"""Where the control socket lives and who may open it.

Default: ``$XDG_RUNTIME_DIR/abh3/<config name>.sock`` (systemd's per-user runtime
directory), else ``/tmp/abh3-<uid>/<config name>.sock``. The directory is ours alone
(0700; 0750 with a group) and the socket owner-only (0600; 0660 with a group), so another
user's process cannot connect. A directory that exists with other owners or wider rights
is refused rather than used.
"""

from __future__ import annotations

import grp
import os
import socket
import stat
from pathlib import Path

from abh3_supervisor.errors import RunError


def default_socket(config_file: str) -> Path:
    runtime = os.environ.get("XDG_RUNTIME_DIR")
    base = Path(runtime) / "abh3" if runtime and Path(runtime).is_dir() else None
    if base is None:
        base = Path("/tmp") / f"abh3-{os.getuid()}"
    return base / f"{Path(config_file).stem or 'abh3'}.sock"


def group_id(group: str | None) -> int | None:
    if group is None:
        return None
    try:
        return grp.getgrnam(group).gr_gid
    except KeyError:
        raise RunError(f"--socket-group {group}: no such group") from None


def prepare_directory(path: Path, gid: int | None) -> None:
    """Create the socket's directory, or check an existing one is ours and private."""
    directory = path.parent
    mode = 0o750 if gid is not None else 0o700
    try:
        directory.mkdir(mode=mode, parents=True, exist_ok=True)
        info = directory.stat()
    except OSError as exc:
        raise RunError(f"control socket {path}: cannot create {directory}: {exc}") from exc
    if info.st_uid != os.getuid():
        raise RunError(f"control socket {path}: {directory} belongs to another user")
    if gid is not None and info.st_gid != gid:
        os.chown(directory, -1, gid)
    os.chmod(directory, mode)


def remove_stale(path: Path) -> None:
    """A socket file left by a supervisor that died is removed; a live one is an error."""
    if not path.exists() and not path.is_symlink():
        return
    if not stat.S_ISSOCK(path.lstat().st_mode):
        raise RunError(f"control socket {path}: exists and is not a socket")
    probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        probe.settimeout(0.5)
        probe.connect(str(path))
    except OSError:
        path.unlink(missing_ok=True)  # nobody answers: left behind
        return
    finally:
        probe.close()
    raise RunError(
        f"control socket {path}: another supervisor is serving it "
        "(stop it first, or give this one --socket PATH)"
    )


def restrict(path: Path, gid: int | None) -> None:
    if gid is not None:
        os.chown(path, -1, gid)
    os.chmod(path, 0o660 if gid is not None else 0o600)
