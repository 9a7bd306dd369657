"""Random sequences against a served supervisor, judged on the wire after every step.

A hypothesis rule-based state machine drives a supervisor on the simulator through its
control socket as clients would: clients connect, command (``SERVO``, ``START``, ``VEL``),
stream (``velocity``, ``twist``), prove they are alive or go quiet, and leave; the
operator e-stops and clears; parameter writes race the rest on connections of their own;
``verify`` runs; simulated drives fall silent, raise error bits or slow their parameter
transport. After every step the wire monitor (tests/support/wire_monitor.py) must have
seen nothing break an invariant; at the end the supervisor stops and each commanded
drive's last frame must be the safe word.

Real time: the supervisor runs on its own loop, so every step waits for DP0 commands on
the wire (the gate decided that many frames since), never for a fixed time.

A failure prints the shortest sequence of steps and the seed. Rerun it with
``pytest tests/test_gate_properties.py --hypothesis-seed=SEED`` (the seed is in the
failure's message), or paste the printed ``@reproduce_failure(...)`` blob onto
:func:`test_the_gate_holds_its_invariants_on_the_wire`.
"""

from __future__ import annotations

import contextlib
import random
import shutil
import tempfile
import threading
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, settings
from hypothesis import seed as with_seed
from hypothesis import strategies as st
from hypothesis.stateful import (
    Bundle,
    RuleBasedStateMachine,
    consumes,
    get_state_machine_test,
    invariant,
    precondition,
    rule,
)

from abh3_supervisor.clients.control import ControlClient
from abh3_supervisor.config.model import Fault, FaultKind
from abh3_supervisor.errors import Abh3Error
from abh3_supervisor.params.telabh3 import pack_float
from tests.support.served import Served
from tests.support.wire_monitor import WireMonitor

pytestmark = pytest.mark.wallclock

CONFIG = """
buses:
  b: {interface: virtual, channel: gate, simulate: true}
units:
  - {name: left, abh3_id: 1, command_rate_hz: 50, broadcast: {mask: 0x03, rate_hz: 10}}
  - {name: right, abh3_id: 3, protocol: "2023", command_rate_hz: 50, verify: refuse,
     broadcast: {mask: 0x03, rate_hz: 10}}
"""
UNITS = {"left": 1, "right": 3}
STEP_FRAMES = 4  # each step waits for this many DP0 commands: two periods of both units
PERIOD_S = 0.02  # at 50 Hz; a silent drive is commanded more slowly: a step waits 5 periods
BUDGET = settings(
    max_examples=15,
    stateful_step_count=20,
    deadline=None,
    print_blob=True,
    report_multiple_bugs=False,
    suppress_health_check=[HealthCheck.too_slow],
)

units = st.sampled_from(sorted(UNITS))
switches = st.sampled_from(
    ["SERVO ON ON", "SERVO OFF OFF", "START ON ON", "START OFF OFF", "BRAKE ON ON", "BRAKE OFF OFF"]
)
speeds = st.integers(-400, 400).map(float)


class Gate(RuleBasedStateMachine):
    """One served supervisor per example; the monitor judges its wire throughout."""

    clients = Bundle("clients")

    def __init__(self, wire: WireMonitor) -> None:
        super().__init__()
        self.wire = wire
        self.tmp = Path(tempfile.mkdtemp(dir="/tmp", prefix="gate-"))  # AF_UNIX: short
        self.served = Served(self.tmp, CONFIG).__enter__()
        self.open: list[ControlClient] = []
        self.writers: list[threading.Thread] = []
        self.operator = self.connect_client()  # the e-stop's own connection
        self.estopped = False
        self.failed = False  # an invariant failed already: the teardown adds no second report

    def connect_client(self) -> ControlClient:
        client = ControlClient(self.served.path)
        self.open.append(client)
        return client

    def step(self, frames: int = STEP_FRAMES) -> None:
        self.wire.wait_commands(frames, timeout=(frames + 5) * PERIOD_S * 2)

    # ------------------------------------------------------------ clients

    @precondition(lambda self: len(self.open) < 5)
    @rule(target=clients)
    def connect(self) -> ControlClient:
        return self.connect_client()

    @rule(client=consumes(clients))
    def leave(self, client: ControlClient) -> None:
        client.close()
        self.open.remove(client)
        self.step()

    @rule(client=clients, unit=units, text=switches)
    def command(self, client: ControlClient, unit: str, text: str) -> None:
        with contextlib.suppress(Abh3Error):  # refused (e-stop, a write): said, not obeyed
            client.call("command", unit=unit, text=text)
        self.step()

    @rule(client=clients, unit=units, ay=speeds, bx=speeds)
    def vel(self, client: ControlClient, unit: str, ay: float, bx: float) -> None:
        with contextlib.suppress(Abh3Error):
            client.call("command", unit=unit, text=f"VEL {ay:g} {bx:g}")
        self.step()

    @rule(client=clients, unit=units, ay=speeds, bx=speeds, twist=st.booleans())
    def stream(self, client: ControlClient, unit: str, ay: float, bx: float, twist: bool) -> None:
        with contextlib.suppress(Abh3Error):
            if twist:
                client.call("twist", unit=unit, linear_x=ay / 1000, angular_z=bx / 1000)
            else:
                client.call("velocity", unit=unit, ay=ay, bx=bx)
        self.step()

    @rule(client=clients)
    def alive(self, client: ControlClient) -> None:
        with contextlib.suppress(Abh3Error):
            client.call("alive")
        self.step()

    @rule(periods=st.integers(1, 30))
    def quiet(self, periods: int) -> None:
        """Every client goes quiet for a while (past the 0.5 s freshness at the most)."""
        self.step(2 * periods)

    # ------------------------------------------------------------ the operator

    @rule()
    def estop(self) -> None:
        self.operator.call("estop")
        self.wire.estop()  # in effect once answered: judged from the next frame on
        self.estopped = True
        self.step()

    @precondition(lambda self: self.estopped)
    @rule()
    def clear(self) -> None:
        self.wire.clear()  # nothing is judged as e-stopped from here on
        self.estopped = False
        self.operator.call("clear_estop")
        self.step()

    @rule(unit=units)
    def verify(self, unit: str) -> None:
        with contextlib.suppress(Abh3Error):
            self.operator.call("verify", unit=unit)
        self.step()

    @precondition(lambda self: len(self.writers) < 4)
    @rule(unit=units, value=st.sampled_from([600, 800, 1000]))
    def param_write(self, unit: str, value: int) -> None:
        """A write on a connection of its own, left in flight: the next steps race it."""

        def write() -> None:
            with (
                contextlib.suppress(Abh3Error),
                contextlib.closing(ControlClient(self.served.path, timeout=10)) as client,
            ):
                client.call("param_write", unit=unit, address=0x5000, word=pack_float(value))

        thread = threading.Thread(target=write, daemon=True)
        self.writers.append(thread)
        thread.start()
        self.step()

    # ------------------------------------------------------------ the drives

    @rule(unit=units, silent=st.booleans())
    def silence(self, unit: str, silent: bool) -> None:
        self.operator.call("simulate", unit=unit, silent=silent)
        self.step()

    @rule(unit=units, bits=st.sampled_from([1 << 6, 1 << 2]))
    def error_bits(self, unit: str, bits: int) -> None:
        self.served.on_loop(self.drive(unit).inject_error, bits)
        self.step()

    @rule(unit=units, delay_ms=st.sampled_from([40.0, 120.0]))
    def slow_transport(self, unit: str, delay_ms: float) -> None:
        drive = self.drive(unit)
        slow = Fault(FaultKind.TP_SLOW_DT, at_s=0.0, for_s=1e6, delay_ms=delay_ms)
        self.served.on_loop(setattr, drive, "faults", (*drive.faults, slow))
        self.step()

    def drive(self, unit: str) -> Any:
        assert self.served.rt is not None
        return self.served.rt.sims["b"].drives[UNITS[unit]]

    # ------------------------------------------------------------ judged

    @invariant()
    def the_wire_is_clean(self) -> None:
        self.failed = True
        self.wire.check()
        self.failed = False

    def teardown(self) -> None:
        try:
            for thread in self.writers:
                thread.join(15)
            for client in self.open:
                client.close()
            for unit in UNITS:  # confirmed stops: the way out in 0.1 s, not after 1 s
                self.served.on_loop(setattr, self.drive(unit), "silent", False)
            self.served.__exit__(None, None, None)  # the way out: judged at the bus's close
        finally:
            self.wire.clear()
            shutil.rmtree(self.tmp, ignore_errors=True)
        if not self.failed:
            self.wire.check()  # the way out
        self.wire.violations.clear()


def test_the_gate_holds_its_invariants_on_the_wire(
    wire: WireMonitor, request: pytest.FixtureRequest
) -> None:
    chosen = request.config.getoption("hypothesis_seed", None)
    seed = int(chosen) if chosen is not None else random.SystemRandom().getrandbits(32)

    class OnThisWire(Gate):
        def __init__(self) -> None:
            super().__init__(wire)

    run = with_seed(seed)(get_state_machine_test(OnThisWire, settings=BUDGET))
    print(f"hypothesis seed {seed}: rerun with --hypothesis-seed={seed}")
    try:
        run()
    except BaseException as exc:
        exc.add_note(f"rerun with: pytest {__file__} --hypothesis-seed={seed}")
        raise
