"""The in-process simulator's bus (simulator/local_bus.py): python-can's virtual bus whose
drives' side has a doorbell — a descriptor that rings when a bus of ours on the channel
sends, read by the pump as any descriptor is — and how a runtime on the simulator opens
and reads its two buses."""

from __future__ import annotations

import asyncio
import select
import time

import can
import pytest

from abh3_supervisor.config import parse_config
from abh3_supervisor.runtime.bus_runtime import Runtime
from abh3_supervisor.scheduler.sources import FdReader, ThreadReader, source_for
from abh3_supervisor.simulator.local_bus import LocalBus


def frame(ident: int) -> can.Message:
    return can.Message(arbitration_id=ident, is_extended_id=True, data=bytes(8))


def rung(bus: can.BusABC) -> bool:
    return bool(select.select([bus.fileno()], [], [], 0)[0])


def test_a_doorbell_rings_once_for_what_ours_send_and_the_read_silences_it() -> None:
    drives = LocalBus("lb-ring", doorbell=True)
    host = LocalBus("lb-ring")
    try:
        assert not rung(drives)
        host.send(frame(1))
        host.send(frame(2))
        assert rung(drives)
        first = drives.recv(0)
        assert first is not None and first.arbitration_id == 1 and not rung(drives)
        host.send(frame(3))  # sent after the read began: rings again
        assert rung(drives)
        assert [m.arbitration_id for m in iter(lambda: drives.recv(0), None)] == [2, 3]
        drives.send(frame(4))  # the drives' replies: the host's side is read by a thread
        assert (got := host.recv(0)) is not None and got.arbitration_id == 4
    finally:
        host.shutdown()
        drives.shutdown()


def test_another_sender_on_the_channel_is_heard_but_rings_nothing() -> None:
    drives = LocalBus("lb-other", doorbell=True)
    other = can.Bus(interface="virtual", channel="lb-other")
    try:
        other.send(frame(7))
        assert not rung(drives)  # read at the drives' next step
        assert (got := drives.recv(0)) is not None and got.arbitration_id == 7
    finally:
        other.shutdown()
        drives.shutdown()


def test_the_host_side_has_no_descriptor_and_is_read_by_a_thread() -> None:
    async def pick(bus: can.BusABC) -> type:
        source = source_for(bus, asyncio.get_running_loop(), print, print, "b")
        source.stop()
        return type(source)

    drives = LocalBus("lb-kind", doorbell=True)
    host = LocalBus("lb-kind")
    try:
        with pytest.raises(NotImplementedError):
            host.fileno()
        assert asyncio.run(pick(host)) is ThreadReader
        assert asyncio.run(pick(drives)) is FdReader
    finally:
        host.shutdown()
        drives.shutdown()


@pytest.mark.wallclock
def test_a_runtime_on_the_simulator_steps_its_drives_by_the_doorbell() -> None:
    """4 units at 100 Hz: the drives' pump is woken by the doorbell, about once a period,
    and every unit exchanges."""
    units = "".join(
        f"  - {{name: u{i}, abh3_id: {i + 1}, host_id: 100, command_rate_hz: 100,"
        f" broadcast: {{mask: 0}}}}\n"
        for i in range(4)
    )
    config = parse_config(
        f"buses:\n  b: {{interface: virtual, channel: lb-run, simulate: true}}\nunits:\n{units}",
        "lb.yaml",
    )

    async def scenario() -> tuple[int, int, float]:
        async with Runtime(config) as rt:
            sup = rt.supervisor
            assert await sup.wait_exchange("u3", sup.clock(), 3.0)
            (sim_pump,) = rt._sim_pumps
            assert isinstance(sim_pump.bus, LocalBus) and sim_pump.bus.fileno() >= 0
            assert isinstance(rt.pumps["b"].bus, LocalBus)
            received, replies = sim_pump.frames_received, rt.pumps["b"].frames_received
            start = time.monotonic()
            await asyncio.sleep(0.5)
            seconds = time.monotonic() - start
            return (
                sim_pump.frames_received - received,
                rt.pumps["b"].frames_received - replies,
                seconds,
            )

    commands, replies, seconds = asyncio.run(scenario())
    assert commands >= 0.8 * 400 * seconds  # every unit's command reached its drive
    assert replies >= 0.8 * 400 * seconds  # and its reply came back
