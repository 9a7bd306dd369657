"""Probe (issue 29): the e-stop's power-off step on a drive that has stopped answering.

Stop category 1 (docs/safety.md): zero and START off at once, then SERVO and brake release
off "at the latest 1.0 s after" (``ESTOP_POWER_OFF_S``). Found from outside on the
simulator: when the drive has gone quiet a little before the e-stop, the unit is declared
OFFLINE (1 s without an answer) before the power-off is due, its frames drop to the
offline probe rate (one a second), and the frame with SERVO and brake release off goes
out only at the next probe — 1.7–2.6 s after the e-stop in the recordings. A drive that
hears the host but whose answers are lost keeps its servo on and its brake released that
long. Judged here by an observer of its own on the virtual bus (not the supervisor's
state, not the suite's monitor: that one judges the frames that went out, and the late
one is already off).
"""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from abh3_supervisor.clients.control import ControlClient
from tests.support.can_observer import Observer
from tests.support.served import Served
from tests.support.wire_monitor import ESTOP_POWER_OFF_S, ESTOP_SLACK_S, WireMonitor

pytestmark = pytest.mark.wallclock

CHANNEL = "probe-estop-offline"
CONFIG = f"""
buses:
  b: {{interface: virtual, channel: {CHANNEL}, simulate: true}}
units:
  - {{name: left, abh3_id: 1, command_rate_hz: 50}}
"""
SERVO, BRAKE = (1 << 0) | (1 << 12), 1 << 28  # 2021 input word (§5)
QUIET_FRAMES = 20  # 0.4 s of 50 Hz frames unanswered before the e-stop


def test_estop_powers_off_a_drive_that_went_quiet_within_the_bound(
    tmp_path: Path, wire: WireMonitor
) -> None:
    observer = Observer(CHANNEL)
    try:
        with Served(tmp_path, CONFIG) as served:
            client = ControlClient(served.path)
            try:
                for text in ("SERVO ON ON", "BRAKE ON ON", "START ON ON"):
                    client.call("command", unit="left", text=text)
                observer.drain()
                while not observer.next_word(2.0)[1] & SERVO:  # the drive has been told
                    pass
                client.call("simulate", unit="left", silent=True)
                for _ in range(QUIET_FRAMES):
                    observer.next_word(2.0)
                client.call("estop")
                estop_at = time.time()
                wire.estop()
                off_at = None
                while off_at is None:
                    t, word = observer.next_word(4.0)
                    if not word & (SERVO | BRAKE):
                        off_at = t
                late = off_at - estop_at
                assert late <= ESTOP_POWER_OFF_S + ESTOP_SLACK_S, (
                    f"SERVO and brake release went off {late:.3f} s after the e-stop "
                    f"(bound {ESTOP_POWER_OFF_S} s): the drive went quiet before it"
                )
                client.call("simulate", unit="left", silent=False)
                client.call("clear_estop")
                wire.clear()
            finally:
                client.close()
    finally:
        observer.close()
