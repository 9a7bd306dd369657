"""Probe (issue 29): an e-stop cleared before its power-off step never powers off.

docs/safety.md: the e-stop is stop category 1 — zero and START off at once, SERVO and brake
release off once the drive reports it stopped, "at the latest 1.0 s after"; clearing it
means "START, SERVO and motion must be given anew". Found from outside on the simulator
(a drive that decelerates slowly): e-stop, clear 0.3 s later while the drive is still
turning down — SERVO and brake release stay on in every frame after, for as long as the
run lasts (until the way out, 1.8 s later in the recording). The clear cancels the power
off instead of completing it, so SERVO is never "given anew": it was never taken.
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

CHANNEL = "probe-estop-clear-early"
CONFIG = f"""
buses:
  b: {{interface: virtual, channel: {CHANNEL}, simulate: {{time_constant_ms: 3000}}}}
units:
  - {{name: left, abh3_id: 1, command_rate_hz: 50}}
"""
SERVO, BRAKE = (1 << 0) | (1 << 12), 1 << 28  # 2021 input word (protocol doc §5)
FRAMES = 15  # 0.3 s at 50 Hz


def test_clearing_an_estop_early_still_powers_off_within_the_bound(
    tmp_path: Path, wire: WireMonitor
) -> None:
    observer = Observer(CHANNEL)
    try:
        with Served(tmp_path, CONFIG) as served:
            client = ControlClient(served.path)
            try:
                for text in ("SERVO ON ON", "BRAKE ON ON", "START ON ON", "VEL 1000 0"):
                    client.call("command", unit="left", text=text)
                for _ in range(FRAMES):  # under way: the drive turns up on its slow ramp
                    observer.next_word(2.0)
                    client.call("alive")
                client.call("estop")
                estop_at = time.time()
                wire.estop()
                for _ in range(FRAMES):  # still turning down: the power-off is not due yet
                    observer.next_word(2.0)
                client.call("clear_estop")
                wire.clear()
                off_at = None
                while off_at is None:
                    t, word = observer.next_word(2.0)
                    if not word & (SERVO | BRAKE):
                        off_at = t
                    elif t > estop_at + 2 * ESTOP_POWER_OFF_S:
                        break
                assert off_at is not None and off_at - estop_at <= (
                    ESTOP_POWER_OFF_S + ESTOP_SLACK_S
                ), "SERVO and brake release still on after the e-stop was cleared early"
            finally:
                client.close()
    finally:
        observer.close()
