"""Who owns motion: a standing VEL holds while its owner proves it is alive, goes to zero
on the wire the moment the owner leaves or goes quiet, and an older setpoint never comes
back. On a fake clock, asserting what the simulated drive is told."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import pytest

from abh3_supervisor.core.commands import VelocityCommand
from abh3_supervisor.core.inputs import ZERO, InputArbiter, InputCommand, InputSource
from abh3_supervisor.core.supervisor import Notice
from abh3_supervisor.plugin_host.feed import InputFeed
from abh3_supervisor.protocol import scaling
from abh3_supervisor.scheduler.core import GapEvent
from tests.support.headless import headless_demo
from tests.support.rig import Deaf, Rig, present, set_velocity
from tests.support.wire_monitor import WireMonitor

PERIOD = 0.02  # 50 Hz: TWO_UNITS' command rate


class Source(InputSource):
    def start(self, feed: InputFeed) -> None:
        pass

    def stop(self) -> None:
        pass


class ArbiterNode(Deaf):
    """The arbiter as a machine on the timeline: polled at its deadline, as the runtime's
    deadline timer does; ``alive_until`` makes a client prove it is alive every 0.2 s."""

    def __init__(self, arbiter: InputArbiter) -> None:
        self.arbiter = arbiter
        self.alive: dict[str, float] = {}  # source → until when it proves it is alive
        self.next_touch = 0.0

    def poll(self, now: float) -> list[tuple[int, bytes]]:
        if now >= self.next_touch:
            for name, until in self.alive.items():
                if now < until:
                    self.arbiter.touch(name, now)
            self.next_touch = now + 0.2
        self.arbiter.poll(now)
        return []

    def next_deadline(self) -> float:
        touches = self.next_touch if any(self.alive.values()) else float("inf")
        return min(self.arbiter.next_deadline(), touches)


def owned_rig(rig: Rig) -> tuple[InputArbiter, ArbiterNode]:
    for text in ("SERVO ON ON", "START ON ON"):  # a robot moves only while switched on
        assert rig.sup.apply_text("left", text) == ""
    arb = rig.sup.arbiter
    for name in ("tui1", "client2"):
        arb.add(Source(name, ("left",), priority=50, timeout=0.5))
    node = ArbiterNode(arb)
    rig.timeline.add(node)
    return arb, node


def commanded(rig: Rig) -> float:
    """The velocity the simulated left drive was last told (AY, min⁻¹)."""
    return scaling.VELOCITY.to_physical(rig.drive("left").cmd_raw[0])


def zero_on_the_wire_at(rig: Rig, start: float, limit: float) -> float:
    """When the drive was first told zero after ``start`` (stepping a millisecond at a time)."""
    while rig.timeline.now < start + limit:
        rig.run(0.001)
        if commanded(rig) == 0.0:
            return rig.timeline.now
    raise AssertionError(f"still {commanded(rig)} min⁻¹ {limit} s after {start}")


def test_a_standing_vel_holds_while_its_owner_is_alive_and_stops_within_a_period_when_it_leaves(
    rig: Rig, wire: WireMonitor
) -> None:
    arb, node = owned_rig(rig)
    rig.run(0.2)
    node.alive["tui1"] = 10.0
    arb.submit("tui1", VelocityCommand(777, 0), rig.timeline.now, standing=True)
    rig.run(3.0)  # no repetition: it holds
    assert commanded(rig) == 777.0
    left = rig.timeline.now
    arb.remove("tui1", left)  # the client disconnects
    with wire.unowned(1, left):  # judged on the wire too: no setpoint a period after
        assert zero_on_the_wire_at(rig, left, 1.0) - left <= PERIOD + 0.002
        rig.run(1.0)


def test_an_owner_that_stops_proving_it_is_alive_loses_its_motion_within_0_6_s(
    rig: Rig, wire: WireMonitor
) -> None:
    arb, node = owned_rig(rig)
    lapsed: list[str] = []
    arb.on_lapse = lapsed.append
    node.alive["tui1"] = 2.0  # SIGSTOP at t = 2: no proof of life after it
    arb.submit("tui1", VelocityCommand(300, 0), 0.1, standing=True)
    rig.run(2.0)
    assert commanded(rig) == 300.0
    with wire.unowned(1, 2.0 + 0.5):  # quiet for its 0.5 s timeout: gone from then
        stopped = zero_on_the_wire_at(rig, 2.0, 1.0)
        rig.run(1.0)
    assert stopped - 2.0 <= 0.6
    assert lapsed == ["tui1"]


def test_a_replaced_setpoint_never_comes_back(rig: Rig) -> None:
    """client2's VEL replaces tui1's; when client2 leaves the unit goes to zero, although
    tui1 is still alive and holding its older VEL."""
    arb, node = owned_rig(rig)
    node.alive.update(tui1=10.0, client2=10.0)
    arb.submit("tui1", VelocityCommand(777, 0), 0.1, standing=True)
    rig.run(0.5)
    arb.submit("client2", VelocityCommand(100, 0), rig.timeline.now, standing=True)
    rig.run(0.5)
    assert commanded(rig) == 100.0
    arb.remove("client2", rig.timeline.now)
    rig.run(2.0)
    assert commanded(rig) == 0.0  # never back to 777
    arb.submit("tui1", VelocityCommand(50, 0), rig.timeline.now, standing=True)
    rig.run(0.2)
    assert commanded(rig) == 50.0  # a command given after it counts


def test_a_startup_vel_never_comes_back_after_a_client_took_over(rig: Rig) -> None:
    arb, node = owned_rig(rig)
    # the YAML's startup: VEL, as Supervisor.run_startup gives it (its source startup:left)
    assert rig.sup.startup("left", "VEL 300 0").response == ""
    assert rig.sup.arbiter.owner("left") == "startup:left"
    rig.run(0.3)
    assert commanded(rig) == 300.0
    node.alive["tui1"] = 10.0
    arb.submit("tui1", VelocityCommand(777, 0), rig.timeline.now, standing=True)
    rig.run(0.3)
    arb.remove("tui1", rig.timeline.now)
    rig.run(1.0)
    assert commanded(rig) == 0.0


def test_the_startup_is_an_input_source_under_the_arbitration_rules(rig: Rig) -> None:
    """The YAML's startup: is the input source startup:<unit> (Supervisor.startup, as
    run_startup runs each line): its VEL is owned by that source, a source of higher
    priority outranks it, and once it was replaced it never comes back."""
    for text in ("SERVO ON ON", "START ON ON"):
        assert rig.sup.apply_text("left", text) == ""
    assert rig.sup.startup("left", "VEL 300 0").response == ""
    assert (rig.sup.arbiter.owner("left"), rig.sup.units["left"].setpoint.ay) == (
        "startup:left",
        300,
    )
    rig.sup.arbiter.add(Source("joystick", ("left",), priority=5, timeout=float("inf")))
    rig.sup.arbiter.submit("joystick", VelocityCommand(50, 0), rig.timeline.now)
    assert rig.sup.startup("left", "VEL 200 0").response == ""  # said, but outranked
    assert (rig.sup.arbiter.owner("left"), rig.sup.units["left"].setpoint.ay) == ("joystick", 50)
    rig.run(0.1)
    rig.sup.arbiter.submit("joystick", None, rig.timeline.now)  # the joystick lets go
    rig.run(0.3)
    assert rig.sup.arbiter.owner("left") is None
    assert rig.sup.units["left"].setpoint.ay == 0 and commanded(rig) == 0.0


def test_a_streamed_source_takes_over_at_its_next_sample_but_a_standing_one_does_not() -> None:
    applied: list[tuple[str, InputCommand]] = []
    arb = InputArbiter(apply=lambda u, c: applied.append((u, c)), clock=lambda: 0.0)
    arb.add(Source("joy", ("left",), priority=10, timeout=0.5))
    arb.add(Source("net", ("left",), priority=0, timeout=0.5))
    arb.add(Source("client", ("left",), priority=0, timeout=0.5))
    arb.submit("client", VelocityCommand(5, 0), 0.0, standing=True)
    arb.submit("joy", VelocityCommand(9, 0), 0.1)
    arb.submit("net", VelocityCommand(1, 0), 0.55)  # streamed: fresh, repeated by its source
    arb.touch("client", 0.55)
    arb.poll(0.6)  # joy silent: net (fresh, streamed) takes over; client's standing VEL not
    arb.submit("net", None, 0.7)
    assert applied[-2:] == [("left", VelocityCommand(1, 0)), ("left", ZERO)]


def test_touch_moves_the_deadline_of_a_standing_command_only() -> None:
    arb = InputArbiter(apply=lambda u, c: None, clock=lambda: 0.0)
    arb.add(Source("a", ("left",), timeout=0.5))
    arb.add(Source("b", ("right",), timeout=0.5))
    arb.submit("a", VelocityCommand(1, 0), 0.0, standing=True)
    arb.submit("b", VelocityCommand(1, 0), 0.0)
    arb.touch("a", 0.4)
    arb.touch("b", 0.4)  # a streamed command is fresh from when it was heard, not touched
    assert arb.next_deadline() == 0.5
    arb.poll(0.5)
    assert arb.next_deadline() == pytest.approx(0.9)


def test_a_gap_still_voids_a_standing_command(rig: Rig) -> None:
    """The drive stopped itself (a gap): the owner's standing VEL is not resumed either."""
    arb, node = owned_rig(rig)
    node.alive["tui1"] = 10.0
    arb.submit("tui1", VelocityCommand(200, 0), 0.1, standing=True)
    rig.run(0.5)
    rig.sup.subscribe(lambda e: arb.hold(e.unit) if isinstance(e, GapEvent) and e.started else None)
    rig.drive("left").silent = True
    rig.run(1.5)
    rig.drive("left").silent = False
    rig.run(1.0)
    assert commanded(rig) == 0.0


def test_a_command_the_arbitration_gives_back_later_is_checked_anew(rig: Rig) -> None:
    """set_velocity's command is checked once as it is submitted (Supervisor._submit),
    not again as the arbitration applies it on the same call; given back later (the
    source that took over let go), it is checked afresh: refused, with a notice, and
    the drive is told zero."""
    arb, node = owned_rig(rig)
    notes: list[str] = []
    rig.sup.subscribe(lambda e: notes.append(e.message) if isinstance(e, Notice) else None)
    mine = rig.own("left")
    set_velocity(rig.sup, "left", 300, 0, source=mine)
    assert rig.sup._checked is None  # nothing kept past the call
    rig.run(0.1)
    assert commanded(rig) == 300.0
    node.alive["tui1"] = 10.0
    arb.submit("tui1", VelocityCommand(100, 0), rig.timeline.now, standing=True)  # priority 50
    rig.run(0.1)
    assert commanded(rig) == 100.0
    rig.sup.gate.foreign["left"] = "another host commands it"  # as core/foreign.py says it
    arb.remove("tui1", rig.timeline.now)  # mine is fresh again: given back, and refused
    rig.run(0.1)
    assert commanded(rig) == 0.0 and arb.owner("left") is None
    assert notes[-1].startswith(f"input {mine} refused: unit 'left' is stopped: another host")


def test_clamp_note_names_the_limit_and_reaches_the_event_log(rig: Rig) -> None:
    notes: list[str] = []
    rig.sup.subscribe(lambda e: notes.append(e.message) if isinstance(e, Notice) else None)
    assert rig.sup.admit("left", VelocityCommand(99999, 0)) == (
        "clamped: VEL 99999 0 → 6553.4 0 (wire range -6553.6 … 6553.4)"
    )
    assert rig.sup.admit("left", VelocityCommand(10, 0)) is None
    set_velocity(rig.sup, "left", 99999, 0, source=present(rig.sup, "left"))
    assert notes[-1] == "clamped: VEL 99999 0 → 6553.4 0 (wire range -6553.6 … 6553.4)"


@pytest.mark.wallclock
def test_abh3_send_names_its_target_holds_motion_and_reports_clamping(tmp_path: Path) -> None:
    root = Path(__file__).parent.parent
    sock = tmp_path / "run" / "demo.sock"
    with headless_demo(sock):

        def abh3(*args: str) -> subprocess.CompletedProcess[str]:
            cmd = [sys.executable, "-m", "abh3_supervisor", *args, "--connect", str(sock)]
            return subprocess.run(cmd, capture_output=True, text=True, cwd=root, timeout=30)

        def setpoint() -> float:
            state = json.loads(abh3("status", "--json").stdout)
            return float(state["units"]["left"]["setpoint"]["ay"])

        untargeted = abh3("send", "SERVO ON ON")
        assert untargeted.returncode == 2 and "--unit NAME" in untargeted.stderr
        assert untargeted.stdout == ""
        unknown = abh3("send", "SERVO ON ON", "--unit", "nobody")
        assert unknown.returncode == 2
        assert "no unit named 'nobody' (units: left, right)" in unknown.stderr
        every = abh3("send", "SERVO ON ON", "--all")
        assert (every.returncode, every.stdout) == (0, "left: ''\nright: ''\n")
        before = setpoint()
        one_shot = abh3("send", "VEL 5000 0", "--unit", "left")
        assert one_shot.returncode == 2 and "--hold" in one_shot.stderr
        assert setpoint() == before  # nothing was sent
        assert abh3("send", "VEL 0 0", "--unit", "left").returncode == 0  # zero needs no owner

        hold = subprocess.Popen(
            [sys.executable, "-m", "abh3_supervisor", "send", "VEL 99999 0", "--unit", "left",
             "--hold", "--connect", str(sock)],
            cwd=root, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        )  # fmt: skip
        assert hold.stderr is not None
        clamp = hold.stderr.readline()
        assert clamp.startswith("left: clamped: VEL 99999 0 → 1500 0 (limits.velocity 1500)"), clamp
        assert "holding" in hold.stderr.readline()
        assert setpoint() == pytest.approx(1500)  # held without repetition by the user
        hold.send_signal(2)
        out, err = hold.communicate(timeout=10)
        assert hold.returncode == 0 and "released" in err
        assert out == "''\n"
        # left with its owner (the service may read the hangup just after our next
        # connection: wait for the effect, bounded), and not back to the startup VEL
        deadline = time.monotonic() + 5
        while setpoint() != 0.0:
            assert time.monotonic() < deadline, "the held VEL outlived its owner"


def test_a_stream_beyond_the_limit_says_so_once_a_second(rig: Rig) -> None:
    """A joystick pushed past the limit must not flood the log: one note a second, and
    the next one counts what it held back."""
    notes: list[str] = []
    rig.sup.subscribe(lambda e: notes.append(e.message) if isinstance(e, Notice) else None)
    for text in ("SERVO ON ON", "START ON ON"):
        assert rig.sup.apply_text("left", text) == ""
    for i in range(50):  # 50 Hz for a second, every value beyond the wire's range
        set_velocity(rig.sup, "left", 7000 + i, 0, source=present(rig.sup, "left"))
        rig.run(0.02)
    set_velocity(rig.sup, "left", 8000, 0, source=present(rig.sup, "left"))
    clamped = [n for n in notes if n.startswith("clamped: ")]
    assert len(clamped) == 2
    assert clamped[1].endswith("(49 more like it since the last line not shown)")
