"""The arbitration decides per robot: random submissions, holds and silences, judged on
what each unit was last given (never the arbiter's own bookkeeping alone)."""

from __future__ import annotations

import math

from hypothesis import given, settings
from hypothesis import strategies as st

from abh3_supervisor.core.commands import VelocityCommand
from abh3_supervisor.core.inputs import ZERO, InputArbiter, InputCommand, Stop, Twist

ROBOT = ("fl", "fr")  # one robot on two units
ALONE = "solo"  # a unit that is a robot of its own
SOURCES = {
    "joy": ((ROBOT[0],), 0),  # targets one unit of the robot: its twist drives both
    "tui": ((ROBOT[1], ALONE), 1),
    "net": ((*ROBOT, ALONE), 2),
}

commands = st.one_of(
    st.builds(Twist, st.sampled_from([0.0, 0.3, -0.2]), st.sampled_from([0.0, 1.0])),
    st.builds(VelocityCommand, st.sampled_from([0.0, 100.0]), st.sampled_from([0.0, -50.0])),
    st.none(),  # a release
)
steps = st.lists(
    st.one_of(
        st.tuples(st.just("submit"), st.sampled_from(sorted(SOURCES)), commands),
        st.tuples(st.just("hold"), st.sampled_from([*ROBOT, ALONE]), st.none()),
        st.tuples(st.just("wait"), st.sampled_from([0.1, 0.3, 0.6]), st.none()),
    ),
    max_size=40,
)


class _Source:
    def __init__(self, name: str, units: tuple[str, ...], priority: int) -> None:
        self.name, self.units, self.priority, self.timeout = name, units, priority, 0.5


@settings(max_examples=300, deadline=None)
@given(steps)
def test_a_robot_has_one_owner_and_its_twist_reaches_every_unit(plan: list[tuple]) -> None:  # type: ignore[type-arg]
    now = [0.0]
    given_to: dict[str, InputCommand] = {}  # what each unit was last told to do

    def apply(unit: str, command: InputCommand) -> bool:
        given_to[unit] = command
        return True

    arb = InputArbiter(apply=apply, clock=lambda: now[0])
    arb.domains = {u: ROBOT for u in ROBOT}
    for name, (units, priority) in SOURCES.items():
        arb.add(_Source(name, units, priority))  # type: ignore[arg-type]
    for kind, what, command in plan:
        if kind == "submit":
            arb.submit(str(what), command, now[0])
        elif kind == "hold":
            arb.hold(str(what))
            given_to[str(what)] = ZERO  # the caller zeroes the unit it holds
        else:
            now[0] += float(what)
            if now[0] >= arb.next_deadline():
                arb.poll(now[0])
        owners = {arb.owner(u) for u in ROBOT} - {None}
        assert len(owners) <= 1, f"two owners of one robot: {owners}"
        moving = {u: c for u in ROBOT if not _still(c := given_to.get(u, ZERO))}
        if any(isinstance(c, Twist) for c in moving.values()):
            # a twist drives the whole robot: every unit has that same twist
            assert len({given_to.get(u) for u in ROBOT}) == 1
        for unit in (*ROBOT, ALONE):
            if arb.owner(unit) is None:
                assert _still(given_to.get(unit, ZERO)), f"{unit} moves with no owner"
        fresh = [s for s in arb.sources.values() if s.fresh(now[0])]
        assert all(s.expires() > now[0] for s in fresh)
    assert math.isfinite(now[0])


def _still(command: InputCommand) -> bool:
    if isinstance(command, Stop):
        return True
    if isinstance(command, Twist):
        return command.linear_x == 0 and command.angular_z == 0
    if isinstance(command, VelocityCommand):
        return command.ay == 0 and command.bx == 0
    return False
