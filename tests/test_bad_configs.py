"""Every broken or hostile configuration gets a clear answer from `check` and from `run`.

The corpus and its expectations are in tests/data/bad-configs (README there). For every
file: an allowed exit code, `FILE:LINE:` in the message where required, never a
traceback, at most 20 problems then "and N more", and an answer well under a second.
Both commands run in-process through the CLI's main(), from a scratch directory.
"""

from __future__ import annotations

import json
import logging
import re
import time
from pathlib import Path
from typing import Any

import pytest

from abh3_supervisor.clients.cli import MAX_SHOWN, main
from abh3_supervisor.config.source import MAX_BYTES

DATA = Path(__file__).resolve().parent / "data" / "bad-configs"
EXPECT: dict[str, dict[str, Any]] = json.loads((DATA / "expect.json").read_text())
ANSWER_S = 1.0  # a refusal
RUN_S = 1.0  # --duration of a run that starts
STOP_S = 2.0  # a run's start and safe stop around its duration


@pytest.fixture(autouse=True)
def scratch(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    monkeypatch.chdir(tmp_path)  # some files write into out/ relative to it
    caplog.set_level(logging.INFO)  # the run's log, as it would reach stderr


def abh3(
    args: list[str], capsys: pytest.CaptureFixture[str], caplog: pytest.LogCaptureFixture
) -> tuple[int, str, list[str], float]:
    """Exit code, everything printed or logged, the error lines, seconds taken."""
    started = time.monotonic()
    code = main(args)
    elapsed = time.monotonic() - started
    out = capsys.readouterr()
    errors = [line for line in out.err.splitlines() if line.startswith("error:")]
    return code, out.out + out.err + caplog.text, errors, elapsed


def test_every_file_has_its_expectation() -> None:
    assert {p.name for p in DATA.glob("*.yaml")} == set(EXPECT)


@pytest.mark.wallclock
@pytest.mark.parametrize("name", sorted(EXPECT))
def test_check(
    name: str, capsys: pytest.CaptureFixture[str], caplog: pytest.LogCaptureFixture
) -> None:
    path, expect = str(DATA / name), EXPECT[name]
    code, text, errors, elapsed = abh3(["check", path], capsys, caplog)
    assert code in expect["check"], text
    assert_clear_answer(path, expect, code, text, errors)
    assert elapsed < ANSWER_S
    if code == 0:
        assert "OK" in text
        assert ("warning" in text) == expect["warn_if_0"], text
    else:
        assert "OK" not in text


@pytest.mark.wallclock
@pytest.mark.parametrize("name", sorted(EXPECT))
def test_run(
    name: str, capsys: pytest.CaptureFixture[str], caplog: pytest.LogCaptureFixture
) -> None:
    path, expect = str(DATA / name), EXPECT[name]
    args = ["run", path, "--headless", "--duration", f"{RUN_S:g}", "--status-interval", "0"]
    code, text, errors, elapsed = abh3(args, capsys, caplog)
    assert code in expect["run"], text
    assert_clear_answer(path, expect, code, text, errors)
    if code == 0:  # ran: on the built-in simulator, which answered
        assert elapsed < RUN_S + STOP_S
        assert "online" in text and "stop frame confirmed" in text, text
        assert ("WARNING" in text) == expect["warn_if_0"], text
    else:  # refused before any drive was commanded
        assert elapsed < ANSWER_S
        assert not re.search(r"unit \w+: startup |running \d+ unit", text), text


def assert_clear_answer(
    path: str, expect: dict[str, Any], code: int, text: str, errors: list[str]
) -> None:
    assert "Traceback" not in text
    if code != 0:
        assert errors, text
        if expect["file_line"]:
            assert re.search(rf"{re.escape(path)}:\d+: ", errors[0]), errors[0]
    assert len(errors) <= MAX_SHOWN + 1


# ---------------------------------------------------------------- large files, generated


def unit_list(path: Path, size: int) -> Path:
    """Units that all claim abh3_id 1: one problem per unit after the first."""
    head = "buses:\n  demo: {interface: virtual, channel: big, simulate: true}\nunits:\n"
    unit = "  - {{name: u{}, abh3_id: 1, command_rate_hz: 50, broadcast: {{rate_hz: 14}}}}\n"
    rows, total, i = [head], len(head), 0
    while total + len(unit) + 8 < size:
        rows.append(unit.format(i))
        total += len(rows[-1])
        i += 1
    path.write_text("".join(rows))
    return path


@pytest.mark.wallclock
@pytest.mark.parametrize("command", ["check", "run"])
def test_a_5_mb_unit_list_is_refused_at_once(
    command: str,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    caplog: pytest.LogCaptureFixture,
) -> None:
    big = unit_list(tmp_path / "big.yaml", 5_000_000)
    code, _, errors, elapsed = abh3([command, str(big)], capsys, caplog)
    assert code == 2 and elapsed < ANSWER_S
    assert errors == [
        f"error: {big}:1: file: larger than 512 KiB, not a configuration (is this the right file?)"
    ]


@pytest.mark.wallclock
def test_the_largest_file_allowed_answers_in_seconds_and_prints_20_problems(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], caplog: pytest.LogCaptureFixture
) -> None:
    big = unit_list(tmp_path / "big.yaml", MAX_BYTES)
    code, text, errors, elapsed = abh3(["check", str(big)], capsys, caplog)
    assert code == 2 and elapsed < 3.0 and "Traceback" not in text
    assert len(errors) == MAX_SHOWN + 1
    assert (
        errors[0]
        == f"error: {big}:5: units[1].abh3_id: unit 'u0' already uses abh3_id 1 on bus 'demo'"
    )
    assert re.fullmatch(r"error: and \d{4} more", errors[-1]), errors[-1]


# ---------------------------------------------------------------- named causes (issue 21)


@pytest.mark.wallclock
@pytest.mark.parametrize("command", ["check", "run"])
def test_an_interface_python_can_does_not_know_is_a_mistake_in_the_file(
    command: str, capsys: pytest.CaptureFixture[str], caplog: pytest.LogCaptureFixture
) -> None:
    """A typo is found by `check` (not only when `run` opens the bus), at its line, with a
    did-you-mean from python-can's list — on a simulated bus too, which runs on `virtual`."""
    path = str(DATA / "interface-typo-sockecan-simulated.yaml")
    code, text, errors, _ = abh3([command, path], capsys, caplog)
    assert code == 2 and "Traceback" not in text
    assert len(errors) == 1, errors
    assert errors[0].startswith(
        f"error: {path}:3: buses.demo.interface: python-can has no interface 'sockecan'; "
        "did you mean 'socketcan'? (its interfaces: "
    )
    assert "wacousb" in errors[0]  # an entry-point interface is in the list too
