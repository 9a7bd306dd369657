"""Shared fixtures: fake-clock setups and a guard against leaked virtual buses."""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest
from can.interfaces import virtual

from abh3_supervisor.config import parse_config
from tests.support.rig import TWO_UNITS, Rig
from tests.support.served import served_thread  # noqa: F401  (the `served` fixture)
from tests.support.wire_monitor import INVARIANTS, WireMonitor
from tests.support.wire_tap import tap


@pytest.fixture
def rig() -> Rig:
    return Rig(parse_config(TWO_UNITS, "two.yaml"))


@pytest.fixture(autouse=True)
def wire(request: pytest.FixtureRequest) -> Iterator[WireMonitor]:
    """The wire monitor (tests/support/wire_monitor.py) on every bus of every test; a test
    opts out of one invariant with ``@pytest.mark.wire_allow(NAME, reason=...)``."""
    monitor = WireMonitor()
    for mark in request.node.iter_markers("wire_allow"):
        unknown = set(mark.args) - set(INVARIANTS)
        assert not unknown and mark.kwargs.get("reason"), f"wire_allow: {mark}"
        monitor.allowed.update(mark.args)
    with pytest.MonkeyPatch.context() as patches:  # its own: a test's undo() keeps it
        tap(monitor, patches)
        yield monitor
    monitor.check()  # what the fixtures' teardown sent (a runtime left at the end)


@pytest.hookimpl(wrapper=True)
def pytest_runtest_call(item: pytest.Item) -> Iterator[None]:
    """A broken invariant fails the test itself, whatever it was testing."""
    result = yield
    monitor = getattr(item, "funcargs", {}).get("wire")
    if isinstance(monitor, WireMonitor):
        monitor.check()
    return result


@pytest.fixture(autouse=True)
def no_leaked_buses() -> Iterator[None]:
    yield
    leaked = {name: len(ch) for name, ch in virtual.channels.items() if ch}
    virtual.channels.clear()
    assert not leaked, f"virtual buses left open: {leaked}"


@pytest.fixture(autouse=True)
def private_runtime_dir() -> Iterator[None]:
    """Supervisors the tests start serve their sockets here, never in the user's own
    runtime directory (where `abh3 tui` and `abh3 status` would find them)."""
    saved = os.environ.get("XDG_RUNTIME_DIR")
    runtime = Path(tempfile.mkdtemp(dir="/tmp", prefix="abh3t-"))  # short: AF_UNIX paths
    os.environ["XDG_RUNTIME_DIR"] = str(runtime)
    try:
        yield
    finally:
        if saved is None:
            os.environ.pop("XDG_RUNTIME_DIR", None)
        else:
            os.environ["XDG_RUNTIME_DIR"] = saved
        shutil.rmtree(runtime, ignore_errors=True)
