"""The fake-clock rig: a supervisor and simulated drives on one :class:`Timeline`."""

from __future__ import annotations

import math
from collections.abc import Callable

from abh3_supervisor.config import Config
from abh3_supervisor.core.inputs import InputSource
from abh3_supervisor.core.supervisor import Supervisor
from abh3_supervisor.simulator import SimBus
from abh3_supervisor.simulator.timeline import Timeline

TWO_UNITS = """
buses:
  b: {interface: virtual, channel: t, simulate: true}
units:
  - {name: left, abh3_id: 1, command_rate_hz: 50, broadcast: {mask: 0x7f, rate_hz: 14}}
  - {name: right, abh3_id: 3, protocol: "2023", velocity_model: motor, command_rate_hz: 50,
     broadcast: {mask: 0x0f, rate_hz: 8}}
"""


class Rig:
    """A supervisor and simulated drives on one fake-clock bus."""

    def __init__(
        self, config: Config, bitrate: int | None = None, *, whole_robots: bool = True
    ) -> None:
        self.timeline = Timeline(bitrate)
        self.config = config
        self.sup = Supervisor(config, clock=self.timeline.clock, whole_robots=whole_robots)
        bus = next(iter(config.buses))
        sim_cfg = config.buses[bus].simulate
        assert sim_cfg is not None
        self.sim = SimBus.for_units(
            config.units_on(bus), sim_cfg, 0.0, robots=config.robots.values()
        )
        self.scheduler = self.sup.schedulers[bus]
        self.timeline.add(self.scheduler, after_step=lambda: self.sup.dispatch(bus))
        self.timeline.add(self.sim)
        self.timeline.add(Clockwork(self.sup))
        self.events: list[object] = []
        self.sup.subscribe(self.events.append)
        for unit in config.units:  # the test is the operator: its API commands stand
            self.sup.arbiter.add(_TestSource(f"api:{unit}", (unit,), timeout=math.inf))

    def run(self, seconds: float) -> None:
        self.timeline.run_until(self.timeline.now + seconds)

    def drive(self, unit: str):  # type: ignore[no-untyped-def]
        return self.sim.drives[self.config.units[unit].abh3_id]

    def own(self, unit: str) -> str:
        """A source present for the whole test that owns ``unit``'s motion (pass it as
        ``source=``): the API's own source is streamed and lapses after 0.5 s."""
        return present(self.sup, unit)


def present(sup: Supervisor, unit: str) -> str:
    """Register a test's input source for ``unit`` that never lapses; its name."""
    name = f"test:{unit}"
    if name not in sup.arbiter.sources:
        sup.arbiter.add(_TestSource(name, (unit,), timeout=math.inf))
    return name


class _TestSource(InputSource):
    def start(self, feed: object) -> None:
        pass

    def stop(self) -> None:
        pass


class Deaf:
    """A Timeline node that hears nothing: it only acts when polled."""

    def on_frame(self, arbitration_id: int, data: bytes, now: float) -> None:
        pass

    def on_send_failed(self, arbitration_id: int) -> None:
        pass

    def on_bad_frame(self, arbitration_id: int, now: float, reason: str) -> None:
        pass


class Clockwork(Deaf):
    """The runtime's timers on the fake clock: the arbitration expired at its deadline
    (``Runtime._arbitrate``), the supervisor's ``call_at`` calls run when due (the
    e-stop's power-off deadline)."""

    def __init__(self, sup: Supervisor) -> None:
        self.sup = sup
        self.calls: list[tuple[float, Callable[[], None]]] = []
        sup.call_at = self.at

    def at(self, when: float, fn: Callable[[], None]) -> None:
        self.calls.append((when, fn))

    def poll(self, now: float) -> list[tuple[int, bytes]]:
        due = [fn for when, fn in self.calls if when <= now]
        self.calls = [(when, fn) for when, fn in self.calls if when > now]
        for fn in due:
            fn()
        if now >= self.sup.arbiter.next_deadline():
            self.sup.arbiter.poll(now)
        return []

    def next_deadline(self) -> float:
        return min([self.sup.arbiter.next_deadline(), *(when for when, _ in self.calls)])
