"""The pump's deadline timer: fires once per arming, can be re-armed and cancelled."""

from __future__ import annotations

import asyncio

import pytest

from abh3_supervisor.scheduler import timer as timer_module
from abh3_supervisor.scheduler.timer import DeadlineTimer

pytestmark = pytest.mark.wallclock  # real time: runtimes, sockets, processes


@pytest.mark.parametrize("precise", [True, False], ids=["timerfd", "call_at"])
def test_fires_at_the_deadline_and_not_after_cancel(
    precise: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    if not precise:
        monkeypatch.setattr(timer_module, "_LIBC", None)

    async def scenario() -> None:
        loop = asyncio.get_running_loop()
        fired: list[float] = []
        done = loop.create_future()

        def callback() -> None:
            fired.append(loop.time())
            if not done.done():
                done.set_result(None)

        t = DeadlineTimer(loop, callback)
        if precise and timer_module._LIBC is None:
            pytest.skip("no timerfd on this platform")
        assert t.precise is precise
        t.arm(loop.time() + 10)
        deadline = loop.time() + 0.02
        t.arm(deadline)  # an earlier deadline replaces the armed one
        t.arm(loop.time() + 5)  # a later one keeps it (the callback re-arms when it fires)
        await asyncio.wait_for(done, 5)
        assert fired[0] >= deadline - 1e-4 and len(fired) == 1
        t.arm(loop.time() + 0.01)
        t.cancel()
        other = loop.create_future()
        loop.call_later(0.05, other.set_result, None)  # a later event proves no firing
        await other
        assert len(fired) == 1
        t.close()

    asyncio.run(scenario())
