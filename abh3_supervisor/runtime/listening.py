"""Listen before touching a drive: does another host already command it?

``abh3 commission`` and ``abh3 param -c`` open their own buses; on a bus where another
host (``abh3 run``, a test script, a second copy) keeps a drive under command, two hosts
would fight over it. A host that keeps a drive under command must send it a command within
the drive's command-zero timeout (0x4117, the unit's ``drive_timeout_ms``), or the drive
stops itself: so listening that long, plus :data:`~abh3_supervisor.core.foreign.LISTEN_MARGIN_S`,
hears every such host. Nothing is sent while listening. The evidence is core/foreign.py's:
only commanding frames (a DP0 command, a parameter session) refuse; a reader does not.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Iterable, Mapping

import can

from abh3_supervisor.config.model import Config, UnitConfig
from abh3_supervisor.core.foreign import LISTEN_MARGIN_S, Foreign, ForeignWatch
from abh3_supervisor.errors import BusInUse
from abh3_supervisor.runtime.bus_runtime import as_opened, open_bus


def listen_time(units: Iterable[UnitConfig]) -> float:
    """How long to listen [s]: the longest command-zero timeout of the drives, plus the
    margin (a host keeping a drive under command sends at least that often)."""
    return max((u.drive_timeout_ms for u in units), default=0) / 1000 + LISTEN_MARGIN_S


class _Hear(can.Listener):
    def __init__(self, watch: ForeignWatch, loop: asyncio.AbstractEventLoop) -> None:
        self.watch, self.loop = watch, loop

    def on_message_received(self, msg: can.Message) -> None:
        if msg.is_extended_id and not (msg.is_error_frame or msg.is_remote_frame):
            self.watch.frame(msg.arbitration_id, bytes(msg.data), self.loop.time())


async def commanders(
    config: Config, drives: Mapping[str, Mapping[int, str]], seconds: float
) -> list[tuple[str, Foreign]]:
    """Listen ``seconds`` on each bus of ``drives`` (bus → drive address → unit), all at
    once, sending nothing: every (bus, host) heard commanding one of those drives."""
    loop = asyncio.get_running_loop()
    watches = {bus: ForeignWatch(addresses) for bus, addresses in drives.items()}
    with contextlib.ExitStack() as stack:
        for bus, watch in watches.items():
            opened = open_bus(as_opened(config.buses[bus]))
            stack.callback(opened.shutdown)
            notifier = can.Notifier(opened, [_Hear(watch, loop)], timeout=0.05, loop=loop)
            stack.callback(notifier.stop)
        await asyncio.sleep(seconds)  # the listening itself: nothing to wait for but time
    return [
        (bus, host)
        for bus, watch in watches.items()
        for host in watch.hosts.values()
        if host.commanding
    ]


async def refuse_if_commanded(config: Config, units: Iterable[str], tool: str) -> None:
    """Raise :class:`BusInUse` naming every host heard commanding a drive of ``units``."""
    touched = [config.units[name] for name in units]
    drives: dict[str, dict[int, str]] = {}
    for unit in touched:
        drives.setdefault(unit.bus, {})[unit.abh3_id] = unit.name
    seconds = listen_time(touched)
    heard = await commanders(config, drives, seconds)
    if heard:
        lines = [f"bus {bus}: {host.text()}" for bus, host in heard]
        raise BusInUse(
            f"{tool}: refused: another host already commands a drive it would touch "
            f"(heard in {seconds:.2f} s of listening, nothing sent):\n  "
            + "\n  ".join(lines)
            + "\nstop that host first (an `abh3 run` serving these drives: use "
            "`--connect` to work through it where the tool offers it)"
        )
