"""A TUI attached to a supervisor's socket, headless, for the timing benchmark: run as
``python -m benchmarks.tui_client SOCKET SECONDS`` in a process of its own, as an operator's
TUI would be. It cycles through the tabs so every screen renders."""

from __future__ import annotations

import asyncio
import sys
from pathlib import Path

from abh3_supervisor.clients.link import Link
from abh3_supervisor.clients.mirror import Mirror
from abh3_supervisor.clients.tui.app import STATE_HZ, TABS, SupervisorApp
from abh3_supervisor.clients.tui.run import yield_to_the_buses


async def main(path: Path, seconds: float) -> None:
    yield_to_the_buses()  # as `abh3 tui` and `abh3 run` do
    link = await Link.open(path)
    mirror = Mirror.from_hello(await link.call("hello", name="bench"))
    app = SupervisorApp(mirror, link, owner=False)
    await link.call("subscribe", events=True, state_hz=STATE_HZ)
    task = asyncio.ensure_future(app.run_async(headless=True, size=(160, 50)))
    loop = asyncio.get_running_loop()
    end = loop.time() + seconds
    tabs = list(TABS.values())
    i = 0
    while loop.time() < end and not task.done():
        await asyncio.sleep(1.0)
        app.action_tab(tabs[i % len(tabs)])
        i += 1
    app.exit()
    await task
    await link.close()


if __name__ == "__main__":
    asyncio.run(main(Path(sys.argv[1]), float(sys.argv[2])))
