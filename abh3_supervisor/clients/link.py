"""An asyncio connection to the control socket, for clients that live on an event loop
(the TUI): requests with their replies, notifications to a callback, and one future that
says when and why the connection ended — a service that dies is seen at once. The socket
is local, or on another host through SSH (``ssh://…``, :mod:`.ssh`: the tunnel lives as
long as the link).

While connected it proves it is alive: the service drops the motion of a client that
holds motion and has not said ``alive`` for 0.5 s. The notification is sent from the
client's own event loop, so a client that hangs or is stopped (SIGSTOP) stops proving.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import json
import socket
from collections.abc import Callable
from pathlib import Path
from typing import Any

from abh3_supervisor.clients import peer
from abh3_supervisor.clients.ssh import Endpoint, Tunnel
from abh3_supervisor.errors import RunError
from abh3_supervisor.service import protocol as rpc

Notified = Callable[[str, dict[str, Any]], None]
ALIVE_S = 0.2  # the service wants proof every 0.5 s: this leaves room for a late tick
ALIVE = rpc.encode({"jsonrpc": "2.0", "method": "alive"})  # a notification: no reply


class LinkError(RunError):
    """The service refused a request (its message says why) or the connection is gone."""


class LinkLost(LinkError):
    """The connection is gone: a request had no answer, and may or may not have acted."""


class Link:
    def __init__(
        self,
        path: Endpoint,
        reader: asyncio.StreamReader,
        writer: asyncio.StreamWriter,
        tunnel: Tunnel | None = None,
    ) -> None:
        self.path, self.reader, self.writer, self.tunnel = path, reader, writer, tunnel
        self.on_notification: Notified = lambda method, params: None
        self.closed: asyncio.Future[str] = asyncio.get_running_loop().create_future()
        self._ids = itertools.count(1)
        self._pending: dict[int, asyncio.Future[Any]] = {}
        self._task = asyncio.ensure_future(self._read())
        self._alive = asyncio.ensure_future(self._prove_alive())

    @classmethod
    async def open(cls, path: Endpoint, timeout: float = 5.0) -> Link:
        tunnel = None
        local = path
        if not isinstance(path, Path):
            tunnel = Tunnel(path)
            try:
                tunnel.start()  # on this thread: ssh's parent-death signal follows it
                local = await asyncio.to_thread(tunnel.wait_ready)
            except BaseException:
                tunnel.close()
                raise
        try:
            reader, writer = await asyncio.wait_for(
                asyncio.open_unix_connection(str(local), limit=rpc.MAX_LINE * 64), timeout
            )
        except (FileNotFoundError, ConnectionRefusedError):
            if tunnel is not None:
                tunnel.close()
            raise LinkError(
                f"no supervisor serves {path} (is `abh3 run CONFIG --headless` running? "
                "give its socket with --connect PATH)"
            ) from None
        except (OSError, TimeoutError) as exc:
            if tunnel is not None:
                tunnel.close()
            raise LinkError(f"cannot connect to {path}: {exc}") from None
        try:
            peer.check(writer.get_extra_info("socket"), path)  # who listens, before a word
        except RunError as exc:
            writer.close()
            if tunnel is not None:
                tunnel.close()
            raise LinkError(str(exc)) from None
        if tunnel is not None:
            tunnel.forget_path()
        return cls(path, reader, writer, tunnel)

    async def call(self, method: str, **params: Any) -> Any:
        """Send a request and wait for its reply; :class:`LinkError` on an error reply."""
        if self.closed.done():
            raise LinkLost(f"not connected: {self.closed.result()}")
        rid = next(self._ids)
        reply = asyncio.get_running_loop().create_future()
        self._pending[rid] = reply
        message = {"jsonrpc": "2.0", "id": rid, "method": method, "params": params}
        try:
            self.writer.write(rpc.encode(message))
            return await reply
        finally:
            self._pending.pop(rid, None)

    async def _prove_alive(self) -> None:
        while not self.closed.done() and not self.writer.is_closing():
            self.writer.write(ALIVE)
            await asyncio.sleep(ALIVE_S)

    def detach_now(self) -> None:
        """Shut the connection down at once, from any thread or a signal handler: the
        service sees this client leave even if this process's event loop never runs
        again (a terminal gone can block it). :meth:`close` still tidies up."""
        sock = self.writer.get_extra_info("socket")
        if sock is not None:
            with contextlib.suppress(OSError):
                sock.shutdown(socket.SHUT_RDWR)

    async def _read(self) -> None:
        reason = "the supervisor closed the connection"
        try:
            while line := await self.reader.readline():
                self._dispatch(json.loads(line))
        except (OSError, ValueError) as exc:
            reason = f"the connection broke: {exc}"
        finally:
            if self.tunnel is not None:  # through SSH: ssh may know better
                reason = self.tunnel.explain() or reason
            for reply in self._pending.values():
                if not reply.done():
                    reply.set_exception(LinkLost(f"{self.path}: {reason}"))
            if not self.closed.done():
                self.closed.set_result(reason)

    def _dispatch(self, message: dict[str, Any]) -> None:
        if "method" in message:
            params = message.get("params")
            if message["method"] == "bye" and isinstance(params, dict) and not self.closed.done():
                self.closed.set_result(str(params.get("reason", "bye")))
            self.on_notification(message["method"], params if isinstance(params, dict) else {})
            return
        if message.get("id") is None and "error" in message:  # refused: it says why
            self._refused(str(message["error"].get("message")))
            return
        reply = self._pending.get(message.get("id", -1))
        if reply is None or reply.done():
            return
        if "error" in message:
            reply.set_exception(LinkError(str(message["error"].get("message"))))
        else:
            reply.set_result(message.get("result"))

    def _refused(self, why: str) -> None:
        reason = f"{self.path}: the supervisor refused this client: {why}"
        for reply in self._pending.values():
            if not reply.done():
                reply.set_exception(LinkError(reason))
        if not self.closed.done():
            self.closed.set_result(reason)

    async def close(self) -> None:
        for task in (self._alive, self._task):
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await task
        self.writer.close()
        with contextlib.suppress(Exception):
            await self.writer.wait_closed()
        if self.tunnel is not None:
            await asyncio.to_thread(self.tunnel.close)
