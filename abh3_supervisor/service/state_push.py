"""The state pushed to subscribed clients, built so that the buses never wait for it.

The supervisor's buses and its control socket share one event loop (the scheduler and
the server are both single-threaded asyncio code; docs/architecture.md, "The bus loop
comes first"). A whole snapshot of 8 units takes about 0.4 ms to build and encode; done in
one go it delays any DP0 exchange that falls due meanwhile by as much. So it is built one
unit at a time, each unit encoded as it is read, and the loop serves the buses between
units: no single step of the push holds the loop for more than one unit's ~50 µs.

Every client woken on the same tick shares one build (``share_s``), and a build already
under way is joined rather than started again. The snapshot's ``t`` is when its build
began; each unit's values carry their own times (feedback ``t``, ``reported.t``). Its
``slowed`` says whether the pushes give way to late buses (service/view_pace.py).
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from abh3_supervisor.service.protocol import dumps
from abh3_supervisor.service.snapshot import bus_state, head, unit_json

if TYPE_CHECKING:
    from abh3_supervisor.runtime.bus_runtime import Runtime


class SharedState:
    """``await latest()``: the encoded ``state`` notification, at most ``share_s`` old,
    and never one whose build began before the last :meth:`forget`."""

    def __init__(
        self,
        rt: Runtime,
        share_s: float,
        slowed: Callable[[], dict[str, Any] | None] = lambda: None,
    ) -> None:
        self.rt, self.share_s, self.slowed = rt, share_s, slowed
        self._generation = 0  # counts forget(): a build of an older generation is stale
        self._cached: tuple[int, float, bytes] = (-1, -1e300, b"")  # generation, began, data
        self._building: tuple[int, asyncio.Future[bytes]] | None = None

    def forget(self) -> None:
        """What a call just changed (an e-stop) must show at the next push: build anew."""
        self._generation += 1

    async def latest(self) -> bytes:
        loop = asyncio.get_running_loop()
        while True:
            wanted = self._generation
            generation, began, data = self._cached
            if generation == wanted and loop.time() - began <= self.share_s:
                return data
            if self._building is None or self._building[0] != wanted:
                self._building = (wanted, asyncio.ensure_future(self._build(wanted, loop.time())))
            data = await asyncio.shield(self._building[1])
            if wanted == self._generation:  # else a call changed things while it was built
                return data

    async def _build(self, generation: int, began: float) -> bytes:
        sup = self.rt.supervisor
        opening = dumps(head(sup, self.slowed()))
        units: list[bytes] = []
        for name, unit in list(sup.units.items()):
            units.append(dumps(name) + b":" + unit_json(sup, unit))
            await asyncio.sleep(0)  # the buses' turn: a deadline may have fallen due
        pumps = self.rt.pumps
        buses = {name: bus_state(sup, name, pumps.get(name)) for name in sup.schedulers}
        data = b"".join(
            (
                b'{"jsonrpc":"2.0","method":"state","params":',
                opening[:-1],  # the object left open: units and buses follow
                b',"units":{',
                b",".join(units),
                b'},"buses":',
                dumps(buses),
                b"}}\n",
            )
        )
        if generation == self._generation:
            self._cached = (generation, began, data)
        if self._building is not None and self._building[0] == generation:
            self._building = None
        return data
