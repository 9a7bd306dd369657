"""Where the wire monitor listens: every path a frame takes in the tests.

In-process frames cross either python-can's ``virtual`` bus (runtimes, pumps, raw test
buses) or the fake-clock :class:`Timeline` (the rig). Both are tapped once the frame is on
the wire; the simulated drives are told apart from the host by the machine a pump or a
timeline node runs (a :class:`SimBus`). Subprocesses are out of reach: their recordings
are judged by :func:`tests.support.safe_word.assert_stopped_in`.
"""

from __future__ import annotations

import threading
import time
from typing import Any

import can
import pytest
from can.interfaces import virtual
from can.interfaces.virtual import VirtualBus

from abh3_supervisor.scheduler.pump import BusPump
from abh3_supervisor.simulator.bus import SimBus
from abh3_supervisor.simulator.timeline import Timeline
from tests.support.wire_monitor import Violation, WireMonitor


def tap(monitor: WireMonitor, monkeypatch: pytest.MonkeyPatch) -> None:
    """Route every frame of this test through ``monitor`` (undone by ``monkeypatch``)."""
    lock = threading.Lock()  # plugins' and clients' threads send too

    def guarded(fn: Any, *args: Any) -> None:
        with lock:
            try:
                fn(*args)
            except Exception as exc:  # a bug here must fail the test, not the product
                monitor.report(Violation("monitor", "?", 0.0, 0, repr(args[:3]), repr(exc)))

    def virtual_key(bus: VirtualBus) -> tuple[str, object]:
        return ("virtual", bus.channel_id)

    def watch_virtual(bus: VirtualBus) -> None:
        monitor.bus(virtual_key(bus), f"virtual:{bus.channel_id}")

    send, shutdown, pump_init = VirtualBus.send, VirtualBus.shutdown, BusPump.__init__

    def tapped_send(self: VirtualBus, msg: can.Message, timeout: float | None = None) -> None:
        send(self, msg, timeout)
        if msg.is_extended_id and not (msg.is_error_frame or msg.is_remote_frame):
            data = bytes(msg.data)
            guarded(watch_virtual, self)
            guarded(
                monitor.frame, virtual_key(self), self, msg.arbitration_id, data, time.monotonic()
            )  # asyncio's loop.time()

    def tapped_shutdown(self: VirtualBus) -> None:
        was_open = getattr(self, "_open", False)
        shutdown(self)
        if was_open:
            last = self.channel_id not in virtual.channels
            guarded(monitor.closed, virtual_key(self), self, last)

    def tapped_pump_init(self: BusPump, bus: can.BusABC, machine: Any, **kwargs: Any) -> None:
        pump_init(self, bus, machine, **kwargs)
        if isinstance(bus, VirtualBus) and isinstance(machine, SimBus):
            guarded(watch_virtual, bus)
            guarded(monitor.drives, virtual_key(bus), machine, bus)

    monkeypatch.setattr(VirtualBus, "send", tapped_send)
    monkeypatch.setattr(VirtualBus, "shutdown", tapped_shutdown)
    monkeypatch.setattr(BusPump, "__init__", tapped_pump_init)

    add, finish = Timeline.add, Timeline._finish_transmission

    def tapped_add(self: Timeline, machine: Any, after_step: Any = None) -> int:
        index = add(self, machine, after_step)
        monitor.bus(self, f"timeline@{id(self):x}", lambda: self.now)
        if isinstance(machine, SimBus):
            monitor.drives(self, machine, index)
        return index

    def tapped_finish(self: Timeline) -> None:
        on_wire = self._on_wire
        finish(self)
        if on_wire is not None:
            sender, arbitration_id, data, _ = on_wire
            guarded(monitor.frame, self, sender, arbitration_id, data, self.now)

    monkeypatch.setattr(Timeline, "add", tapped_add)
    monkeypatch.setattr(Timeline, "_finish_transmission", tapped_finish)
