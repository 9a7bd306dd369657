"""The pushed state: built unit by unit between the buses' turns, shared, never stale."""

from __future__ import annotations

import asyncio
import itertools
import json
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, cast

import pytest

from abh3_supervisor.config import parse_config
from abh3_supervisor.core.supervisor import Supervisor
from abh3_supervisor.service import state_push
from abh3_supervisor.service.snapshot import supervisor_state, unit_json, unit_state
from abh3_supervisor.service.state_push import SharedState
from tests.support.rig import Rig

pytestmark = pytest.mark.wallclock  # real time: runtimes, sockets, processes

if TYPE_CHECKING:
    from abh3_supervisor.runtime.bus_runtime import Runtime

UNITS = "".join(f"  - {{name: u{i}, bus: b, abh3_id: {i + 1}, host_id: 100}}\n" for i in range(8))


@dataclass
class FakeRuntime:
    """What the push reads of a runtime: the supervisor and the pumps (none here)."""

    supervisor: Supervisor
    pumps: dict[str, Any] = field(default_factory=dict)


def runtime() -> Runtime:
    config = parse_config(f"buses: {{b: {{interface: virtual}}}}\nunits:\n{UNITS}")
    return cast("Runtime", FakeRuntime(Supervisor(config, clock=lambda: 12.5)))


def decoded(data: bytes) -> dict[str, Any]:
    assert data.endswith(b"\n") and data.count(b"\n") == 1
    message = json.loads(data)
    assert message["jsonrpc"] == "2.0" and message["method"] == "state"
    return message["params"]  # type: ignore[no-any-return]


def test_the_push_is_the_state_method_s_snapshot_byte_for_byte_in_meaning() -> None:
    rt = runtime()
    slowed = {"by": 2, "late_ms": 37.2}  # the pace's word (service/view_pace.py), as given
    data = asyncio.run(SharedState(rt, 0.005, lambda: slowed).latest())
    method = {**supervisor_state(rt.supervisor, {}), "slowed": slowed}  # as server._state
    assert decoded(data) == json.loads(json.dumps(method))


def test_the_loop_runs_between_units_while_a_snapshot_is_built(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A bus deadline falling due mid-build waits for one unit, not for the snapshot."""
    rt = runtime()
    read = 0
    turns: list[int] = []  # units read when each loop turn came

    def counted(sup: Supervisor, unit: Any) -> bytes:
        nonlocal read
        read += 1
        return unit_json(sup, unit)

    monkeypatch.setattr(state_push, "unit_json", counted)

    async def main() -> None:
        build = asyncio.ensure_future(SharedState(rt, 0.005).latest())
        while not build.done():
            turns.append(read)
            await asyncio.sleep(0)
        assert len(decoded(build.result())["units"]) == 8

    asyncio.run(main())
    # the loop had a turn after every unit: never more than one unit read between turns
    assert read == 8 and turns[-1] == 8
    assert max(b - a for a, b in itertools.pairwise(turns)) == 1


def test_clients_on_one_tick_share_one_build() -> None:
    rt = runtime()
    builds = 0

    async def main() -> list[bytes]:
        nonlocal builds
        shared = SharedState(rt, 0.005)
        real = shared._build

        async def counted(generation: int, began: float) -> bytes:
            nonlocal builds
            builds += 1
            return await real(generation, began)

        shared._build = counted  # type: ignore[method-assign]
        first = await asyncio.gather(*(shared.latest() for _ in range(5)))
        return [*first, await shared.latest()]  # within share_s: the cached bytes

    datas = asyncio.run(main())
    assert builds == 1 and len(set(datas)) == 1


def test_a_change_during_a_build_is_in_what_every_waiting_client_gets() -> None:
    """An e-stop confirmed to a client must not be followed by a push that predates it."""
    rt = runtime()
    sup = rt.supervisor

    async def main() -> tuple[bytes, bytes]:
        shared = SharedState(rt, 10.0)  # shared for long: only forget() makes it rebuild
        waiting = asyncio.ensure_future(shared.latest())
        await asyncio.sleep(0)  # the build has begun, estop still False in its head
        await asyncio.sleep(0)
        sup.gate.latch(sup.clock())  # what the e-stop call does …
        shared.forget()  # … and the server after every state-changing call
        return await waiting, await shared.latest()

    during, after = asyncio.run(main())
    assert decoded(during)["estop"] is True
    assert decoded(after)["estop"] is True


def test_a_live_unit_s_pushed_state_is_its_state_in_meaning(rig: Rig) -> None:
    """Status records, flag words of both generations, inputs and verification: spliced
    in encoded once per value, and still what ``state`` says, push after push."""
    for _ in range(3):
        rig.run(0.35)  # status packets and words change between pushes
        for unit in rig.sup.units.values():
            ours = json.loads(unit_json(rig.sup, unit))
            assert ours == json.loads(json.dumps(unit_state(rig.sup, unit)))
            assert ours["status"] and ours["words"] and ours["inputs"]["names"]
