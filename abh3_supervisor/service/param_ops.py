"""Parameter access on a running supervisor, on its event loop: the one implementation
behind ``abh3 param`` on its own bus and the control socket's ``param_*`` methods.

A request goes to the unit's parameter channel in the bus scheduler and is awaited; the
channel always ends an exchange (J1939 timeouts, 1.25 s per step), and ``CALL_DEADLINE``
bounds it again. A write is refused while the servo is on — as this supervisor commands it,
or as the drive reports it when asked at that moment (``force`` overrides) — reads the old
value first and the new one back, and is logged in the event log with both (an
:class:`OperatorAction`).
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from typing import TYPE_CHECKING

from abh3_supervisor.core.verify import CHECKS, State
from abh3_supervisor.core.verifying import verify_units
from abh3_supervisor.errors import Abh3Error, CommandError, RunError
from abh3_supervisor.params import table
from abh3_supervisor.params.session import Result
from abh3_supervisor.params.telabh3 import Command, Request
from abh3_supervisor.protocol.generation import Generation

if TYPE_CHECKING:
    from abh3_supervisor.core.supervisor import Supervisor

CALL_DEADLINE = 10.0  # s: a transport session always ends within ~4 s; never hang past this
CHECKED = frozenset(c.address for c in CHECKS)  # the settings the start-up check compares


class ParamFailed(RunError):
    """The drive or the transport failed a request, or a write was refused: exit 1."""


def shown(address: int, word: int, monitor: bool = False) -> str:
    return table.display(table.to_value(word, table.kind_of(address, monitor)))


class ParamOps:
    def __init__(self, sup: Supervisor, wake: Callable[[str], None]) -> None:
        self.sup, self.wake = sup, wake

    async def call(self, unit: str, request: Request) -> Result:
        bus = self.sup.unit(unit).cfg.bus  # CommandError for an unknown unit
        future: asyncio.Future[Result] = asyncio.get_running_loop().create_future()

        def done(result: Result) -> None:
            if not future.done():
                future.set_result(result)

        channel = self.sup.schedulers[bus].params[unit]
        channel.submit(request, done)
        self.wake(bus)
        try:
            # asyncio.timeout, not wait_for: 3.11's wait_for can swallow a cancellation that
            # arrives as the answer does, and a stop signal would then be lost
            async with asyncio.timeout(CALL_DEADLINE):
                return await future
        except TimeoutError:
            channel.withdraw(done, "no answer")
            raise ParamFailed(f"unit {unit}: no answer within {CALL_DEADLINE:g} s") from None

    async def read(self, unit: str, command: Command, address: int) -> int:
        """The 32-bit word of a ``CP`` or ``CM`` read."""
        return check(unit, await self.call(unit, Request(command, address)))

    def form(self, unit: str) -> str | None:
        """The TelABH3 string form the unit's drive answers, once known (core/verify.py)."""
        from abh3_supervisor.core.verify import form_of

        return form_of(self.sup.schedulers[self.sup.unit(unit).cfg.bus].params[unit])

    async def identity(self, unit: str, address: int) -> str:
        result = await self.call(unit, Request(Command.IDENTITY, address))
        check(unit, result, word=False)
        assert result.reply is not None
        return result.reply.data

    async def servo_on(self, unit: str) -> bool | None:
        """The servo as the drive reports it *now*: in an answer to a request sent after
        this call — a 2023 drive's DP0 reply (every exchange carries its control word), a
        2021 drive's broadcast 1, asked for whatever the unit's mask polls. None if no such
        answer comes within the unit's timeout. A word heard before never decides."""
        state = self.sup.unit(unit)
        since = self.sup.clock()
        if state.layout.generation is Generation.G2023:
            answered = self.sup.expect_exchange(unit, since)
        else:
            answered = self.sup.expect_status(unit, 1, since)
            self.sup.request_status(unit, 1)
        try:
            async with asyncio.timeout(state.cfg.timeout_ms / 1000):
                await answered
        except TimeoutError:
            return None
        control = state.words.get("control")  # just set from that answer
        return None if control is None else bool(control & state.layout.servo.both)

    async def write(
        self, unit: str, address: int, word: int, *, force: bool, source: str
    ) -> tuple[int, int]:
        """Write ``word``; (old, read back). Under the unit's parameter-write lock (the
        motion gate: its safe word on the wire, SERVO ON refused from anyone until the write
        ends), taken only while this supervisor does not command its servo on; then refused
        unless the drive, asked now, reports its servo off — ``force`` skips that question."""
        try:
            with self.sup.param_write(unit):
                if not force:
                    await self.refuse_unless_servo_off(unit)
                old = await self.read(unit, Command.PARAM, address)
                check(
                    unit, await self.call(unit, Request(Command.PARAM, address, word)), word=False
                )
                new = await self.read(unit, Command.PARAM, address)
                if address in CHECKED and self.sup.unit(unit).verify.state is not State.OFF:
                    # a setting the start-up check compares (0x4117 among them): checked
                    # again now, still under the lock — a drive left without its
                    # command-zero timeout is held before it can move (core/verify.py)
                    await verify_units(self.sup, [unit])
        except CommandError as exc:
            raise ParamFailed(f"unit {unit}: {exc}: not writing") from None  # the lock refused
        name = table.label(address)
        self.sup.audit(
            source,
            unit,
            f"parameter 0x{address:04X} {name}: {shown(address, old)} ({old:08X}) → "
            f"{shown(address, new)} ({new:08X})",
        )
        if new != word:
            raise ParamFailed(
                f"unit {unit}: 0x{address:04X} reads back {shown(address, new)}, "
                f"not {shown(address, word)}"
            )
        return old, new

    async def refuse_unless_servo_off(self, unit: str) -> None:
        """:class:`ParamFailed` unless the drive reports its servo off in answer to a
        question asked now (the lock already keeps this supervisor's SERVO off)."""
        servo = await self.servo_on(unit)
        if servo is not False:
            why = "reports its servo ON" if servo else "did not answer whether its servo is on"
            raise ParamFailed(f"unit {unit} {why}: not writing")


def check(unit: str, result: Result, word: bool = True) -> int:
    """A read's word (``word``), or 0; :class:`ParamFailed` with the reason otherwise."""
    request = result.request
    monitor = request.command is Command.MONITOR
    where = f"unit {unit}: {request.command.value} {table.label(request.address, monitor)}"
    if result.error is not None:
        raise ParamFailed(f"{where}: {result.error}")
    assert result.reply is not None
    if not result.reply.ok:
        raise ParamFailed(f"{where}: the drive refused it (NAK): no such address?")
    if not word:
        return 0
    try:
        return result.reply.word
    except Abh3Error as exc:
        raise ParamFailed(f"{where}: {exc}") from None
