"""The TUI's socket connection (clients/link.py): proof of life while connected, and a
detach that the service sees at once."""

from __future__ import annotations

import asyncio
import itertools
import json
import tempfile
from pathlib import Path

import pytest

from abh3_supervisor.clients import link as link_module
from abh3_supervisor.clients.link import ALIVE_S, Link
from abh3_supervisor.runtime.bus_runtime import Runtime
from abh3_supervisor.service.server import ControlServer
from tests.support.served import no_clients, served

pytestmark = pytest.mark.wallclock  # real time: runtimes, sockets, processes


def test_alive_is_a_bare_notification_every_0_2_s_while_connected() -> None:
    async def scenario(path: Path) -> None:
        loop = asyncio.get_running_loop()
        heard: asyncio.Queue[tuple[float, dict[str, object]]] = asyncio.Queue()
        ended = loop.create_future()

        async def client(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
            while line := await reader.readline():
                await heard.put((loop.time(), json.loads(line)))
            ended.set_result(True)
            writer.close()

        server = await asyncio.start_unix_server(client, path=str(path))
        link = await Link.open(path)
        times = []
        for _ in range(4):
            t, message = await asyncio.wait_for(heard.get(), 2)
            assert message == {"jsonrpc": "2.0", "method": "alive"}  # no id: no reply wanted
            times.append(t)
        gaps = [b - a for a, b in itertools.pairwise(times)]
        assert all(gap >= ALIVE_S * 0.9 for gap in gaps), gaps  # paced, not a flood
        await link.close()
        assert await asyncio.wait_for(ended, 2)  # closing ends the connection …
        assert heard.empty()  # … and the proof with it
        server.close()
        await server.wait_closed()

    with tempfile.TemporaryDirectory(dir="/tmp") as tmp:
        asyncio.run(scenario(Path(tmp) / "fake.sock"))


def test_the_service_answers_nothing_to_alive_and_sees_a_detach_at_once() -> None:
    """A notification the service does not know gets no error reply (JSON-RPC); the next
    request's reply is the next line. ``detach_now`` ends the connection without the loop."""

    async def check(rt: Runtime, server: ControlServer, path: Path) -> None:
        reader, writer = await asyncio.open_unix_connection(str(path))
        writer.write(link_module.ALIVE * 3 + b'{"jsonrpc":"2.0","id":7,"method":"state"}\n')
        reply = json.loads(await asyncio.wait_for(reader.readline(), 5))
        assert reply["id"] == 7 and "units" in reply["result"]
        writer.close()
        await no_clients(server)
        link = await Link.open(path)
        assert (await link.call("hello", name="tui"))["name"].startswith("tui")
        assert len(server.clients) == 1
        link.detach_now()
        await asyncio.wait_for(link.closed, 2)
        await no_clients(server)
        await link.close()

    served(check)
