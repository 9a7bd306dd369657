"""Edges the issue found, judged on the wire by the monitor (tests/support/wire_monitor.py):
what the answers say is beside the point here; what reaches the drives is."""

from __future__ import annotations

import contextlib
import threading
from pathlib import Path

import pytest

from abh3_supervisor.clients.control import ControlClient
from abh3_supervisor.errors import Abh3Error
from abh3_supervisor.params.telabh3 import pack_float
from tests.support.served import Served
from tests.support.wire_monitor import ESTOP_POWER_OFF_S, ESTOP_SLACK_S, WireMonitor

pytestmark = pytest.mark.wallclock

ROUNDS = 40  # the issue saw 4 writes in 40 go out after SERVO on
SLOW_CHECK = """
buses:
  b:
    interface: virtual
    channel: slow-check
    simulate:
      faults: [{kind: tp_slow_dt, at_s: 0, for_s: 60, unit: right, delay_ms: 3000}]
units:
  - {name: left, abh3_id: 1, command_rate_hz: 50}
  - {name: right, abh3_id: 3, protocol: "2023", command_rate_hz: 50, verify: refuse,
     startup: ["SERVO ON ON", "BRAKE ON ON", "START ON ON", "VEL 100 0"]}
"""
CHECK_FRAMES = 2 * 50 * 3  # both units at 50 Hz for 3 s: past the check's 2 s bound


def test_servo_on_racing_a_parameter_write_never_puts_the_write_after_servo_on(
    tmp_path: Path, wire: WireMonitor
) -> None:
    """Client A writes a parameter, client B switches SERVO on a moment later: the write
    and SERVO on may not overlap on the wire (a lock, not a check before the write)."""
    with Served(tmp_path) as served:
        a, b = ControlClient(served.path, timeout=10), ControlClient(served.path, timeout=10)
        try:
            for i in range(ROUNDS):

                def write(value: int = 600 + i) -> None:
                    with contextlib.suppress(Abh3Error):  # refused is fine; late is not
                        a.call("param_write", unit="left", address=0x5000, word=pack_float(value))

                writer = threading.Thread(target=write)
                writer.start()
                # B as soon as A's write is under way: its RTS is on the wire, its DT
                # frames wait for the drive's CTS
                assert wire.wait_seen("rts", 1, timeout=5.0)
                with contextlib.suppress(Abh3Error):
                    b.call("command", unit="left", text="SERVO ON ON")
                writer.join(10)
                assert not writer.is_alive()
                b.call("command", unit="left", text="SERVO OFF OFF")
                assert wire.wait_commands(4, timeout=2.0)  # the drive has been told
                wire.check()  # the round that broke it, at once
        finally:
            a.close()
            b.close()


def test_a_refuse_unit_whose_check_cannot_complete_stays_held(
    tmp_path: Path, wire: WireMonitor
) -> None:
    """``verify: refuse`` fails closed: the drive's parameter transport is too slow for the
    check to finish, so the unit is never verified, and its start-up (SERVO, brake, START,
    a VEL) must not reach it."""
    with wire.held(3, "verify: refuse, never verified"), Served(tmp_path, SLOW_CHECK) as served:
        client = ControlClient(served.path)
        try:
            assert wire.wait_commands(CHECK_FRAMES, timeout=10.0)
            with contextlib.suppress(Abh3Error):  # a client's VEL to it: refused, or held
                client.call("command", unit="right", text="VEL 100 50")
            assert wire.wait_commands(20, timeout=2.0)
            wire.check()
        finally:
            client.close()


def test_an_estop_switches_nothing_on_and_powers_off_within_the_bound(
    tmp_path: Path, wire: WireMonitor
) -> None:
    """Stop category 1: zero and START off at once, SERVO and brake off within
    ``ESTOP_POWER_OFF_S``; SERVO, START or brake asked for while latched do not go out."""
    with Served(tmp_path) as served:
        client = ControlClient(served.path)
        try:
            for text in ("SERVO ON ON", "START ON ON", "VEL 100 0"):
                client.call("command", unit="left", text=text)
            client.call("command", unit="right", text="SERVO OFF OFF")
            assert wire.wait_commands(4, timeout=2.0)
            client.call("estop")
            wire.estop()
            for text in ("SERVO ON ON", "BRAKE ON ON", "START ON ON"):
                with contextlib.suppress(Abh3Error):
                    client.call("command", unit="right", text=text)
            # both units for the bound and two periods more (50 Hz)
            assert wire.wait_commands(2 * int((ESTOP_POWER_OFF_S + ESTOP_SLACK_S) * 50) + 4, 5.0)
            wire.check()
            wire.clear()
            client.call("clear_estop")
        finally:
            client.close()
