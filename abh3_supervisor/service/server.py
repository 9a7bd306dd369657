"""The local control endpoint: a Unix socket serving the protocol of :mod:`.protocol`.

It runs on the runtime's event loop and never blocks it: requests are handled as they
come, every reply and notification is queued to the client's socket, and a client that
stops reading (its buffer passes ``MAX_BUFFER``) is disconnected rather than waited for.
Each client's motion is owned by an input source of its own in the usual arbitration:
streamed motion (twist, velocity, current) is fresh for ``CLIENT_TIMEOUT_S`` after each
request; a command-language ``VEL``/``CUR`` holds while the client proves it is alive —
any line from it, ``alive`` at the least, every ``CLIENT_TIMEOUT_S`` — and leaving,
dying or going quiet lets go at once (docs/architecture.md, "who owns motion"). Switches,
e-stop and clear act at once. A read-only listener answers only what changes nothing
(``READ_ONLY_METHODS``).

No client can take the socket down or hold up the loop: whatever a line holds is answered
with a JSON-RPC error (a fault of ours while answering too: ``INTERNAL_ERROR``, logged),
and the connection goes on; accepting, refusing and answering are bounded per loop turn
(:mod:`.accepting`).
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import itertools
import logging
import math
import re
import socket
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from abh3_supervisor import __version__
from abh3_supervisor.config.model import ControlMode, Role
from abh3_supervisor.core import verifying
from abh3_supervisor.core.commands import (
    RESPONSE_OK,
    CurrentCommand,
    VelocityCommand,
    parse_command,
)
from abh3_supervisor.core.eventlog import EventLog
from abh3_supervisor.core.inputs import (
    CommandOutcome,
    InputCommand,
    InputSource,
    Motion,
    Twist,
    VelocityYX,
    execute,
)
from abh3_supervisor.core.readiness import SETTLE_S
from abh3_supervisor.core.robot import RobotConfig
from abh3_supervisor.core.supervisor import Notice
from abh3_supervisor.core.text import clean
from abh3_supervisor.errors import Abh3Error, CommandError
from abh3_supervisor.params.telabh3 import Command
from abh3_supervisor.plugin_host.feed import InputFeed
from abh3_supervisor.plugin_host.terminal import KeyInput
from abh3_supervisor.scheduler.core import HealthEvent
from abh3_supervisor.service import paths
from abh3_supervisor.service import protocol as rpc
from abh3_supervisor.service.accepting import Acceptor, Tally, Turns
from abh3_supervisor.service.connection import Connection
from abh3_supervisor.service.param_ops import ParamFailed, ParamOps
from abh3_supervisor.service.snapshot import state
from abh3_supervisor.service.state_push import SharedState
from abh3_supervisor.service.view_pace import ViewPace, of_runtime

if TYPE_CHECKING:
    from abh3_supervisor.plugin_host.host import PluginHost
    from abh3_supervisor.runtime.bus_runtime import Runtime

log = logging.getLogger(__name__)
MAX_CLIENTS = 32
MAX_BUFFER = 1 << 20  # bytes queued for one client before it is dropped as too slow
MAX_STATE_HZ = 20.0
SHARE_S = 0.005  # clients woken on the same tick get the same encoded state
CLIENT_TIMEOUT_S = 0.5  # streamed motion is fresh this long (as the seed's topics); a
# client holding a VEL proves it is alive at least this often
CLIENT_PRIORITY = 50  # above plugins' default 0: an operator's client wins over them
READ_ONLY_METHODS = {"hello", "state", "subscribe", "keys", "alive"}
# what a client that has gone may still have carried out: it only ever stops motion
WHEN_GONE = READ_ONLY_METHODS | {"estop", "release"}
LABEL = re.compile(r"[a-z][a-z0-9_-]{0,15}")


@dataclass(frozen=True)
class ServiceOptions:
    """Where `abh3 run --headless` serves: the control socket, a group that may use it,
    and an optional second, read-only socket (status for a wider audience)."""

    path: Path
    group: str | None = None
    read_only_path: Path | None = None


def preflight(options: ServiceOptions) -> dict[Path, socket.socket]:
    """The sockets bound, before any drive is commanded: whatever about them can fail
    fails here (exit 2 for a path that cannot be served). Each is handed to its
    :class:`ControlServer`; :func:`release` what was not."""
    read_only = options.read_only_path
    if read_only is not None and read_only.resolve() == options.path.resolve():
        # one file cannot be both: the read-only server would take the control socket's
        # place (no e-stop, no command through it), or the second bind would fail late
        raise Abh3Error(
            f"--read-only-socket {read_only}: that is the control socket's own file "
            f"(--socket {options.path}); give the read-only socket a path of its own"
        )
    gid = paths.group_id(options.group)
    bound = {options.path: paths.bind(options.path, gid)}
    if options.read_only_path is not None:
        try:
            bound[options.read_only_path] = paths.bind(options.read_only_path, None)
        except BaseException:
            release(bound)
            raise
    return bound


def release(bound: dict[Path, socket.socket]) -> None:
    """Sockets bound and never served: closed, their files removed."""
    for path, sock in bound.items():
        sock.close()
        path.unlink(missing_ok=True)
    bound.clear()


class ClientSource(InputSource):
    """One client's motion on one robot (``<client>:<robot>``; a one-drive robot is named
    after its unit, so that is ``<client>:<unit>``). Whatever the client commands on the
    robot — a twist (the whole robot), a ``VEL`` on some of its drives — is this one
    source's, so a client never competes with itself for a robot (the arbitration gives a
    robot one winner) and a ``VEL`` on both drives of a robot moves both. A client may
    hold motion on one robot and other motion on the next, each its own in the
    arbitration."""

    def __init__(self, client: str, robot: RobotConfig) -> None:
        name = f"{client}:{robot.name}"
        super().__init__(name, robot.units, priority=CLIENT_PRIORITY, timeout=CLIENT_TIMEOUT_S)
        self.robot = robot
        self.targets = robot.units  # the units its last motion was given to
        self.feed: InputFeed | None = None
        self.moving = False  # its motion was taken and has not ended yet (as far as said)
        self.standing = False  # that motion is a held VEL/CUR, not a stream
        self.lost: str | None = None  # why its motion ended without the client letting go

    def took(self, *, standing: bool) -> None:
        self.moving, self.standing, self.lost = True, standing, None

    def start(self, feed: InputFeed) -> None:
        self.feed = feed

    def stop(self) -> None:
        self.feed = None


class _Client:
    def __init__(
        self,
        server: ControlServer,
        n: int,
        writer: Connection,
        read_only: bool,
    ) -> None:
        self.server, self.n, self.writer = server, n, writer
        self.read_only = read_only
        self.events = False
        self.state_task: asyncio.Task[None] | None = None
        self.sources: dict[str, ClientSource] = {}  # robot → this client's motion on it
        self.label = "client"  # what it calls itself in `hello` (e.g. "tui")
        writer.on_hangup = self.let_go  # at once: not after a request under way ends

    @property
    def name(self) -> str:
        return f"{self.label}{self.n}"

    def send(self, data: bytes) -> None:
        if self.writer.is_closing():
            return
        if self.writer.queued > MAX_BUFFER:
            log.warning("control %s: not reading its messages; disconnected", self.name)
            self.writer.close()
            return
        self.writer.write(data)

    async def serve(self) -> None:
        while True:
            try:
                line = await self.writer.read_line()
            except EOFError:
                return
            await self.server.turns.enter()
            if line is None:  # its rest is dropped up to the newline: go on after it
                too_long = f"line over {rpc.MAX_LINE} bytes: dropped"
                self.send(rpc.error(None, rpc.INVALID_REQUEST, too_long))
            elif line.strip():
                await self.handle(line)

    async def handle(self, line: bytes) -> None:
        for source in self.sources.values():
            if source.feed is not None:
                source.feed.alive()  # any line proves the client alive: its motion holds
        rid: int | str | None = None
        try:
            try:
                request = rpc.parse_request(line)
            except rpc.RpcError as exc:
                self.send(rpc.error(rpc.request_id(line), exc.code, exc.message))
                return
            rid = request.id
            try:
                value = await self.server.call(self, request)
            except rpc.RpcError as exc:
                if rid is not None:
                    self.send(rpc.error(rid, exc.code, exc.message))
                return
            if rid is not None:
                self.send(rpc.result(rid, value))
        except Exception:  # a fault of ours: said to the client and logged; it goes on
            self.server.faults.note(asyncio.get_running_loop())
            log.debug("control %s: fault answering %r", self.name, line[: rpc.SHOWN], exc_info=True)
            self.send(
                rpc.error(rid, rpc.INTERNAL_ERROR, "internal error (logged by the supervisor)")
            )

    def let_go(self) -> None:
        """Leaving takes the motion with it: its units stop now, and what it sent that is
        still waiting here can move nothing (``ControlServer.call``)."""
        if self.server.host is not None:
            for source in self.sources.values():
                self.server.host.detach(source.name)
        self.sources.clear()

    def close(self) -> None:
        if self.state_task is not None:
            self.state_task.cancel()
            self.state_task = None  # it refers to this client: no cycle left to collect
        self.let_go()
        self.writer.close()


class ControlServer:
    def __init__(
        self,
        rt: Runtime,
        host: PluginHost | None,
        path: Path,
        *,
        read_only: bool = False,
        group: str | None = None,
        sock: socket.socket | None = None,
        pace: ViewPace | None = None,
    ) -> None:
        """``sock``: the socket :func:`preflight` bound at ``path`` (else bound on start);
        ``pace``: the pushes' pace, shared with the runtime's other sockets (else its own)."""
        self.rt, self.host, self.path = rt, host, path
        self.read_only = read_only
        self.gid = paths.group_id(group)
        self.clients: set[_Client] = set()
        self.turns = Turns()
        self.faults = Tally(logging.ERROR, f"control socket {path}: a fault answering a client")
        self._tasks: set[asyncio.Task[None]] = set()
        self._ids = itertools.count(1)
        self._sock = sock
        self._acceptor: Acceptor | None = None
        self._events = EventLog(rt.supervisor)
        self._reader = rt.supervisor.journal.reader()  # the event lines' (_send_lines)
        self._lines_queued = False
        self._methods: dict[str, Callable[[_Client, dict[str, Any]], Awaitable[Any]]] = {
            "hello": self._hello,
            "state": self._state,
            "subscribe": self._subscribe,
            "alive": self._alive,
            "command": self._command,
            **{name: functools.partial(self._motion, name) for name in _FIELDS},
            "release": self._release,
            "estop": self._estop,
            "clear_estop": self._clear_estop,
            "enable": functools.partial(self._enable, True),
            "disable": functools.partial(self._enable, False),
            "audit": self._audit,
            "keys": self._keys,
            "key": self._key,
            "simulate": self._simulate,
            # parameter access (docs/parameters.md): abh3 param --connect, the TUI
            "param_read": self._param_read,
            "param_identity": self._param_identity,
            "param_servo": self._param_servo,
            "param_write": self._param_write,
            "verify": self._verify,
        }
        self._log_handler = _Forward(self)
        # pushes give way while the buses' steps come late (view_pace.py)
        self._pace = pace if pace is not None else of_runtime(rt)
        self._pushed = SharedState(rt, SHARE_S, self._pace.to_json)  # one build a tick for all
        self._check_queued = False
        self._loop: asyncio.AbstractEventLoop | None = None
        self._params = ParamOps(rt.supervisor, lambda bus: rt.pumps[bus].wake())

    async def start(self) -> None:
        if self._sock is None:
            self._sock = paths.bind(self.path, self.gid)
        refusal = rpc.error(
            None,
            rpc.REFUSED,
            f"too many clients: this supervisor serves at most {MAX_CLIENTS} at once",
        )
        refused = Tally(
            logging.WARNING,
            f"control socket {self.path}: refused a client ({MAX_CLIENTS} connected)",
        )
        self._acceptor = Acceptor(self._sock, self._admit, self._full, refusal, refused)
        self._acceptor.start()
        self._loop = asyncio.get_running_loop()
        self._reader = self.rt.supervisor.journal.reader()  # from now on
        self.rt.supervisor.watchers.append(self._on_news)
        if not self.read_only:  # who owns each unit's motion: told at once (core/inputs.py)
            self.rt.supervisor.arbiter.watchers.append(self._owner_changed)
        self._log_handler.loop = asyncio.get_running_loop()
        logging.getLogger().addHandler(self._log_handler)
        kind = "read-only " if self.read_only else ""
        log.info("serving the %scontrol socket %s", kind, self.path)

    async def close(self, reason: str = rpc.STOPPING) -> None:
        """Also for a server never started: its bound socket is let go all the same."""
        logging.getLogger().removeHandler(self._log_handler)
        if self._on_news in self.rt.supervisor.watchers:
            self.rt.supervisor.watchers.remove(self._on_news)
        watchers = self.rt.supervisor.arbiter.watchers
        if self._owner_changed in watchers:
            watchers.remove(self._owner_changed)
        if self._acceptor is not None:
            self._acceptor.close()
        elif self._sock is not None:
            self._sock.close()
        self.faults.close()
        for client in list(self.clients):
            client.send(rpc.notification("bye", {"reason": reason}))
            client.close()
        self.clients.clear()
        for task in list(self._tasks):
            task.cancel()
        if self._tasks:
            await asyncio.wait(self._tasks, timeout=1.0)
        self.path.unlink(missing_ok=True)

    def _full(self) -> bool:
        return len(self.clients) >= MAX_CLIENTS

    def _admit(self, conn: socket.socket) -> None:
        client = _Client(self, next(self._ids), Connection(conn), self.read_only)
        self.clients.add(client)
        task = asyncio.ensure_future(self._serve(client))
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    async def _serve(self, client: _Client) -> None:
        try:
            await client.serve()
        finally:
            self.clients.discard(client)
            client.close()

    async def call(self, client: _Client, request: rpc.Request) -> Any:
        method = self._methods.get(request.method)
        if method is None:
            raise rpc.RpcError(rpc.METHOD_NOT_FOUND, f"no method {rpc.shown(request.method)!r}")
        if client.read_only and request.method not in READ_ONLY_METHODS:
            raise rpc.RpcError(rpc.READ_ONLY, "this connection is read-only")
        if request.method not in WHEN_GONE:
            self._present(client, request.method)
        try:
            return await method(client, request.params)
        except (CommandError, ParamFailed) as exc:
            raise rpc.RpcError(rpc.REFUSED, str(exc)) from None
        finally:
            if request.method not in READ_ONLY_METHODS:
                # the shared encoded state may predate what this call changed (an e-stop):
                # the next push builds a fresh one
                self._pushed.forget()
                self._check_soon()

    def _present(self, client: _Client, what: str) -> None:
        """A client that has gone (closed, or shut its sending side) commands nothing any
        more: what it sent and we had not done yet is dropped (its e-stop aside)."""
        if client.writer.hung_up():
            client.let_go()
            log.info("control %s: has gone; its %s is not carried out", client.name, what)
            raise rpc.RpcError(rpc.REFUSED, "this client has gone: its request is dropped")

    # ------------------------------------------------------------ who holds motion

    def _owner_changed(self, unit: str) -> None:
        """The arbitration gave ``unit`` to another source, or to none (in its decision)."""
        self._check_soon()

    def _check_soon(self) -> None:
        if not self._check_queued and self._loop is not None and not self._loop.is_closed():
            self._check_queued = True
            self._loop.call_soon(self._check_motion)

    def _check_motion(self) -> None:
        """Each client whose motion ended without it letting go is told at once, and why
        (a ``lost`` notification, and a warning in the log): taken over, e-stopped, lapsed,
        the drive stopped itself. It is not resumed: only a new command moves it again."""
        self._check_queued = False
        for client in self.clients:
            for source in client.sources.values():
                if not source.moving:
                    continue
                why = self._why_lost(source)
                if why is None:
                    continue
                source.moving = False
                if not why:  # a stream that stopped: the client's own doing
                    continue
                source.lost = why
                on = ",".join(source.targets)
                log.warning("control %s: its motion on %s ended: %s", client.name, on, why)
                for unit in source.targets:
                    client.send(rpc.notification("lost", {"unit": unit, "reason": why}))

    def _why_lost(self, source: ClientSource) -> str | None:
        """None while ``source`` still owns its unit's motion; else why not (``""``: its
        stream stopped, as the client meant)."""
        feed = source.feed
        arbiter = self.rt.supervisor.arbiter
        if feed is None or arbiter.closed:
            return "the supervisor is stopping"
        if self.rt.supervisor.estop:
            return "the emergency stop is latched"
        stops = self.rt.supervisor.gate.foreign  # another host on its drives (core/foreign.py)
        if (why := next((stops[u] for u in source.robot.units if u in stops), None)) is not None:
            return f"stopped: {why}"
        # the robot's one owner: another source's VEL on the robot's other drive leaves
        # this source's units with none (zero), so every unit of the robot is asked
        robot = source.robot.units
        owner = next((o for u in robot if (o := arbiter.owner(u)) is not None), None)
        if owner is not None and owner != source.name:
            return f"taken over by {owner}"
        if not source.standing:
            return None if owner == source.name else ""
        if not feed.holds():
            return (
                f"lapsed: no line from this client for {CLIENT_TIMEOUT_S:g} s (stopped or starved)"
            )
        if owner == source.name:
            return None
        if not all(self.rt.supervisor.units[u].online for u in source.targets):
            return "the unit went offline"
        return "the drive stopped on its own (a gap in its answers), or the unit is held"

    # ------------------------------------------------------------ events

    def _on_news(self) -> None:
        """The journal has news (once per step of the loop): read after the step."""
        if not self._lines_queued and self._loop is not None:
            self._lines_queued = True
            self._loop.call_soon(self._read_journal)

    def _read_journal(self) -> None:
        """A notice is checked at once (an e-stop, from a key or a plugin, is one); the
        events go as lines to every client that listens."""
        self._lines_queued = False
        listeners = [c for c in self.clients if c.events]
        missed = self._reader.missed
        for _, event, _ in self._reader.read():
            if isinstance(event, Notice):
                self._check_soon()
            if listeners and (line := self._events.line(event)) is not None:
                self.broadcast(listeners, line[0], line[1], getattr(event, "unit", None))
        if self._reader.missed > missed:  # the loop outran this step's reads: said
            text = f"{self._reader.missed - missed} event(s) were not read in time: not sent"
            log.warning("control socket %s: %s", self.path, text)
            if listeners:
                self.broadcast(listeners, logging.WARNING, text)

    def broadcast(
        self, listeners: list[_Client], level: int, text: str, unit: str | None = None
    ) -> None:
        """An ``event`` notification: the supervisor's event lines and what is logged."""
        params = {"t": self.rt.supervisor.clock(), "level": logging.getLevelName(level)}
        data = rpc.notification("event", {**params, "unit": unit, "text": text})
        for client in listeners:
            client.send(data)

    def forward(self, record: logging.LogRecord) -> None:
        """What the service logs (plugins, the stop path) reaches clients too, on the loop."""
        listeners = [c for c in self.clients if c.events]
        if listeners:
            self.broadcast(listeners, record.levelno, record.getMessage())

    # ------------------------------------------------------------ methods

    async def _hello(self, client: _Client, params: dict[str, Any]) -> Any:
        config = self.rt.config
        if "name" in params:
            label = params["name"]
            if not isinstance(label, str) or not LABEL.fullmatch(label):
                raise rpc.RpcError(rpc.INVALID_PARAMS, "'name': 1–16 of a-z 0-9 _ -")
            client.label = label
        return {
            "protocol": rpc.PROTOCOL,
            "version": __version__,
            "config": config.file,
            "config_path": str(Path(config.file).resolve()),  # the file, wherever we run
            "read_only": client.read_only,
            "units": list(config.units),
            # each robot's drives (a twist drives them all); one-drive robots too
            "robots": {name: list(robot.units) for name, robot in config.robots.items()},
            "buses": list(config.buses),
            "config_text": config.text,  # a client rebuilds the same typed Config from it
            "simulated": sorted(self.rt.sims),
            "name": client.name,
        }

    async def _state(self, client: _Client, params: dict[str, Any]) -> Any:
        return state(self.rt, self._pace.to_json())

    async def _subscribe(self, client: _Client, params: dict[str, Any]) -> Any:
        events = params.get("events", True)
        hz = params.get("state_hz", 0)
        if not isinstance(events, bool):
            raise rpc.RpcError(rpc.INVALID_PARAMS, "'events' must be true or false")
        if isinstance(hz, bool) or not isinstance(hz, int | float) or not 0 <= hz <= MAX_STATE_HZ:
            raise rpc.RpcError(rpc.INVALID_PARAMS, f"'state_hz' must be 0–{MAX_STATE_HZ:g}")
        if events and not client.events:  # after the reply: what is already so
            asyncio.get_running_loop().call_soon(self._online_lines, client)
        client.events = events
        if client.state_task is not None:
            client.state_task.cancel()
            client.state_task = None
        if hz:
            client.state_task = asyncio.ensure_future(self._push_state(client, 1 / hz))
        return {"events": events, "state_hz": hz}

    def _online_lines(self, client: _Client) -> None:
        """The units already online, as the headless log said it when they came."""
        sup = self.rt.supervisor
        for name, unit in sup.units.items():
            if unit.online:
                line = self._events.line(HealthEvent(name, sup.clock(), True))
                if line is not None:
                    self.broadcast([client], line[0], line[1], name)

    async def _push_state(self, client: _Client, asked: float) -> None:
        """On a grid of the period ``asked`` (longer while the buses run late: view_pace.py)
        shared by every client at that pace: one snapshot built per tick for all of them,
        unit by unit between the buses' steps (state_push.py)."""
        loop = asyncio.get_running_loop()
        while not client.writer.is_closing():
            client.send(await self._pushed.latest())
            period, now = self._pace.period(asked), loop.time()
            await asyncio.sleep((math.floor(now / period) + 1) * period - now)

    def _commanded(self, params: dict[str, Any]) -> tuple[str, ...]:
        sup = self.rt.supervisor
        units = rpc.units(params, tuple(sup.units))
        for unit in units:
            if sup.units[unit].cfg.role is not Role.COMMAND:
                raise rpc.RpcError(rpc.REFUSED, f"unit {unit!r} is role: monitor")
        return units

    async def _alive(self, client: _Client, params: dict[str, Any]) -> Any:
        """Proof of life (as any line is): a client holding a ``VEL`` sends it ≥ 2 Hz.
        ``holds``: the units whose standing motion this client still owns; ``lost``: why
        the motion it held on a unit ended (taken over, e-stop, lapsed, the drive)."""
        self._check_motion()  # as things are now, not as they were at the last check
        sources = client.sources.values()
        holds = [u for s in sources if s.moving and s.standing for u in s.targets]
        lost = {u: s.lost for s in sources if s.lost is not None for u in s.targets}
        return {"ok": True, "holds": holds, "lost": lost}

    async def _command(self, client: _Client, params: dict[str, Any]) -> Any:
        """The command language; a ``VEL``/``CUR`` is this client's motion, held while it is
        connected and alive (``held``), with a note per unit whose value was clamped."""
        units = self._commanded(params)
        text = rpc.text(params, "text")

        def submit(command: Motion) -> None:
            self._submit(self._per_robot(client, units), command, standing=True)

        if _moves(text) or len(units) == 1:  # motion: on every unit or on none
            outcome = await execute(self.rt.supervisor, units, text, submit)
        else:  # switches, unit after unit: none after the client has gone
            parts = []
            for unit in units:
                self._present(client, "command")
                parts.append(await execute(self.rt.supervisor, (unit,), text, submit))
            outcome = CommandOutcome(
                {u: r for part in parts for u, r in part.responses.items()},
                {u: n for part in parts for u, n in part.clamped.items()},
                why={u: w for part in parts for u, w in part.why.items()},
            )
        response = outcome.response
        log.info(
            "control %s: %r on %s → %r%s",
            client.name,
            clean(text),
            ",".join(units),
            response,
            "".join(f"; {unit}: {note}" for unit, note in outcome.clamped.items()),
        )
        return {
            "response": response,
            "responses": outcome.responses,
            "clamped": outcome.clamped,
            "held": outcome.motion and response == RESPONSE_OK,
            "why": outcome.why,  # each refused unit's reason, where the seed's answer has none
        }

    def _source(self, client: _Client, robot: RobotConfig) -> ClientSource:
        """The client's motion source on ``robot``, attached on first use."""
        if self.host is None:
            raise rpc.RpcError(rpc.REFUSED, "this supervisor runs without inputs")
        source = client.sources.get(robot.name)
        if source is None:
            source = ClientSource(client.name, robot)
            if self.host.attach(source) is None:
                raise rpc.RpcError(rpc.REFUSED, "the supervisor is stopping")
            client.sources[robot.name] = source
        if source.feed is None:
            raise rpc.RpcError(rpc.REFUSED, "the supervisor is stopping")
        return source

    def _per_robot(
        self, client: _Client, units: tuple[str, ...]
    ) -> list[tuple[ClientSource, tuple[str, ...]]]:
        """The client's source on each robot of ``units``, with the units of it named."""
        config = self.rt.config
        named: dict[str, list[str]] = {}
        for unit in units:
            robot = config.robot_of(unit)
            if robot is None:  # a monitor unit: _commanded refused it already
                raise rpc.RpcError(rpc.REFUSED, f"unit {unit!r} drives no robot")
            named.setdefault(robot.name, []).append(unit)
        return [(self._source(client, config.robots[r]), tuple(us)) for r, us in named.items()]

    def _submit(
        self,
        targets: list[tuple[ClientSource, tuple[str, ...]]],
        command: InputCommand,
        *,
        standing: bool,
    ) -> None:
        """``command`` as each source's, on its units, on the loop now (the reply comes
        after the arbitration decided). The source is given its units in the same
        decision, so its previous command never reaches the new units."""
        arbiter = self.rt.supervisor.arbiter
        if arbiter.closed:
            raise CommandError("the supervisor is stopping: commands are refused")
        for source, units in targets:
            source.targets = units
            arbiter.submit(source.name, command, arbiter.clock(), standing=standing, units=units)
        if standing or not self.rt.supervisor.estop:  # zero under the e-stop: nothing to lose
            for source, _ in targets:
                source.took(standing=standing)

    def _robots(self, params: dict[str, Any]) -> tuple[RobotConfig, ...]:
        """``robot``/``robots``, or ``unit``/``units`` naming robots or units (each unit
        stands for its robot): the robots a twist drives, each as a whole."""
        sup, config = self.rt.supervisor, self.rt.config
        if "robot" in params or "robots" in params:
            names = rpc.names(params, "robot", "robots")
        else:
            names = rpc.names(params, "unit", "units")
        robots: dict[str, RobotConfig] = {}
        for name in names:
            robot = config.robots.get(name)
            if robot is None and name in sup.units:
                robot = config.robot_of(self._commanded({"unit": name})[0])
            if robot is None:
                known = ", ".join(config.robots) or "none"
                raise rpc.RpcError(
                    rpc.REFUSED, f"no robot or unit named {rpc.shown(name)!r} (robots: {known})"
                )
            robots[robot.name] = robot
        return tuple(robots.values())

    async def _motion(self, method: str, client: _Client, params: dict[str, Any]) -> Any:
        values = [rpc.number(params, key) for key in _FIELDS[method]]  # checked before use
        if method == "twist":  # a robot's twist drives all its drives (core/robot_motion.py)
            robots = self._robots(params)
            units = tuple(u for robot in robots for u in robot.units)
        else:
            units = self._commanded(params)
        if any(values):  # refused in the answer, not only in a notice: e-stop, held, …
            kind = ControlMode.CURRENT if method == "current" else ControlMode.VELOCITY
            for unit in units:
                try:
                    self.rt.supervisor.refuse_motion(unit, kind)
                except CommandError as exc:
                    raise rpc.RpcError(rpc.REFUSED, str(exc)) from None
        self._submit(self._per_robot(client, units), _COMMANDS[method](*values), standing=False)
        reply: dict[str, Any] = {"ok": True, "fresh_for_s": CLIENT_TIMEOUT_S}
        if method == "twist":
            reply["robots"] = [robot.name for robot in robots]
        return reply

    async def _release(self, client: _Client, params: dict[str, Any]) -> Any:
        for source in client.sources.values():
            if source.feed is not None:
                source.feed.release()
            source.moving, source.lost = False, None  # let go on purpose: nothing lost
        return {"ok": True}

    async def _estop(self, client: _Client, params: dict[str, Any]) -> Any:
        self.rt.supervisor.emergency_stop(client.name)  # each unit's stop frame at once
        log.warning("control %s: EMERGENCY STOP", client.name)
        return {"ok": True}

    async def _clear_estop(self, client: _Client, params: dict[str, Any]) -> Any:
        # the stops other hosts caused are cleared with it, once that host is quiet
        standing = self.rt.supervisor.clear_emergency_stop(client.name)
        log.warning("control %s: emergency stop cleared", client.name)
        return {"ok": True, "standing": standing}

    async def _enable(self, on: bool, client: _Client, params: dict[str, Any]) -> Any:
        """SERVO and START of a robot's wheel axes on (or off) as one act; on: the answer
        comes once every drive reports it, or says which did not follow within the
        settle time (docs/safety.md, "The robot decision")."""
        sup = self.rt.supervisor
        robots = self._robots(params)
        try:
            for robot in robots:
                sup.enable(robot.name, on, client.name)
        except CommandError as exc:
            raise rpc.RpcError(rpc.REFUSED, str(exc)) from None
        reply: dict[str, Any] = {"ok": True, "robots": [r.name for r in robots]}
        if not on:
            return reply
        loop = asyncio.get_running_loop()
        deadline = loop.time() + SETTLE_S + 0.2
        pending = list(robots)
        while pending and loop.time() < deadline:
            await asyncio.sleep(0.01)
            pending = [r for r in robots if sup.robot_unready(r.units[0]) is not None]
        unready = {r.name: sup.robot_unready(r.units[0]) for r in robots}
        reply["not_ready"] = {name: why.why for name, why in unready.items() if why is not None}
        return reply

    async def _audit(self, client: _Client, params: dict[str, Any]) -> Any:
        """An operator's action at the client, into the audit trail (and every event log)."""
        unit = params.get("unit")
        if unit is not None:
            unit = rpc.units({"unit": unit}, tuple(self.rt.supervisor.units))[0]
        self.rt.supervisor.audit(client.name, unit, rpc.text(params, "action"))
        return {"ok": True}

    def _key_inputs(self) -> dict[str, KeyInput]:
        sources = self.host.sources if self.host is not None else ()
        return {s.name: s for s in sources if isinstance(s, KeyInput)}

    async def _keys(self, client: _Client, params: dict[str, Any]) -> Any:
        """The keys each input source that reads a terminal wants, avoiding ``taken`` (the
        client's own): a client owning a terminal hands them over with ``key``."""
        taken = params.get("taken", [])
        if not isinstance(taken, list) or not all(isinstance(k, str) for k in taken):
            raise rpc.RpcError(rpc.INVALID_PARAMS, "'taken' must be a list of keys")
        return {name: s.key_map(taken) for name, s in self._key_inputs().items()}

    async def _key(self, client: _Client, params: dict[str, Any]) -> Any:
        name, key = rpc.text(params, "source"), rpc.text(params, "key")
        source = self._key_inputs().get(name)
        if source is None:
            raise rpc.RpcError(rpc.INVALID_PARAMS, f"no input source {name!r} takes keys")
        if len(key) != 1 or not key.isprintable():
            raise rpc.RpcError(rpc.INVALID_PARAMS, "'key' must be one printable character")
        source.press(key)  # a key outside its map is ignored by the source
        return {"ok": True}

    async def _simulate(self, client: _Client, params: dict[str, Any]) -> Any:
        """A simulated drive stops answering (``silent``) or answers again: a rehearsal."""
        unit = rpc.units(params, tuple(self.rt.supervisor.units))[0]
        cfg = self.rt.config.units[unit]
        sim = self.rt.sims.get(cfg.bus)
        silent = params.get("silent")
        if sim is None:
            raise rpc.RpcError(rpc.REFUSED, f"unit {unit!r} is not simulated")
        if not isinstance(silent, bool):
            raise rpc.RpcError(rpc.INVALID_PARAMS, "'silent' must be true or false")
        sim.drives[cfg.abh3_id].silent = silent
        log.warning(
            "control %s: simulated %s %s",
            client.name,
            unit,
            "stops answering" if silent else "answers again",
        )
        return {"ok": True}

    # ------------------------------------------------------------ parameters

    def _param_args(self, params: dict[str, Any]) -> tuple[str, int]:
        unit = rpc.text(params, "unit")
        address = params.get("address")
        if isinstance(address, bool) or not isinstance(address, int) or not 0 <= address <= 0xFFFF:
            raise rpc.RpcError(rpc.INVALID_PARAMS, "'address' must be an integer 0-0xFFFF")
        self.rt.supervisor.unit(unit)  # CommandError for an unknown unit
        return unit, address

    async def _param_read(self, client: _Client, params: dict[str, Any]) -> Any:
        unit, address = self._param_args(params)
        command = params.get("command", "CP")
        if command not in (Command.PARAM.value, Command.MONITOR.value):
            raise rpc.RpcError(rpc.INVALID_PARAMS, "'command' must be 'CP' or 'CM'")
        return {"word": await self._params.read(unit, Command(command), address)}

    async def _param_identity(self, client: _Client, params: dict[str, Any]) -> Any:
        unit, address = self._param_args(params)
        text = await self._params.identity(unit, address)
        return {"text": text, "form": self._params.form(unit)}

    async def _verify(self, client: _Client, params: dict[str, Any]) -> Any:
        """Compare the drive's CAN settings with the YAML again (a unit ``verify: refuse``
        holds is released when they agree, and its start-up commands run)."""
        unit = rpc.units(params, tuple(self.rt.supervisor.units))[0]
        self.rt.supervisor.audit(client.name, unit, "verify the drive's settings again")
        return (await verifying.verify_units(self.rt.supervisor, [unit]))[unit].to_json()

    async def _param_servo(self, client: _Client, params: dict[str, Any]) -> Any:
        unit = rpc.text(params, "unit")
        return {"servo": await self._params.servo_on(unit)}

    async def _param_write(self, client: _Client, params: dict[str, Any]) -> Any:
        unit, address = self._param_args(params)
        word = params.get("word")
        if isinstance(word, bool) or not isinstance(word, int) or not 0 <= word <= 0xFFFFFFFF:
            raise rpc.RpcError(rpc.INVALID_PARAMS, "'word' must be a 32-bit unsigned integer")
        force = params.get("force", False) is True
        source = f"param {client.name}"
        old, new = await self._params.write(unit, address, word, force=force, source=source)
        return {"old": old, "new": new}


class _Forward(logging.Handler):
    """Log records to the clients, from whatever thread logs them: always through the
    loop's queue, so a record logged while sending to a client is sent after it."""

    def __init__(self, server: ControlServer) -> None:
        super().__init__(logging.INFO)
        self.server = server
        self.loop: asyncio.AbstractEventLoop | None = None

    def emit(self, record: logging.LogRecord) -> None:
        if record.name == "abh3":  # the supervisor's own event lines go as events already
            return
        loop = self.loop
        if loop is None:
            return
        with contextlib.suppress(RuntimeError):  # the loop closed meanwhile
            loop.call_soon_threadsafe(self.server.forward, record)


def _moves(text: str) -> bool:
    """A ``VEL``/``CUR``: motion, taken on every unit or on none."""
    try:
        return isinstance(parse_command(text), VelocityCommand | CurrentCommand)
    except CommandError:
        return False


_COMMANDS: dict[str, Callable[[float, float], InputCommand]] = {
    "twist": Twist,
    "velocity_yx": VelocityYX,
    "velocity": VelocityCommand,
    "current": CurrentCommand,
}
_FIELDS = {
    "twist": ("linear_x", "angular_z"),
    "velocity_yx": ("y", "x"),
    "velocity": ("ay", "bx"),
    "current": ("ay", "bx"),
}
