"""Every string gets one of the documented answers from every entry point, never an exception.

Entry points: the parser, the Supervisor API (the TUI command line and the ROS 2 service
both end in ``Supervisor.command`` → ``apply_text``), and ``startup:`` in the YAML.
"""

from __future__ import annotations

import asyncio

import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from abh3_supervisor.config import parse_config
from abh3_supervisor.core.commands import (
    KEYWORDS,
    CurrentCommand,
    SelectCommand,
    SwitchCommand,
    VelocityCommand,
    parse_command,
)
from abh3_supervisor.errors import CommandError, ConfigError
from tests.support.rig import TWO_UNITS, Rig

ANSWERS = {"", "Invalid Command.", "Packet Error: 1", "Packet Error: 2", "Packet Error: 3"}
# any Unicode (no lone surrogates: they cannot be text in a YAML file or a DDS string)
ANY_TEXT = st.text(st.characters(exclude_categories=["Cs"]), max_size=300)
VALUES = st.sampled_from(["ON", "off", "1", "0", "7", "²", "١", "1e999", "nan", "-0", "x"])
# near-valid commands find the interesting corners faster than random text
NEAR = st.builds(
    lambda k, a, b, sep: sep.join([k, a, b]),
    st.sampled_from([*KEYWORDS, "servo", "SELECT", "Ｓervo"]),
    VALUES,
    VALUES,
    st.sampled_from([" ", "\t", "\u3000", "  ", "\n", "\x00"]),
)


@settings(max_examples=500, deadline=None)
@given(st.one_of(ANY_TEXT, NEAR))
def test_the_parser_answers_or_refuses(text: str) -> None:
    try:
        command = parse_command(text)
    except CommandError as exc:
        assert str(exc)  # says what is wrong
        return
    assert (
        isinstance(command, SwitchCommand | SelectCommand | VelocityCommand | CurrentCommand)
        and text.isascii()
    )


@settings(max_examples=300, deadline=None)
@given(st.lists(st.one_of(ANY_TEXT, NEAR), min_size=1, max_size=4))
def test_the_supervisor_api_answers_every_string(texts: list[str]) -> None:
    rig = Rig(parse_config(TWO_UNITS, "two.yaml"))
    for text in texts:
        for unit in ("left", "right"):
            assert rig.sup.apply_text(unit, text) in ANSWERS
    rig.sup.emergency_stop()
    for text in texts:
        assert rig.sup.apply_text("left", text) in ANSWERS


@settings(max_examples=200, deadline=None)
@given(st.one_of(ANY_TEXT, NEAR))
def test_startup_commands_are_checked_when_the_file_loads(text: str) -> None:
    doc = yaml.safe_load(TWO_UNITS)
    doc["units"][0]["startup"] = [text]
    source = yaml.safe_dump(doc, allow_unicode=True)
    try:
        parse_config(source, "fuzz.yaml")
    except ConfigError as exc:
        assert all(p.startswith("fuzz.yaml:") for p in exc.problems)
        assert any("startup" in p for p in exc.problems)


@pytest.mark.wallclock
def test_the_async_command_answers_too() -> None:
    """``Supervisor.command`` is what the TUI command line and the ROS 2 service call."""
    rig = Rig(parse_config(TWO_UNITS, "two.yaml"))

    async def scenario() -> list[str]:
        texts = ["SELECT ² 7", "SERVO\u3000ON ON", "\x00", "x" * 10_000, "VEL 1e999 0"]
        return [await rig.sup.command("left", t) for t in texts]

    assert asyncio.run(scenario()) == ["Invalid Command."] * 5
