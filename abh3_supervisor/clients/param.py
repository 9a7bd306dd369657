"""``abh3 param``: read, write, dump, diff and restore drive parameters, watch monitors,
read the identity — on the configuration's own buses (``--config``) or through a running
supervisor's control socket (``--connect``, or the only one serving).

On its own buses every unit runs as ``role: monitor`` without start-up commands: this
tool never moves a motor and never fights a supervisor that does. Parameter traffic
shares the bus with the DP0 exchanges (scheduler/core.py). Writes ask first (``--yes``
skips), are refused while the unit reports its servo on (``--force``), and are logged
with the old and the new value in the event log of whichever process writes
(service/param_ops.py). Exit: 0 done, 1 a drive, the transport or the service failed or
refused, 2 a mistake on the command line or in a file.
"""

from __future__ import annotations

# light imports only: the parser is built for every `abh3` command; the buses, YAML and
# the runtime load in run()
import argparse
import asyncio
import contextlib
import logging
import sys
import threading
import time
from collections.abc import Callable, Coroutine, Iterable
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

from abh3_supervisor.clients import peer
from abh3_supervisor.clients.argtypes import count, finite_positive
from abh3_supervisor.clients.ssh import endpoint
from abh3_supervisor.errors import CommandError, Interrupted, PartialWrite
from abh3_supervisor.params import table
from abh3_supervisor.params.telabh3 import Command
from abh3_supervisor.runtime import signals

if TYPE_CHECKING:
    from abh3_supervisor.clients.control import ControlClient
    from abh3_supervisor.config import Config
    from abh3_supervisor.params.files import ParamValue

log = logging.getLogger("abh3")
IDENTITY_ADDRESSES = (0x0, 0x2, 0x4, 0x5, 0x8, 0xC)


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser("param", help="read and write drive parameters (TelABH3 over CAN)")
    where = p.add_mutually_exclusive_group()
    where.add_argument("--config", "-c", type=Path, help="use this configuration's buses")
    where.add_argument(
        "--connect",
        type=endpoint,
        metavar="PATH",
        help="a running supervisor's control socket (ssh://[user@]host[:port]/path: on "
        "another host)",
    )
    peer.add_option(p)
    ops = p.add_subparsers(dest="op", required=True, metavar="OP")
    get = ops.add_parser("get", help="read parameters")
    get.add_argument("unit")
    get.add_argument("addresses", nargs="+", metavar="ADDR", help="name, 0x5000 or decimal")
    put = ops.add_parser("set", help="write one parameter")
    put.add_argument("unit")
    put.add_argument("address", metavar="ADDR")
    put.add_argument("value", help="the value (packed float or integer, by the address)")
    dump = ops.add_parser("dump", help="read every known parameter")
    dump.add_argument("unit")
    dump.add_argument("-o", "--output", type=Path, help=".csv (maker's, cp932), .yaml, .json")
    diff = ops.add_parser("diff", help="compare the drive with a file")
    diff.add_argument("unit")
    diff.add_argument("file", type=Path)
    restore = ops.add_parser("restore", help="write what differs from a file")
    restore.add_argument("unit")
    restore.add_argument("file", type=Path)
    mon = ops.add_parser("monitor", help="read monitors repeatedly (Ctrl-C ends)")
    mon.add_argument("unit")
    mon.add_argument("addresses", nargs="+", metavar="ADDR", help="e.g. VELOCITY_AY, 0x1054")
    mon.add_argument("--interval", type=finite_positive, default=0.5, metavar="S")
    mon.add_argument("--count", type=count, default=0, metavar="N", help="stop after N rounds")
    ident = ops.add_parser("identity", help="the drive's identity strings (firmware version)")
    ident.add_argument("unit")
    for op in (diff, restore):
        op.add_argument(
            "--allow-unknown", action="store_true", help="accept addresses not in the table"
        )
    for op in (put, restore):
        op.add_argument("--yes", "-y", action="store_true", help="do not ask")
        op.add_argument("--force", action="store_true", help="write even while the servo is on")


class Backend(Protocol):
    """What the operations need: :class:`ParamOps` here, or the same over the socket."""

    async def read(self, unit: str, command: Command, address: int) -> int: ...
    async def identity(self, unit: str, address: int) -> str: ...
    def form(self, unit: str) -> str | None: ...
    async def servo_on(self, unit: str) -> bool | None: ...
    async def write(
        self, unit: str, address: int, word: int, *, force: bool, source: str
    ) -> tuple[int, int]: ...


class Remote:
    """:class:`Backend` through a running supervisor's control socket (``param_*``)."""

    def __init__(self, client: ControlClient) -> None:
        self.client = client
        self._forms: dict[str, str | None] = {}  # as the service last said

    async def read(self, unit: str, command: Command, address: int) -> int:
        reply = self.client.call("param_read", unit=unit, command=command.value, address=address)
        return int(reply["word"])

    async def identity(self, unit: str, address: int) -> str:
        reply = self.client.call("param_identity", unit=unit, address=address)
        self._forms[unit] = reply.get("form")
        return str(reply["text"])

    def form(self, unit: str) -> str | None:
        return self._forms.get(unit)

    async def servo_on(self, unit: str) -> bool | None:
        servo = self.client.call("param_servo", unit=unit)["servo"]
        return None if servo is None else bool(servo)

    async def write(
        self, unit: str, address: int, word: int, *, force: bool, source: str
    ) -> tuple[int, int]:
        reply = self.client.call("param_write", unit=unit, address=address, word=word, force=force)
        return int(reply["old"]), int(reply["new"])


def monitor_only(config: Config) -> Config:
    """Every unit as a monitor without start-up commands: this tool never commands motion."""
    import dataclasses

    from abh3_supervisor.config.model import Role

    units = {
        n: dataclasses.replace(u, role=Role.MONITOR, startup=()) for n, u in config.units.items()
    }
    return dataclasses.replace(config, units=units)


def run(args: argparse.Namespace) -> int:
    op = OPS[args.op]
    if args.config is None:
        from abh3_supervisor.clients.control import ControlClient, find_socket

        client = ControlClient(find_socket(args.connect), timeout=30.0)
        try:
            known_unit(args.unit, client.call("hello")["units"])  # before asking anything
            return asyncio.run(op(Remote(client), args))
        finally:
            client.close()
    from abh3_supervisor.config import load_config

    config = monitor_only(load_config(args.config))
    known_unit(args.unit, config.units)  # before any bus opens
    return asyncio.run(_on_own_bus(config, lambda backend: op(backend, args), args.unit))


class _Stop:
    """Stop signals on the loop while ``abh3 param`` works on its own buses: the work is
    cancelled at once and the signal raised as :class:`Interrupted`; the buses' start and
    close are never cut short (a signal then is kept and raised after the start).

    The CLI's own handler raises where the signal lands, which on a running loop is inside
    a pump's callback, where asyncio logs the exception and goes on: a loop needs its own.
    (Through ``--connect`` the work blocks in the socket instead, where that handler works.)
    """

    def __init__(self) -> None:
        self.loop = asyncio.get_running_loop()
        self.signum: int | None = None
        self.task: asyncio.Task[int] | None = None
        self._handled = contextlib.ExitStack()

    def __enter__(self) -> _Stop:
        # every signal that would end the process (docs/signals.md); none off the main
        # thread (a test may run the CLI on another): signals reach only that one
        self._handled.enter_context(signals.on_loop(self.loop, self._caught))
        return self

    def __exit__(self, *exc: object) -> None:
        self._handled.close()

    def _caught(self, signum: int) -> None:
        if self.signum is None:
            self.signum = signum
        self._cancel()

    def _cancel(self) -> None:
        # again until the work ends: library code that catches a cancellation (3.11's
        # wait_for, as an answer arrives) must not be able to lose a stop
        if self.task is not None and not self.task.done() and self.signum is not None:
            self.task.cancel(f"stopped by {signals.name(self.signum)}")
            self.loop.call_later(0.1, self._cancel)

    async def run(self, work: Coroutine[Any, Any, int]) -> int:
        if self.signum is not None:  # stopped while the buses opened
            work.close()
            raise Interrupted(self.signum)
        self.task = asyncio.ensure_future(work)
        try:
            return await self.task
        except asyncio.CancelledError:
            if self.signum is not None:
                raise Interrupted(self.signum) from None
            raise


def known_unit(name: str, units: Iterable[str]) -> None:
    """An unknown unit is a mistake on the command line (exit 2), said in the words every
    other front end uses (``Supervisor.unit``, core/supervisor.py) — also through the
    socket, whose refusal would otherwise come back as the service failing (exit 1)."""
    units = list(units)
    if name not in units:
        raise CommandError(f"no unit named '{name}' (units: {', '.join(units)})")


async def _on_own_bus(
    config: Config, op: Callable[[Backend], Coroutine[Any, Any, int]], unit: str
) -> int:
    from abh3_supervisor.core.eventlog import EventLog
    from abh3_supervisor.core.supervisor import OperatorAction, SupervisorEvent
    from abh3_supervisor.runtime.bus_runtime import Runtime
    from abh3_supervisor.runtime.listening import refuse_if_commanded
    from abh3_supervisor.service.param_ops import ParamOps

    with _Stop() as stop:
        # a host commanding the drive would see our parameter session as another host's
        # (and stop), and we would fight it: refused before anything is sent (exit 2)
        await refuse_if_commanded(config, [unit], "abh3 param")
        async with Runtime(config) as rt:
            events = EventLog(rt.supervisor)

            def on_event(event: SupervisorEvent) -> None:
                if isinstance(event, OperatorAction):  # the writes: nothing else is news here
                    line = events.line(event)
                    if line is not None:
                        log.log(*line)

            rt.supervisor.subscribe(on_event)
            return await stop.run(op(ParamOps(rt.supervisor, lambda bus: rt.pumps[bus].wake())))


# ------------------------------------------------------------ operations


def _value(address: int, word: int) -> ParamValue:
    from abh3_supervisor.params.files import ParamValue

    return ParamValue(address, word)


def _line(v: ParamValue) -> str:
    return f"0x{v.address:04X} {v.name:<28} {v.shown:>12}  ({v.word:08X})"


async def _read_all(backend: Backend, unit: str, addresses: list[int]) -> list[ParamValue]:
    return [_value(a, await backend.read(unit, Command.PARAM, a)) for a in addresses]


async def _get(backend: Backend, args: argparse.Namespace) -> int:
    addresses = [table.parse_address(text) for text in args.addresses]  # all, before any read
    for value in await _read_all(backend, args.unit, addresses):
        print(_line(value))
    return 0


async def _dump(backend: Backend, args: argparse.Namespace) -> int:
    from abh3_supervisor.params import files

    if args.output is not None:
        files.format_of(args.output)  # a wrong extension is refused before the bus is used
    values = await _read_all(backend, args.unit, [e.address for e in table.PARAMETERS])
    if args.output is None:
        sys.stdout.write(files.dumps(values, "yaml", args.unit))
    else:
        files.write(args.output, values, args.unit)
        print(f"{len(values)} parameters of {args.unit} written to {args.output}")
    return 0


async def _differences(
    backend: Backend, unit: str, path: Path, allow_unknown: bool = False
) -> list[tuple[ParamValue, ParamValue]]:
    from abh3_supervisor.params import files

    wanted = files.read(path, allow_unknown=allow_unknown)  # all checked before any read
    have = await _read_all(backend, unit, [v.address for v in wanted])
    return [(h, w) for h, w in zip(have, wanted, strict=True) if h.word != w.word]


def _show(differences: list[tuple[ParamValue, ParamValue]], unit: str, path: Path) -> None:
    for have, want in differences:
        print(f"0x{have.address:04X} {have.name:<28} drive {have.shown:>12}  file {want.shown:>12}")
    print(f"{len(differences)} parameter(s) of {unit} differ from {path}")


async def _diff(backend: Backend, args: argparse.Namespace) -> int:
    found = await _differences(backend, args.unit, args.file, args.allow_unknown)
    _show(found, args.unit, args.file)
    return 0


async def _may_write(backend: Backend, args: argparse.Namespace, what: str) -> bool:
    from abh3_supervisor.service.param_ops import ParamFailed

    servo = await backend.servo_on(args.unit)
    if servo is not False and not args.force:  # refused before asking (checked again)
        why = "reports its servo ON" if servo else "did not answer whether its servo is on"
        raise ParamFailed(
            f"unit {args.unit} {why}: not writing (SERVO OFF first; --force writes with the "
            "servo on, but never while this supervisor commands it ON)"
        )
    if args.yes:
        return True
    if not sys.stdin.isatty():
        raise CommandError(f"{what}: confirm with --yes when not on a terminal")
    return (await _ask(f"{what}? [y/N] ")).strip().lower() in ("y", "yes")


async def _ask(prompt: str) -> str:
    """``input(prompt)`` on a daemon thread: the loop keeps its buses and its signals (a
    Ctrl-C at the question ends the command; the thread is left behind, blocked on stdin)."""
    loop = asyncio.get_running_loop()
    answer: asyncio.Future[str] = loop.create_future()

    def read() -> None:
        try:
            line = input(prompt)
        except EOFError:
            line = ""

        def give() -> None:
            if not answer.done():
                answer.set_result(line)

        loop.call_soon_threadsafe(give)

    threading.Thread(target=read, name="question", daemon=True).start()
    return await answer


async def _write(backend: Backend, args: argparse.Namespace, new: ParamValue) -> ParamValue:
    _, back = await backend.write(
        args.unit, new.address, new.word, force=args.force, source="param"
    )
    return _value(new.address, back)


async def _set(backend: Backend, args: argparse.Namespace) -> int:
    address = table.parse_address(args.address)
    try:
        value = float(args.value)
    except ValueError:
        raise CommandError(f"'{args.value}' is not a number") from None
    new = _value(address, table.to_word(value, table.kind_of(address)))
    old = _value(address, await backend.read(args.unit, Command.PARAM, address))
    print(_line(old))
    if old.word == new.word:
        print("already set: nothing written")
        return 0
    what = f"set {args.unit} 0x{address:04X} {new.name}: {old.shown} → {new.shown}"
    if not await _may_write(backend, args, what):
        print("not written")
        return 0
    print(f"written: {_line(await _write(backend, args, new))}")
    return 0


async def _restore(backend: Backend, args: argparse.Namespace) -> int:
    differences = await _differences(backend, args.unit, args.file, args.allow_unknown)
    _show(differences, args.unit, args.file)
    if not differences:
        return 0
    if not await _may_write(backend, args, f"write {len(differences)} parameter(s) to {args.unit}"):
        print("not written")
        return 0
    journal = Journal(args)
    total = len(differences)
    try:
        for n, (have, want) in enumerate(differences, 1):
            journal.add(have)  # the old value, kept before the write goes out
            _say(f"[{n}/{total}] {have.name}: {have.shown} → {want.shown}")
            await _write(backend, args, want)
            journal.written += 1
    except (Exception, asyncio.CancelledError, Interrupted) as exc:
        journal.close()
        if not journal.entries:
            raise
        raise PartialWrite(journal.report(total, _cause(exc))) from exc
    journal.discard()
    print(f"{total} parameter(s) of {args.unit} restored from {args.file}")
    return 0


def _say(text: str) -> None:
    """A line on stderr that cannot stop a restore: a reader that went away (``| head``,
    a closed terminal) must not turn a partial restore into an unreported one."""
    with contextlib.suppress(OSError, ValueError):
        print(text, file=sys.stderr, flush=True)


def _cause(exc: BaseException) -> str:
    if isinstance(exc, Interrupted):
        return f"stopped by {signals.name(exc.signum)}"
    if isinstance(exc, asyncio.CancelledError):
        return str(exc.args[0]) if exc.args else "cancelled"
    return str(exc) or type(exc).__name__


class Journal:
    """The old value of every parameter a restore is about to write, appended to a file
    before each write goes out (so even ``kill -9`` leaves it): restoring that file undoes
    the restore. Kept when the restore stops part way, removed when it completes."""

    def __init__(self, args: argparse.Namespace) -> None:
        self.args = args
        self.entries: list[ParamValue] = []
        self.written = 0  # writes confirmed; the entry after them may or may not be written
        stamp = time.strftime("%Y%m%d-%H%M%S")
        name = f"{args.file.stem}.undo-{args.unit}-{stamp}.csv"
        self.path: Path | None = args.file.with_name(name)
        self._file: Any = None

    def add(self, old: ParamValue) -> None:
        from abh3_supervisor.params import files

        self.entries.append(old)
        if self._file is None and self.path is not None:
            self._file = self._open()
        if self._file is not None:
            self._file.write(files.dumps([old], "csv").encode(files.ENCODING))
            self._file.flush()

    def _open(self) -> Any:
        assert self.path is not None
        for path in (self.path, Path.cwd() / self.path.name):  # beside the file, else here
            try:
                handle = path.open("xb")
            except OSError:
                continue
            self.path = path
            return handle
        log.warning("cannot save the undo journal beside %s or here", self.args.file)
        self.path = None
        return None

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None

    def discard(self) -> None:
        self.close()
        if self.path is not None:
            self.path.unlink(missing_ok=True)

    def report(self, total: int, cause: str) -> str:
        """Print what was written with its old value; the message for the partial exit."""
        unsure = len(self.entries) - self.written
        _say(f"restore of {self.args.unit} stopped part way ({cause}):")
        for i, old in enumerate(self.entries):
            state = "written" if i < self.written else "maybe written"
            _say(f"  {state}: {_line(old)}  (the old value)")
        args = self.args
        where = f"-c {args.config} " if args.config else ""
        where += f"--connect {args.connect} " if args.connect else ""
        extra = " --allow-unknown" if args.allow_unknown else ""
        if self.path is None:
            undo = "the old values above were not saved: write them back with `abh3 param set`"
        else:
            undo = f"undo: abh3 param {where}restore {args.unit} {self.path} --yes{extra}"
            _say(f"the old values are saved in {self.path}")
        _say(undo)
        maybe = f" (and {unsure} maybe)" if unsure else ""
        return f"partial restore: {self.written} of {total} parameter(s) written{maybe}: see above"


async def _monitor(backend: Backend, args: argparse.Namespace) -> int:
    addresses = [table.parse_address(a, monitor=True) for a in args.addresses]
    rounds = 0
    while not args.count or rounds < args.count:
        shown = []
        for a in addresses:
            word = await backend.read(args.unit, Command.MONITOR, a)
            value = table.to_value(word, table.kind_of(a, monitor=True))
            shown.append(f"{table.label(a, monitor=True)}={table.display(value)}")
        print(" ".join(shown), flush=True)
        rounds += 1
        if not args.count or rounds < args.count:
            await asyncio.sleep(args.interval)  # the operator's pace, in real time
    return 0


async def _identity(backend: Backend, args: argparse.Namespace) -> int:
    for address in IDENTITY_ADDRESSES:
        name = table.IDENTITY.get(address) or f"BI 0x{address:X}"
        print(f"{name:<18} {await backend.identity(args.unit, address)}")
    form = backend.form(args.unit)  # how the drive wants its strings framed on CAN
    print(f"{'TelABH3 form':<18} {form or 'not known'}")
    return 0


OPS: dict[str, Callable[[Backend, argparse.Namespace], Coroutine[Any, Any, int]]] = {
    "get": _get,
    "set": _set,
    "dump": _dump,
    "diff": _diff,
    "restore": _restore,
    "monitor": _monitor,
    "identity": _identity,
}
