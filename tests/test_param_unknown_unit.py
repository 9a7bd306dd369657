"""`abh3 param` names an unknown unit as every front end does (issue 21): the Supervisor's
own words, `error: no unit named 'x' (units: a, b)`, exit 2 — on its own buses (before any
opens) and through a running supervisor's socket."""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest

from abh3_supervisor.clients.cli import main
from abh3_supervisor.config import parse_config
from abh3_supervisor.core.supervisor import Supervisor
from abh3_supervisor.errors import CommandError
from abh3_supervisor.runtime.bus_runtime import Runtime

UNITS = "units:\n  - {name: left, abh3_id: 1}\n  - {name: right, abh3_id: 3}\n"
OPS = (
    ["get", "nobody", "0x5000"],
    ["set", "nobody", "SPEED_AY_0", "900", "--yes"],
    ["dump", "nobody"],
    ["identity", "nobody"],
    ["monitor", "nobody", "VELOCITY_AY", "--count", "1"],
)


def supervisors_words() -> str:
    """What Supervisor.unit says for the same file: the form to use everywhere."""
    sup = Supervisor(parse_config(f"buses: {{b: {{interface: virtual}}}}\n{UNITS}"), clock=float)
    with pytest.raises(CommandError) as info:
        sup.unit("nobody")
    return f"error: {info.value}\n"


def test_the_form_is_the_supervisors() -> None:
    assert supervisors_words() == "error: no unit named 'nobody' (units: left, right)\n"


@pytest.mark.wallclock
@pytest.mark.parametrize("argv", OPS, ids=[a[0] for a in OPS])
def test_on_its_own_buses_before_any_opens(
    argv: list[str], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "robot.yaml"  # a bus that cannot open here: refused before trying
    path.write_text(f"buses:\n  b: {{interface: socketcan, channel: can-absent}}\n{UNITS}")
    assert main(["param", "-c", str(path), *argv]) == 2
    assert capsys.readouterr().err == supervisors_words()


@pytest.mark.wallclock
def test_through_a_running_supervisor(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from abh3_supervisor.service.server import ControlServer

    service = parse_config(
        f"buses: {{b: {{interface: virtual, channel: p-unknown, simulate: true}}}}\n{UNITS}",
        "s.yaml",
    )
    sock = tmp_path / "s.sock"

    async def scenario() -> list[int]:
        async with Runtime(service) as rt:
            server = ControlServer(rt, None, sock)
            await server.start()
            try:
                return [
                    await asyncio.to_thread(main, ["param", "--connect", str(sock), *argv])
                    for argv in OPS
                ]
            finally:
                await server.close()

    assert asyncio.run(scenario()) == [2] * len(OPS)
    err = capsys.readouterr().err
    assert err == supervisors_words() * len(OPS)
