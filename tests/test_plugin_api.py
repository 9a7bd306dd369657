"""The public plugin API: one module, importable at runtime, that the built-ins alone use;
the read-only view plugins get; the e-stop and owner events; the tick; ending a run."""

from __future__ import annotations

import ast
import asyncio
import logging
import math
import pydoc
import re
import threading
import typing
from pathlib import Path
from typing import Any

import pytest

from abh3_supervisor import plugin_api
from abh3_supervisor.config import parse_config
from abh3_supervisor.config.source import Section, Source
from abh3_supervisor.core.state import UnitState
from abh3_supervisor.core.supervisor import (
    EstopChange,
    OperatorAction,
    OwnerChange,
    SupervisorEvent,
)
from abh3_supervisor.errors import CommandError
from abh3_supervisor.plugin_api import (
    FlagChange,
    InputFeed,
    InputSource,
    Notice,
    SupervisorView,
    UnitView,
    hookimpl,
)
from abh3_supervisor.plugin_host import hookspecs, tick
from abh3_supervisor.plugin_host.host import PluginHost
from abh3_supervisor.runtime.headless import run_headless
from tests.support.foreign_host import TimelineHost
from tests.support.rig import TWO_UNITS, Rig, present, set_velocity

ROOT = Path(__file__).resolve().parent.parent
BUILTINS = ROOT / "plugins" / "abh3_plugins"
WORDS = ("error", "alarm", "control", "io", "inputs", "drive_inputs")


def test_the_builtins_import_nothing_of_ours_but_the_plugin_api() -> None:
    wrong = []
    for path in sorted(BUILTINS.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0:
                names = [node.module or ""]
                if node.module == "abh3_supervisor":  # `from abh3_supervisor import x`
                    names = [f"abh3_supervisor.{a.name}" for a in node.names]
            else:
                continue
            for name in names:
                if name.split(".")[0] == "abh3_supervisor" and name != "abh3_supervisor.plugin_api":
                    wrong.append(f"{path.relative_to(ROOT)}:{node.lineno} imports {name}")
    assert not wrong, "\n".join(wrong)


def test_every_public_name_is_there_at_runtime_and_says_where_it_comes_from() -> None:
    assert plugin_api.API_VERSION == "1.3"
    missing = [n for n in plugin_api.__all__ if not hasattr(plugin_api, n)]
    assert not missing
    for name in ("hookimpl", "InputSource", "Feedback", "Setpoint", "Notice", "FlagChange"):
        assert name in plugin_api.__all__
    # nothing only for type checkers: help() and isinstance work on what plugins receive
    for module in (plugin_api, hookspecs):
        assert "TYPE_CHECKING" not in Path(module.__file__ or "").read_text(encoding="utf-8")
    text = re.sub(".\b", "", pydoc.render_doc(plugin_api.FlagChange))  # no bold
    assert "in module abh3_supervisor.core.supervisor" in text
    assert "abh3_supervisor.plugin_api.FlagChange" in text
    # every hook's annotations resolve at runtime, to what plugin_api exports
    for name in ("abh3_flags", "abh3_notice", "abh3_estop", "abh3_owner", "abh3_start"):
        hints = typing.get_type_hints(getattr(hookspecs, name))
        for hint in hints.values():
            assert hint is type(None) or getattr(plugin_api, hint.__name__) is hint


@pytest.mark.parametrize("generation", ["2021", "2023"])
def test_every_word_an_event_names_has_bit_names_in_both_generations(generation: str) -> None:
    """The old guide's ``layout.words[change.word]`` raised KeyError('drive_inputs')."""
    text = TWO_UNITS.replace('protocol: "2023"', f'protocol: "{generation}"')
    cfg = parse_config(text, "g.yaml")
    unit = UnitView(UnitState.initial(cfg.units["right"]))
    for word in WORDS:
        assert isinstance(unit.names(word, 0xFFFFFFFF), list)
        assert isinstance(unit.labels(word, 0xFFFFFFFF, "ja"), list)
    assert unit.names("drive_inputs", 1) == unit.names("inputs", 1) != []
    with pytest.raises(KeyError, match="no flag word 'nope'"):
        unit.names("nope", 1)


def test_the_view_reads_and_never_writes() -> None:
    rig = Rig(parse_config(TWO_UNITS, "v.yaml"))
    loop = asyncio.new_event_loop()
    try:
        view = SupervisorView(rig.sup, loop, "probe")
        assert list(view.units) == ["left", "right"]
        left = view.units["left"]
        assert left.setpoint == rig.sup.units["left"].setpoint
        with pytest.raises(AttributeError):
            left.inputs = 0  # type: ignore[misc]
        with pytest.raises(TypeError):
            view.units["x"] = left  # type: ignore[index]
        for motion in ("set_velocity", "set_twist", "apply", "zero"):
            assert not hasattr(view, motion)
        set_velocity(rig.sup, "left", 0.0, 0.0, source=present(rig.sup, "left"))
        assert view.owner("left") == "test:left"  # live, not a copy taken at start
        change = FlagChange("right", 0.0, "drive_inputs", None, 1)
        assert view.flag_names(change) == (left.names("inputs", 1), [])
        with pytest.raises(CommandError, match="not 0-6"):
            view.request_status("left", 7)
        with pytest.raises(CommandError, match="no unit named 'x'"):
            view.owner("x")
        with pytest.raises(ValueError, match="not a logging level"):
            view.notice(5, "x")
    finally:
        loop.close()


def test_the_views_e_stop_and_its_clearing_are_the_operators_audited() -> None:
    """API 1.1: a plugin its user allows (the mqtt plugin's allow_estop_clear) clears the
    e-stop as an operator does, through the supervisor's own clear, audited."""
    rig = Rig(parse_config(TWO_UNITS, "c.yaml"))
    seen: list[SupervisorEvent] = []
    rig.sup.subscribe(seen.append)
    loop = asyncio.new_event_loop()
    try:
        view = SupervisorView(rig.sup, loop, "fleet")
        view.emergency_stop("scada says stop")
        loop.run_until_complete(asyncio.sleep(0))  # what call_soon_threadsafe handed over
        assert rig.sup.estop
        view.clear_emergency_stop("scada says go")
        loop.run_until_complete(asyncio.sleep(0))
        assert not rig.sup.estop
        counters = view.bus_counters()
        assert list(counters) == list(rig.sup.config.buses)
        assert all(c.send_errors == 0 and c.state == "ok" for c in counters.values())
    finally:
        loop.close()
    audit = [(e.source, e.action) for e in seen if isinstance(e, OperatorAction)]
    assert audit == [
        ("plugin fleet", "emergency stop: scada says stop"),
        ("plugin fleet", "clear the emergency stop: scada says go"),
    ]
    estops = [(e.latched, e.source) for e in seen if isinstance(e, EstopChange)]
    assert estops == [
        (True, "plugin fleet: scada says stop"),
        (False, "plugin fleet: scada says go"),
    ]


def test_the_view_says_which_other_hosts_are_heard_on_a_units_drive() -> None:
    """API 1.1: another host commanding drive 1 (left's), on the fake clock: its record,
    ``lately`` while heard and for foreign.QUIET_S after; right's drive has none."""
    rig = Rig(parse_config(TWO_UNITS, "f.yaml"))
    rig.timeline.add(TimelineHost(1, start=1.0, end=2.0))
    loop = asyncio.new_event_loop()
    try:
        view = SupervisorView(rig.sup, loop, "fleet")
        rig.run(0.9)
        assert view.foreign_hosts("left") == []
        rig.run(0.2)  # its first frames at 1.0, 1.02, …
        (host,) = view.foreign_hosts("left")
        assert (host.source, host.drive, host.commanding, host.lately) == (2, 1, True, True)
        assert host.frames >= 5 and "another host (0x02) commands drive 0x01" in host.text
        assert view.foreign_hosts("right") == []
        rig.run(2.5)  # it left at 2.0, the replies to it with it: quiet over QUIET_S by 3.6
        (gone,) = view.foreign_hosts("left")
        assert not gone.lately and gone.frames > host.frames
        with pytest.raises(CommandError, match="no unit named 'x'"):
            view.foreign_hosts("x")
    finally:
        loop.close()


def test_the_estop_and_owner_changes_are_events() -> None:
    rig = Rig(parse_config(TWO_UNITS, "e.yaml"))
    sup = rig.sup
    seen: list[SupervisorEvent] = []
    sup.subscribe(seen.append)
    source = present(sup, "left")
    sup.apply_text("left", "SERVO ON ON")
    sup.apply_text("left", "START ON ON")
    set_velocity(sup, "left", 100.0, 0.0, source=source)
    set_velocity(sup, "left", 120.0, 0.0, source=source)  # same owner: no event
    sup.emergency_stop("operator")
    sup.emergency_stop("again")  # already latched: no second event
    sup.clear_emergency_stop("tui")
    owners = [(e.unit, e.old, e.new) for e in seen if isinstance(e, OwnerChange)]
    assert owners == [("left", None, "test:left"), ("left", "test:left", None)]
    estops = [(e.latched, e.source) for e in seen if isinstance(e, EstopChange)]
    assert estops == [(True, "operator"), (False, "tui")]


def test_tick_hz_is_the_hosts_key_checked_with_file_and_line() -> None:
    src = Source("t.yaml", {})
    hz, rest = tick.take_rate(Section(src, ("plugins", "p"), {"tick_hz": 20, "a": 1}, None))
    assert (hz, rest) == (20.0, {"a": 1})
    assert tick.take_rate(Section(src, ("plugins", "p"), {"a": 1}, None))[0] == tick.DEFAULT_HZ
    tick.take_rate(Section(src, ("plugins", "p"), {"tick_hz": 0}, None))
    assert any("plugins.p.tick_hz" in p for p in src.problems)


def test_the_ticker_posts_ticks_until_closed() -> None:
    posted: list[tuple[str, dict[str, Any]]] = []
    three = threading.Event()

    def post(hook: str, kwargs: dict[str, Any]) -> None:
        posted.append((hook, kwargs))
        if len(posted) == 3:
            three.set()

    ticker = tick.Ticker("p", 100.0, lambda: 42.0, post)
    assert three.wait(5.0)
    ticker.close()
    assert not ticker.thread.is_alive()
    assert posted[0] == ("abh3_tick", {"t": 42.0})


class _Hold(InputSource):
    """Holds its unit at zero from the start: an owner the arbitration names."""

    def start(self, feed: InputFeed) -> None:
        feed.velocity(0.0, 0.0)

    def stop(self) -> None:
        pass


class Probe:
    """A plugin that watches the new hooks, trips the e-stop on its first tick and ends
    the run when it hears the latch."""

    def __init__(self) -> None:
        self.views: list[object] = []
        self.ticks: list[float] = []
        self.estops: list[EstopChange] = []
        self.owners: list[OwnerChange] = []
        self.notices: list[Notice] = []
        self.done = threading.Event()

    @hookimpl
    def abh3_start(self, supervisor: SupervisorView) -> None:
        self.views.append(supervisor)
        self.view = supervisor

    @hookimpl
    def abh3_input_sources(self, register: Any, supervisor: SupervisorView) -> None:
        self.views.append(supervisor)
        register(_Hold("probe-hold", ("left",), timeout=math.inf))

    @hookimpl
    def abh3_tick(self, t: float) -> None:
        self.ticks.append(t)
        if len(self.ticks) == 1:
            self.view.notice(logging.WARNING, "hello")
        if any(o.new == "probe-hold" for o in self.owners) and not self.estops:
            self.view.emergency_stop("probe says stop")

    @hookimpl
    def abh3_owner(self, change: OwnerChange) -> None:
        self.owners.append(change)

    @hookimpl
    def abh3_notice(self, notice: Notice) -> None:
        self.notices.append(notice)

    @hookimpl
    def abh3_estop(self, event: EstopChange) -> None:
        self.estops.append(event)
        if event.latched:
            self.view.end_run("seen the e-stop")

    @hookimpl
    def abh3_stop(self, supervisor: SupervisorView) -> None:
        self.views.append(supervisor)
        self.done.set()


@pytest.mark.wallclock
def test_a_plugin_trips_the_estop_through_its_view_and_ends_the_run_with_exit_0(
    caplog: pytest.LogCaptureFixture,
) -> None:
    config = parse_config(TWO_UNITS.replace("channel: t", "channel: api-probe"), "p.yaml")
    host = PluginHost(config, available={})
    probe = Probe()
    host.register(probe, "probe")
    with caplog.at_level(logging.INFO):
        code = asyncio.run(
            run_headless(config, duration=30.0, record=None, status_interval=0, plugins=host)
        )
    assert code == 0
    assert probe.done.is_set()
    assert len(probe.views) == 3 and all(isinstance(v, SupervisorView) for v in probe.views)
    assert probe.owners[0].new == "probe-hold" and probe.owners[0].unit == "left"
    assert any(o.old == "probe-hold" and o.new is None for o in probe.owners)  # the e-stop
    assert [(e.latched, e.source) for e in probe.estops] == [
        (True, "plugin probe: probe says stop")
    ]
    assert any(n.message == "plugin probe: hello" for n in probe.notices)
    assert "EMERGENCY STOP (plugin probe: probe says stop)" in caplog.text
    assert "operator (plugin probe): emergency stop: probe says stop" in caplog.text  # audited
    assert "plugin probe ends the run: seen the e-stop" in caplog.text
    assert caplog.text.count("stop frame confirmed by the drive") == 2
    assert len(probe.ticks) >= 1
