"""A TUI attached to a supervisor's socket, headless, for the timing benchmark: run as
``python -m benchmarks.tui_client SOCKET SECONDS [STATES]`` in a process of its own, as an
operator's TUI would be. It cycles through the tabs so every screen renders. ``STATES``: a
file that gets a line per pushed state it applied, ``wall-time slowdown`` (the state's
``slowed``: 1 at the rate asked for), written as they come (the client is killed)."""

from __future__ import annotations

import asyncio
import sys
import time
from pathlib import Path
from typing import Any, TextIO

from abh3_supervisor.clients.link import Link
from abh3_supervisor.clients.mirror import Mirror
from abh3_supervisor.clients.tui.app import STATE_HZ, TABS, SupervisorApp
from abh3_supervisor.clients.tui.run import yield_to_the_buses


def _logged(mirror: Mirror, out: TextIO) -> None:
    """Each state the mirror takes, a line in ``out``."""
    apply = mirror.apply

    def applied(state: dict[str, Any]) -> bool:
        took = apply(state)
        if took:
            out.write(f"{time.time()} {(state.get('slowed') or {}).get('by', 1)}\n")
            out.flush()
        return took

    mirror.apply = applied  # type: ignore[method-assign]


async def main(path: Path, seconds: float, states: Path | None) -> None:
    yield_to_the_buses()  # as `abh3 tui` and `abh3 run` do
    link = await Link.open(path)
    mirror = Mirror.from_hello(await link.call("hello", name="bench"))
    if states is not None:
        _logged(mirror, states.open("w"))
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
    states = Path(sys.argv[3]) if len(sys.argv) > 3 else None
    asyncio.run(main(Path(sys.argv[1]), float(sys.argv[2]), states))
