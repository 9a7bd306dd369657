"""A robot moves whole or not at all (core/readiness.py), judged on the wire.

Every test here reads the command frames the drives were sent from the fake-clock
timeline and decodes them itself, in each drive's own generation — never the
supervisor's state — and holds the robot invariant: no drive of a robot is commanded a
non-zero setpoint while another drive of it is offline, silent past its gap, not
reporting ready, or not recognised as the file's generation; no SERVO goes to a drive
that has reported its servo off since the operator last switched it on; nothing but the
identity probe goes to a drive before its generation is known.
"""

from __future__ import annotations

import pytest

from abh3_supervisor.config import parse_config
from abh3_supervisor.core.readiness import (
    DriveView,
    Unready,
    drive_unready,
    reply_generation,
    robot_unready,
)
from abh3_supervisor.core.supervisor import Notice
from abh3_supervisor.errors import CommandError
from abh3_supervisor.protocol import flags, frames, ids
from abh3_supervisor.protocol.generation import Generation
from abh3_supervisor.simulator.drive import BOOT_S
from tests.support.rig import Rig, set_twist

AGV = """
buses:
  b:
    interface: virtual
    channel: t
    simulate: {{faults: [{faults}]}}
units:
  - {{name: left_drive, abh3_id: 1, velocity_model: motor, command_rate_hz: 50}}
  - {{name: right_drive, abh3_id: 3, protocol: "{right}", velocity_model: motor,
     command_rate_hz: 50}}
robots:
  - name: agv
    track_m: 0.45
    diameter_m: 0.2
    gear_ratio: 20
    wheels:
      - {{unit: left_drive, axis: A, side: left}}
      - {{unit: right_drive, axis: A, side: right, sign: -1}}
"""
UNITS = ("left_drive", "right_drive")


def agv(faults: str = "", right: str = "2023") -> Rig:
    return Rig(parse_config(AGV.format(faults=faults, right=right), "agv.yaml"))


def sent(rig: Rig, unit: str, since: float = 0.0) -> list[tuple[float, int, int, int]]:
    """Every DP0 command to ``unit``'s drive after ``since``: (t, AY raw, BX raw, word)."""
    cfg = rig.config.units[unit]
    want = ids.dp0_command_id(cfg.abh3_id, cfg.host_id) & ids.MATCH_MASK
    return [
        (f.end, *frames.unpack_dp0_command(f.data))
        for f in rig.timeline.frames
        if f.end > since and f.arbitration_id & ids.MATCH_MASK == want
    ]


def moving_frames(rig: Rig, unit: str, since: float = 0.0) -> list[float]:
    return [t for t, ay, bx, _ in sent(rig, unit, since) if ay or bx]


def switch_on(rig: Rig) -> str:
    owner = rig.own("left_drive")  # a twist to the robot names any unit of it
    for unit in UNITS:
        for text in ("SERVO ON ON", "START ON ON"):
            assert rig.sup.apply_text(unit, text) == ""
    return owner


def stream(rig: Rig, owner: str, seconds: float, linear: float = 0.3) -> list[str]:
    """A twist every 50 ms (20 Hz) for ``seconds``; each answer ("" or why refused)."""
    answers = []
    for _ in range(round(seconds / 0.05)):
        try:
            set_twist(rig.sup, "agv", linear, 0.0, source=owner)
            answers.append("")
        except CommandError as exc:
            answers.append(str(exc))
        rig.run(0.05)
    return answers


def test_a_drive_that_falls_silent_stops_the_whole_robot_and_twists_are_refused() -> None:
    rig = agv()
    owner = switch_on(rig)
    assert stream(rig, owner, 1.0) == [""] * 20
    assert moving_frames(rig, "left_drive", 0.8) and moving_frames(rig, "right_drive", 0.8)
    rig.drive("right_drive").silent = True
    silent_at = rig.timeline.now
    answers = stream(rig, owner, 2.0)
    gap = silent_at + rig.config.units["right_drive"].drive_timeout_ms / 1000
    # the left drive is zero from its next frame after the right one's gap …
    late = moving_frames(rig, "left_drive", gap + 0.021)
    assert late == [], f"left commanded to move at {late[:3]} after the right drive's gap"
    # … and every twist after it is refused in its answer, naming the drive and why
    refused = [a for a in answers if a]
    assert refused and all("right_drive" in a for a in refused)
    assert any("no exchange" in a or "offline" in a for a in refused)
    # back: nothing moves until switched on and commanded anew
    rig.drive("right_drive").silent = False
    back = rig.timeline.now
    rig.run(0.5)
    assert stream(rig, owner, 0.3)[-1].startswith("robot 'agv' may not move")
    assert moving_frames(rig, "left_drive", back) == []
    assert moving_frames(rig, "right_drive", back) == []
    for text in ("SERVO ON ON", "START ON ON"):
        assert rig.sup.apply_text("right_drive", text) == ""
    rig.run(0.2)
    assert stream(rig, owner, 0.5)[-1] == ""
    assert moving_frames(rig, "left_drive", rig.timeline.now - 0.2)
    assert moving_frames(rig, "right_drive", rig.timeline.now - 0.2)


def test_a_power_cut_shorter_than_the_offline_timeout_never_restarts_the_drive() -> None:
    rig = agv()
    owner = switch_on(rig)
    stream(rig, owner, 1.0)
    drive = rig.drive("right_drive")
    drive.power_off(rig.timeline.now)
    rig.run(0.3)
    drive.power_on(rig.timeline.now)
    back = rig.timeline.now
    answers = stream(rig, owner, BOOT_S + 1.5)  # the operator's stream goes on meanwhile
    lay = flags.LAYOUT_2023
    # once it reported its servo off, not one frame switched it on again …
    assert all(
        not word & (lay.servo.both | lay.start.both)
        for *_, word in sent(rig, "right_drive", back + BOOT_S + 0.05)
    )
    assert not drive.control_word() & (lay.servo.both | lay.start.both)
    # … and the other drive of the robot stood: no half robot
    assert moving_frames(rig, "left_drive", back + 0.6) == []
    assert answers[-1].startswith("robot 'agv' may not move: right_drive")
    notes = [e.message for e in rig.events if isinstance(e, Notice)]
    assert any("SERVO, START and brake release off" in n or "forgotten" in n for n in notes)


def test_a_drive_of_the_other_generation_gets_only_the_probe_and_holds_its_robot() -> None:
    """right_drive is filed as 2023 but is a 2021 drive: 0x7070 (2023's idle data select)
    would be B SERVO and START in its layout. It gets only the probe; the robot is held."""
    rig = agv("{kind: wrong_protocol, unit: right_drive}")
    drive = rig.drive("right_drive")
    assert drive.generation is Generation.G2021
    owner = switch_on(rig)
    answers = stream(rig, owner, 1.0)
    assert {word for *_, word in sent(rig, "right_drive")} == {flags.ID_PROBE}
    assert (
        drive.inputs == flags.ID_PROBE and not drive.control_word() & flags.LAYOUT_2021.servo.both
    )
    assert moving_frames(rig, "left_drive") == []  # the robot is held whole
    assert answers[-1].startswith("robot 'agv' may not move: right_drive: answers as a 2021 drive")
    with pytest.raises(CommandError, match="answers as a 2021 drive"):
        rig.sup.set_inputs(
            "right_drive", flags.LAYOUT_2023.servo.both, flags.LAYOUT_2023.servo.both
        )
    state = rig.sup.units["right_drive"]
    assert state.identified is Generation.G2021


def test_an_axis_that_drives_no_wheel_is_never_switched_on() -> None:
    rig = agv()
    owner = switch_on(rig)  # SERVO ON ON, START ON ON: B drives nothing
    stream(rig, owner, 0.5)
    for unit, lay in (("left_drive", flags.LAYOUT_2021), ("right_drive", flags.LAYOUT_2023)):
        words = [word for *_, word in sent(rig, unit)]
        assert any(word & lay.servo.ay for word in words)  # A, the wheel, was on
        assert not any(word & (lay.servo.bx | lay.start.bx) for word in words)


def test_a_twist_before_the_robot_is_switched_on_is_refused_naming_the_switches() -> None:
    rig = agv()
    rig.run(0.2)
    with pytest.raises(CommandError, match=r"left_drive: SERVO A, START A not switched on"):
        set_twist(rig.sup, "agv", 0.3, 0.0, source=rig.own("left_drive"))


def test_a_request_while_the_drives_report_their_switches_is_held_at_zero_until_ready() -> None:
    rig = agv()
    owner = switch_on(rig)
    set_twist(rig.sup, "agv", 0.3, 0.0, source=owner)  # taken: pending, not a fault
    ready = next(t for t in (i * 0.001 for i in range(1, 500)) if _ready_by(rig, t))
    rig.run(0.1)
    first = min(moving_frames(rig, "left_drive") + moving_frames(rig, "right_drive"))
    assert first >= ready - 0.001  # no setpoint before every drive reported ready


def _ready_by(rig: Rig, t: float) -> bool:
    rig.timeline.run_until(t)
    return rig.sup.robot_unready("left_drive") is None


# ------------------------------------------------------------ the pure decision


def view(**over: object) -> DriveView:
    lay = flags.LAYOUT_2023
    base: dict[str, object] = {
        "name": "d",
        "layout": lay,
        "declared": Generation.G2023,
        "wheels": (0,),
        "online": True,
        "gap": False,
        "identified": Generation.G2023,
        "commanded": lay.servo.ay | lay.start.ay,
        "reported": lay.servo.ay | lay.start.ay,
        "error": False,
    }
    base.update(over)
    return DriveView(**base)  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("over", "why", "pending"),
    [
        ({"online": None}, "not heard yet", True),
        ({"online": False}, "offline", False),
        ({"gap": True}, "no exchange", False),
        ({"identified": None}, "not yet recognised as a 2023 drive", True),
        ({"identified": Generation.G2021}, "answers as a 2021 drive", False),
        ({"commanded": flags.LAYOUT_2023.servo.ay}, "START A not switched on", False),
        ({"reported": None}, "has not yet reported", True),
        ({"reported": flags.LAYOUT_2023.servo.ay}, "reports START A off", True),
        ({"error": True}, "reports an error", False),
    ],
)
def test_each_condition_of_a_drive_is_named(
    over: dict[str, object], why: str, pending: bool
) -> None:
    got = drive_unready(view(**over))
    assert got is not None and why in got.why and got.pending is pending
    assert drive_unready(view()) is None


def test_a_robot_names_a_fault_before_a_pending_drive() -> None:
    views = [view(name="a", online=None), view(name="b", gap=True), view(name="c")]
    assert robot_unready(views) == Unready(
        "b: no exchange for its drive_timeout_ms (it stopped itself)"
    )
    assert robot_unready([view(name="a", online=None), view(name="c")]) == Unready(
        "a: not heard yet", pending=True
    )
    assert robot_unready([view(), view(name="e")]) is None


def test_the_replies_show_the_generation_or_say_they_cannot() -> None:
    reply21 = frames.encode_dp0_reply_2021(100, 50, 75, 25)
    assert reply_generation(reply21, probed=False) is Generation.G2021
    reply23 = frames.encode_dp0_reply_2023(0, 0, flags.ID_PROBE)
    assert reply_generation(reply23, probed=False) is Generation.G2023
    idle = bytes(8)  # reads alike in both …
    assert reply_generation(idle, probed=False) is None
    assert reply_generation(idle, probed=True) is Generation.G2021  # … but not to the probe


def test_enable_is_refused_whole_while_a_drive_of_the_robot_cannot_follow() -> None:
    rig = agv()
    rig.run(0.2)
    rig.drive("right_drive").silent = True
    rig.run(1.5)  # offline
    with pytest.raises(CommandError, match=r"not switched on: right_drive: offline"):
        rig.sup.enable("agv")
    start = rig.timeline.now
    rig.run(0.2)
    lay = flags.LAYOUT_2021
    assert not any(word & lay.servo.both for *_, word in sent(rig, "left_drive", start))
    rig.drive("right_drive").silent = False
    rig.run(0.5)
    assert rig.sup.enable("agv") == UNITS  # back: one act switches both on
    rig.run(0.2)
    assert rig.sup.robot_unready("agv") is None


def test_a_drive_that_reboots_within_its_own_long_timeouts_is_not_switched_on_again() -> None:
    """The wire campaign's case: drive_timeout_ms 2000 and timeout_ms 3000, a 0.1 s power
    cut — the drive is back (after its boot) before either timeout. A silence of OUTAGE_S
    is an outage all the same: no SERVO goes to it once it answers, and the robot stands."""
    text = (
        AGV.format(faults="", right="2023")
        .replace(
            "command_rate_hz: 50}", "command_rate_hz: 50, drive_timeout_ms: 2000, timeout_ms: 3000}"
        )
        .replace(
            "\n     command_rate_hz: 50}",
            "\n     command_rate_hz: 50, drive_timeout_ms: 2000, timeout_ms: 3000}",
        )
    )
    rig = Rig(parse_config(text, "agv.yaml"))
    assert rig.config.units["right_drive"].drive_timeout_ms == 2000
    owner = switch_on(rig)
    stream(rig, owner, 1.0)
    drive = rig.drive("right_drive")
    drive.power_off(rig.timeline.now)
    rig.run(0.1)
    drive.power_on(rig.timeline.now)
    back = rig.timeline.now + BOOT_S
    stream(rig, owner, BOOT_S + 1.0)
    lay = flags.LAYOUT_2023
    assert not any(word & lay.servo.both for *_, word in sent(rig, "right_drive", back))
    assert not drive.control_word() & lay.servo.both
    assert moving_frames(rig, "left_drive", back) == []  # and its robot stands


G21, G23 = Generation.G2021, Generation.G2023


@pytest.mark.parametrize(
    ("a", "b", "y", "x", "shown"),
    [
        (-100, -50, -75, -25, G21),  # backwards: the fields are signed
        (100, -50, 25, 75, G21),  # turning
        (-30, 30, 0, -30, G21),
        (100, 52, 77, 23, G21),  # 2·Y − (A + B) = 2: the drive's rounding
        (100, 51, 77, 23, G23),  # … = 3: no 2021 reply
        (100, 50, 75, 27, G21),  # X − (A − Y) = 2
        (100, 50, 75, 28, G23),  # … = 3
        (0, 0, 1, 0, G21),  # a creep within the rounding: any non-zero field shows 2021
        (2, 0, 0, 0, G21),
    ],
)
def test_a_reply_is_2021_only_within_the_drives_rounding(
    a: int, b: int, y: int, x: int, shown: Generation
) -> None:
    data = frames.encode_dp0_reply_2021(a, b, y, x)
    assert reply_generation(data, probed=False) is shown


def test_each_reason_reads_as_the_operator_is_told_it() -> None:
    lay = flags.LAYOUT_2023
    said = {
        "not heard yet": view(online=None),
        "offline (no answer within its timeout_ms)": view(online=False),
        "no exchange for its drive_timeout_ms (it stopped itself)": view(gap=True),
        "not yet recognised as a 2023 drive": view(identified=None),
        'answers as a 2021 drive, the file says protocol: "2023" (held at a word safe in both '
        "generations)": view(identified=Generation.G2021),
        "SERVO A, START A not switched on": view(commanded=0),
        "has not yet reported the switches it was given": view(reported=None),
        "reports an error: reset it (RESET), then SERVO and START again": view(error=True),
        "reports START A off": view(reported=lay.servo.ay),
    }
    assert {k: getattr(drive_unready(v), "why", None) for k, v in said.items()} == {
        k: k for k in said
    }
