"""``abh3 param``: read, write, dump, diff and restore drive parameters, watch monitors,
read the identity — over the configuration's own buses.

The buses run as in ``abh3 run`` but every unit as ``role: monitor`` without start-up
commands: this tool never moves a motor and never fights a supervisor that does. Parameter
traffic shares the bus with the DP0 exchanges (scheduler/core.py). Writes ask first
(``--yes`` skips), are refused while the unit reports its servo on (``--force``), and are
logged with the old and the new value. Exit: 0 done, 1 a drive or the transport failed,
2 a mistake on the command line or in a file.
"""

from __future__ import annotations

# light imports only: the parser is built for every `abh3` command; the buses, YAML and
# the runtime load in run()
import argparse
import asyncio
import logging
import sys
from collections.abc import Awaitable, Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from abh3_supervisor.errors import Abh3Error, CommandError, RunError
from abh3_supervisor.params import table
from abh3_supervisor.params.session import Result
from abh3_supervisor.params.telabh3 import Command, Request

if TYPE_CHECKING:
    from abh3_supervisor.config import Config
    from abh3_supervisor.core.supervisor import Supervisor
    from abh3_supervisor.params.files import ParamValue

log = logging.getLogger("abh3")
IDENTITY_ADDRESSES = (0x0, 0x2, 0x4, 0x5, 0x8, 0xC)
CALL_DEADLINE = 10.0  # s: a transport session always ends within ~4 s; never hang past this


class ParamFailed(RunError):
    """The drive or the transport failed a request: exit 1."""


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser("param", help="read and write drive parameters (TelABH3 over CAN)")
    p.add_argument("--config", "-c", type=Path, required=True, help="the YAML of the buses")
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
    mon.add_argument("--interval", type=float, default=0.5, metavar="S")
    mon.add_argument("--count", type=int, default=0, metavar="N", help="stop after N rounds")
    ident = ops.add_parser("identity", help="the drive's identity strings (firmware version)")
    ident.add_argument("unit")
    for op in (put, restore):
        op.add_argument("--yes", "-y", action="store_true", help="do not ask")
        op.add_argument("--force", action="store_true", help="write even while the servo is on")


class Access:
    """Requests to a unit's parameter channel on a running runtime (on its loop)."""

    def __init__(self, sup: Supervisor, wake: Callable[[str], None]) -> None:
        self.sup, self.wake = sup, wake

    async def call(self, unit: str, request: Request) -> Result:
        bus = self.sup.unit(unit).cfg.bus
        future: asyncio.Future[Result] = asyncio.get_running_loop().create_future()

        def done(result: Result) -> None:
            if not future.done():
                future.set_result(result)

        channel = self.sup.schedulers[bus].params[unit]
        channel.submit(request, done)
        self.wake(bus)
        try:
            return await asyncio.wait_for(future, CALL_DEADLINE)
        except TimeoutError:
            channel.cancel("no answer")
            raise ParamFailed(f"unit {unit}: no answer within {CALL_DEADLINE:g} s") from None

    async def word(self, unit: str, command: Command, address: int) -> int:
        result = await self.call(unit, Request(command, address))
        return _word(unit, result)

    async def servo_on(self, unit: str) -> bool | None:
        """As the drive reports it; None if it has not within the unit's timeout."""
        state = self.sup.unit(unit)
        for _ in range(int(state.cfg.timeout_ms / 20) + 1):
            control = state.words.get("control")
            if control is not None:
                return bool(control & state.layout.servo.both)
            await asyncio.sleep(0.02)  # waiting for the drive's first report, real time
        return None


def _word(unit: str, result: Result) -> int:
    where = f"unit {unit}: {result.request.command.value} {table.label(result.request.address)}"
    if result.error is not None:
        raise ParamFailed(f"{where}: {result.error}")
    assert result.reply is not None
    if not result.reply.ok:
        raise ParamFailed(f"{where}: the drive refused it (NAK): no such address?")
    try:
        return result.reply.word
    except Abh3Error as exc:
        raise ParamFailed(f"{where}: {exc}") from None


def monitor_only(config: Config) -> Config:
    """Every unit as a monitor without start-up commands: this tool never commands motion."""
    import dataclasses

    from abh3_supervisor.config.model import Role

    units = {
        n: dataclasses.replace(u, role=Role.MONITOR, startup=()) for n, u in config.units.items()
    }
    return dataclasses.replace(config, units=units)


def run(args: argparse.Namespace) -> int:
    from abh3_supervisor.config import load_config

    config = monitor_only(load_config(args.config))
    if args.unit not in config.units:
        raise CommandError(f"no unit '{args.unit}' (units: {', '.join(config.units)})")
    return asyncio.run(_run_on_own_bus(config, lambda access: OPS[args.op](access, args)))


async def _run_on_own_bus(config: Config, op: Callable[[Access], Awaitable[int]]) -> int:
    from abh3_supervisor.core.eventlog import EventLog
    from abh3_supervisor.core.supervisor import OperatorAction, SupervisorEvent
    from abh3_supervisor.runtime.bus_runtime import Runtime

    async with Runtime(config) as rt:
        events = EventLog(rt.supervisor)

        def on_event(event: SupervisorEvent) -> None:
            if isinstance(event, OperatorAction):  # the writes: nothing else is news here
                line = events.line(event)
                if line is not None:
                    log.log(*line)

        rt.supervisor.subscribe(on_event)
        return await op(Access(rt.supervisor, lambda bus: rt.pumps[bus].wake()))


# ------------------------------------------------------------ operations


def _value(address: int, word: int) -> ParamValue:
    from abh3_supervisor.params.files import ParamValue

    return ParamValue(address, word)


def _line(v: ParamValue) -> str:
    return f"0x{v.address:04X} {v.name:<28} {v.shown:>12}  ({v.word:08X})"


async def _get(access: Access, args: argparse.Namespace) -> int:
    for text in args.addresses:
        address = table.parse_address(text)
        print(_line(_value(address, await access.word(args.unit, Command.PARAM, address))))
    return 0


async def _read_all(access: Access, unit: str, addresses: Sequence[int]) -> list[ParamValue]:
    return [_value(a, await access.word(unit, Command.PARAM, a)) for a in addresses]


async def _dump(access: Access, args: argparse.Namespace) -> int:
    from abh3_supervisor.params import files

    values = await _read_all(access, args.unit, [e.address for e in table.PARAMETERS])
    if args.output is None:
        sys.stdout.write(files.dumps(values, "yaml", args.unit))
    else:
        files.write(args.output, values, args.unit)
        print(f"{len(values)} parameters of {args.unit} written to {args.output}")
    return 0


async def _differences(
    access: Access, unit: str, path: Path
) -> list[tuple[ParamValue, ParamValue]]:
    from abh3_supervisor.params import files

    wanted = files.read(path)
    have = await _read_all(access, unit, [v.address for v in wanted])
    return [(h, w) for h, w in zip(have, wanted, strict=True) if h.word != w.word]


def _show(differences: list[tuple[ParamValue, ParamValue]], unit: str, path: Path) -> None:
    for have, want in differences:
        print(f"0x{have.address:04X} {have.name:<28} drive {have.shown:>12}  file {want.shown:>12}")
    print(f"{len(differences)} parameter(s) of {unit} differ from {path}")


async def _diff(access: Access, args: argparse.Namespace) -> int:
    _show(await _differences(access, args.unit, args.file), args.unit, args.file)
    return 0


async def _may_write(access: Access, args: argparse.Namespace, what: str) -> bool:
    servo = await access.servo_on(args.unit)
    if servo is not False and not args.force:
        why = "reports its servo ON" if servo else "has not reported its servo state"
        raise ParamFailed(f"unit {args.unit} {why}: not writing (--force to write anyway)")
    if args.yes:
        return True
    if not sys.stdin.isatty():
        raise CommandError(f"{what}: confirm with --yes when not on a terminal")
    return input(f"{what}? [y/N] ").strip().lower() in ("y", "yes")


async def _write(access: Access, unit: str, old: ParamValue, new: ParamValue) -> None:
    result = await access.call(unit, Request(Command.PARAM, new.address, new.word))
    _ack(unit, result)
    check = _value(new.address, await access.word(unit, Command.PARAM, new.address))
    access.sup.audit(
        "param",
        unit,
        f"parameter 0x{new.address:04X} {new.name}: {old.shown} ({old.word:08X}) → "
        f"{check.shown} ({check.word:08X})",
    )
    if check.word != new.word:
        raise ParamFailed(
            f"unit {unit}: 0x{new.address:04X} reads back {check.shown}, not {new.shown}"
        )


def _ack(unit: str, result: Result) -> None:
    if result.error is not None or result.reply is None or not result.reply.ok:
        _word(unit, result)  # raises with the reason


async def _set(access: Access, args: argparse.Namespace) -> int:
    address = table.parse_address(args.address)
    try:
        value = float(args.value)
    except ValueError:
        raise CommandError(f"'{args.value}' is not a number") from None
    new = _value(address, table.to_word(value, table.kind_of(address)))
    old = _value(address, await access.word(args.unit, Command.PARAM, address))
    print(_line(old))
    if old.word == new.word:
        print("already set: nothing written")
        return 0
    what = f"set {args.unit} 0x{address:04X} {new.name}: {old.shown} → {new.shown}"
    if not await _may_write(access, args, what):
        print("not written")
        return 0
    await _write(access, args.unit, old, new)
    print(f"written: {_line(new)}")
    return 0


async def _restore(access: Access, args: argparse.Namespace) -> int:
    differences = await _differences(access, args.unit, args.file)
    _show(differences, args.unit, args.file)
    if not differences:
        return 0
    if not await _may_write(access, args, f"write {len(differences)} parameter(s) to {args.unit}"):
        print("not written")
        return 0
    for have, want in differences:
        await _write(access, args.unit, have, want)
    print(f"{len(differences)} parameter(s) of {args.unit} restored from {args.file}")
    return 0


async def _monitor(access: Access, args: argparse.Namespace) -> int:
    addresses = [table.parse_address(a, monitor=True) for a in args.addresses]
    rounds = 0
    while not args.count or rounds < args.count:
        values = []
        for a in addresses:
            word = await access.word(args.unit, Command.MONITOR, a)
            value = table.to_value(word, table.kind_of(a, monitor=True))
            values.append(f"{table.label(a, monitor=True)}={table.display(value)}")
        print(" ".join(values), flush=True)
        rounds += 1
        if not args.count or rounds < args.count:
            await asyncio.sleep(args.interval)
    return 0


async def _identity(access: Access, args: argparse.Namespace) -> int:
    for address in IDENTITY_ADDRESSES:
        result = await access.call(args.unit, Request(Command.IDENTITY, address))
        _ack(args.unit, result)
        assert result.reply is not None
        name = table.IDENTITY.get(address) or f"BI 0x{address:X}"
        print(f"{name:<18} {result.reply.data}")
    return 0


OPS: dict[str, Callable[[Access, argparse.Namespace], Awaitable[int]]] = {
    "get": _get,
    "set": _set,
    "dump": _dump,
    "diff": _diff,
    "restore": _restore,
    "monitor": _monitor,
    "identity": _identity,
}
