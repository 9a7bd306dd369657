"""Races the issue found, judged on the wire by the monitor (tests/support/wire_monitor.py):
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
from tests.support.wire_monitor import WireMonitor

pytestmark = pytest.mark.wallclock

ROUNDS = 40  # the issue saw 4 writes in 40 go out after SERVO on


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
