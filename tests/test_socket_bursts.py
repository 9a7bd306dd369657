"""Bursts of clients are absorbed: 200 connections at once, then 3000 connect/close cycles,
against a recorded headless run, and no drive's DP0 commands are ever more than 1.5
command periods apart on the bus (read from the CAN recording, as the drive saw them)."""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import pytest

from abh3_supervisor.service.server import MAX_CLIENTS
from benchmarks import bursts

MAX_GAP_PERIODS = 1.5


@pytest.mark.wallclock
def test_a_crowd_and_a_churn_of_clients_leave_the_command_rate_alone() -> None:
    with tempfile.TemporaryDirectory(dir="/tmp") as tmp:  # short: AF_UNIX paths
        with bursts.recorded_run(Path(tmp)) as (sock, record):
            start = time.time()
            crowd = bursts.flood(sock, 200)
            cycles = bursts.churn(sock, 3000)
            bursts.settled(sock)  # answered: everything before it was handled
            end = time.time()
        worst = bursts.dp0_gaps(record, start, end)
    assert (crowd.accepted, crowd.refused, crowd.failed) == (MAX_CLIENTS, 200 - MAX_CLIENTS, 0)
    assert cycles == 3000
    assert worst <= MAX_GAP_PERIODS, f"a DP0 gap of {worst:.2f} command periods"
