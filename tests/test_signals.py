"""Every signal whose default action ends the process (docs/signals.md): the table names
them all, and a real `abh3 run --headless`, `abh3 commission` and `abh3 param` holding a
bus take each catchable one as the normal way out — judged from the CAN recording: the
last command frame to each commanded unit is the safe word and the exit code the normal
one."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from abh3_supervisor.protocol import flags, frames, ids
from abh3_supervisor.runtime import signals
from tests.support.safe_word import commands_to, is_stop
from tests.support.terminal import ended, in_a_terminal

ROOT = Path(__file__).resolve().parent.parent
DOCS = ROOT / "docs" / "signals.md"
# signal(7) on Linux: the signals whose default action is "Term" or "Core"
TERMINATING = [
    "SIGHUP", "SIGINT", "SIGQUIT", "SIGILL", "SIGTRAP", "SIGABRT", "SIGBUS", "SIGFPE",
    "SIGKILL", "SIGUSR1", "SIGSEGV", "SIGUSR2", "SIGPIPE", "SIGALRM", "SIGTERM", "SIGSTKFLT",
    "SIGXCPU", "SIGXFSZ", "SIGVTALRM", "SIGPROF", "SIGIO", "SIGPWR", "SIGSYS",
]  # fmt: skip
# one unit moving at VEL 300 20 with SERVO and START on, from the file's start-up
MOVING = """
buses:
  b: {interface: virtual, channel: moving, bitrate: 500000, simulate: true}
units:
  - {name: u, abh3_id: 1, host_id: 2, protocol: "2023", command_rate_hz: 50,
     broadcast: {mask: 0x03, rate_hz: 4}, startup: ["SERVO ON ON", "START ON ON", "VEL 300 20"]}
"""
LAYOUT = flags.LAYOUT_2023


# ---------------------------------------------------------------- the table


def test_the_table_names_every_signal_that_would_end_the_process() -> None:
    named = {e.name for e in signals.TABLE}
    assert {n for n in TERMINATING if hasattr(signal, n)} <= named
    handled = set(signals.STOP_SIGNALS) | set(signals.IGNORED) | set(signals.FAULTS)
    for n in TERMINATING:
        if hasattr(signal, n) and n not in ("SIGKILL",):
            assert int(getattr(signal, n)) in handled, n  # each catchable one has its answer
    # the real-time signals end a process by default too: every one is a stop signal
    assert set(range(signal.SIGRTMIN, signal.SIGRTMAX + 1)) <= set(signals.STOP_SIGNALS)
    assert not set(signals.STOP_SIGNALS) & (set(signals.IGNORED) | set(signals.FAULTS))


def test_the_docs_table_has_a_row_for_every_signal() -> None:
    text = DOCS.read_text()
    rows = {m[1] for m in re.finditer(r"^\| `(SIG\w+)`", text, re.M)}
    assert rows == {e.name for e in signals.TABLE} | {"SIGRTMIN"}, rows


def test_names_of_real_time_signals() -> None:
    assert signals.name(signal.SIGUSR1) == "SIGUSR1"
    assert signals.name(signal.SIGRTMIN + 3) == "SIGRTMIN+3"
    assert signals.name(signal.SIGRTMAX) == "SIGRTMAX"


def test_handlers_installed_from_c_are_not_in_the_way() -> None:
    """Under PYTHONFAULTHANDLER, SIGABRT's handler is faulthandler's (C): Python reads it
    as None and cannot put it back; the CLI still gives its handlers back cleanly."""
    out = subprocess.run(
        [sys.executable, "-m", "abh3_supervisor", "check", str(ROOT / "configs" / "demo.yaml")],
        capture_output=True, text=True, timeout=60, env={**os.environ, "PYTHONFAULTHANDLER": "1"},
    )  # fmt: skip
    assert out.returncode == 0 and "Traceback" not in out.stderr, out.stderr


def test_after_a_signal_the_loop_handlers_leave_the_stop_signals_ignored() -> None:
    """A second Ctrl-C a few milliseconds after a quick way out came while the loop's
    handlers were being taken down: Python's KeyboardInterrupt traceback, or the CLI's
    "stopped while starting". Once a signal began the way out, the stop signals stay
    ignored; a block that ended without one gives the handlers back."""
    import asyncio

    before = {sig: signal.getsignal(sig) for sig in signals.STOP_SIGNALS}
    seen: list[int] = []

    async def block(send: bool) -> None:
        loop = asyncio.get_running_loop()
        got = loop.create_future()

        def caught(signum: int) -> None:
            seen.append(signum)
            if not got.done():
                got.set_result(None)

        with signals.on_loop(loop, caught):
            if send:
                signal.raise_signal(signal.SIGINT)
                await got

    try:
        asyncio.run(block(send=False))
        assert {sig: signal.getsignal(sig) for sig in signals.STOP_SIGNALS} == before
        asyncio.run(block(send=True))
        assert seen == [signal.SIGINT]
        assert {signal.getsignal(sig) for sig in signals.STOP_SIGNALS} == {signal.SIG_IGN}
        signal.raise_signal(signal.SIGINT)  # the second Ctrl-C: nothing happens
    finally:
        for sig, handler in before.items():
            signal.signal(sig, handler)


def test_the_process_leaves_the_stop_signals_ignored_as_it_exits_and_main_gives_them_back(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """A quick way out (a commissioning stopped in under 50 ms) met the operator's second
    Ctrl-C while the interpreter wound down: it ended the process by SIGINT, not with the
    stop's code. The ``abh3`` process (``cli.run``) ignores them once ``main`` is done;
    ``main`` called in a process that goes on gives the handlers it found back."""
    from abh3_supervisor.clients import cli

    before = {sig: signal.getsignal(sig) for sig in signals.STOP_SIGNALS}
    try:
        assert cli.main(["schema"]) == 0
        assert {sig: signal.getsignal(sig) for sig in signals.STOP_SIGNALS} == before
        assert cli.main(["schema"], exiting=True) == 0
        assert {signal.getsignal(sig) for sig in signals.STOP_SIGNALS} == {signal.SIG_IGN}
    finally:
        for sig, handler in before.items():
            signal.signal(sig, handler)
    assert capsys.readouterr().out.startswith("{")


def test_a_signal_after_the_loop_gave_the_handlers_back_is_not_said_to_come_while_starting(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """A run that ended by itself (``--duration``, its stop confirmed) gives the CLI's
    handler back; a Ctrl-C as the interpreter wound down was then said to come "while
    starting; no drive was started". It is said to come while exiting, after the way out;
    one before any loop took over is still said to come while starting."""
    import asyncio

    from abh3_supervisor.clients import cli

    async def ran_and_ended() -> None:
        with signals.on_loop(asyncio.get_running_loop(), lambda signum: None):
            pass  # the run: its way out done without a signal

    def command(loop_first: bool) -> Callable[..., int]:
        def run(args: object, release: object) -> int:
            if loop_first:
                asyncio.run(ran_and_ended())
            signal.raise_signal(signal.SIGINT)
            return 0

        return run

    before = {sig: signal.getsignal(sig) for sig in signals.STOP_SIGNALS}
    try:
        monkeypatch.setattr(cli, "_command", command(loop_first=True))
        assert cli.main(["run", "configs/demo.yaml", "--headless"]) == 128 + signal.SIGINT
        said = capsys.readouterr().err
        assert "while exiting, after its way out" in said and "starting" not in said
        monkeypatch.setattr(cli, "_command", command(loop_first=False))
        assert cli.main(["run", "configs/demo.yaml", "--headless"]) == 128 + signal.SIGINT
        assert "while starting; no drive was started" in capsys.readouterr().err
        assert {sig: signal.getsignal(sig) for sig in signals.STOP_SIGNALS} == before
    finally:
        for sig, handler in before.items():
            signal.signal(sig, handler)


# ---------------------------------------------------------------- helpers


def _abh3(*args: str, cwd: Path) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "abh3_supervisor", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        stdin=subprocess.DEVNULL,
        text=True,
        cwd=cwd,
    )


def _until(stream: object, text: str, limit_s: float = 60) -> list[str]:
    """Lines of ``stream`` up to the first holding ``text`` (the condition waited for)."""
    seen: list[str] = []
    deadline = time.monotonic() + limit_s
    for line in stream:  # type: ignore[attr-defined]
        seen.append(line)
        if text in line:
            return seen
        assert time.monotonic() < deadline, "".join(seen)[-2000:]
    raise AssertionError(f"never saw {text!r}: {''.join(seen)[-2000:]}")


def _finish(proc: subprocess.Popen[str]) -> tuple[str, str]:
    """The rest of stdout and stderr once it has ended: read through the text streams,
    whose buffers may hold lines already read ahead (``communicate`` reads the pipes)."""
    assert proc.stdout is not None and proc.stderr is not None
    try:
        proc.wait(timeout=30)  # a few KB of output: the pipes cannot fill meanwhile
    except subprocess.TimeoutExpired:
        proc.kill()  # stopped (SIGSTOP-like) or hung: fail, never hang the suite
        raise
    return proc.stdout.read(), proc.stderr.read()


def _moving(cmd: frames.Dp0Command, layout: flags.Layout) -> bool:
    on = layout.servo.both | layout.start.both
    return (cmd.cmd_ay, cmd.cmd_bx) == (300.0, 20.0) and cmd.inputs & on == on


def _headless(tmp_path: Path) -> tuple[subprocess.Popen[str], Path]:
    cfg = tmp_path / "moving.yaml"
    cfg.write_text(MOVING)
    record = tmp_path / "run.log"
    proc = _abh3(
        "run", str(cfg), "--headless", "--no-socket", "--status-interval", "0",
        "--record", str(record), cwd=tmp_path,
    )  # fmt: skip
    assert proc.stderr is not None
    _until(proc.stderr, "+AY_START")  # the drive reports it runs: the unit is moving
    return proc, record


def _stopped_on_the_wire(record: Path) -> None:
    cmds = commands_to(record, 1, LAYOUT.generation)
    assert any(_moving(c, LAYOUT) for c in cmds), "the unit never moved"
    assert is_stop(cmds[-1], LAYOUT), cmds[-1]


# ---------------------------------------------------------------- abh3 run --headless

NAMED_STOPS = [s for s in signals.STOP_SIGNALS if s < signal.SIGRTMIN]
REAL_TIME = [signal.SIGRTMIN, signal.SIGRTMIN + 5, signal.SIGRTMAX]


@pytest.mark.wallclock
@pytest.mark.parametrize("sig", NAMED_STOPS + REAL_TIME, ids=signals.name)
def test_every_catchable_terminating_signal_stops_a_moving_unit(tmp_path: Path, sig: int) -> None:
    proc, record = _headless(tmp_path)
    proc.send_signal(sig)
    _, err = _finish(proc)
    assert proc.returncode == 0, err
    assert f"(signal): {signals.name(sig)}: stop" in err
    assert "stop frame confirmed by the drive" in err and "Traceback" not in err
    _stopped_on_the_wire(record)


@pytest.mark.wallclock
def test_a_second_signal_during_the_stop_changes_nothing(tmp_path: Path) -> None:
    proc, record = _headless(tmp_path)
    proc.send_signal(signal.SIGINT)
    assert proc.stderr is not None
    _until(proc.stderr, "stopping: zero")  # the stop path has begun
    proc.send_signal(signal.SIGTERM)
    _, err = _finish(proc)
    assert proc.returncode == 0, err
    assert "stop frame confirmed by the drive" in err and "Traceback" not in err
    _stopped_on_the_wire(record)


@pytest.mark.wallclock
def test_sigpipe_sigxfsz_and_job_control_change_nothing(tmp_path: Path) -> None:
    """Ignored: were either fatal, the run would end by it (not by SIGUSR2, exit 0); had
    job control stopped it, SIGUSR2 would wait for a SIGCONT that never comes."""
    proc, record = _headless(tmp_path)
    for sig in (signal.SIGPIPE, signal.SIGXFSZ, *signals.JOB_CONTROL):
        proc.send_signal(sig)
    proc.send_signal(signal.SIGUSR2)  # a stop signal after them: the run was still there
    _, err = _finish(proc)
    assert proc.returncode == 0, err
    assert "SIGUSR2: stop" in err and "SIGPIPE" not in err and "SIGTSTP" not in err
    _stopped_on_the_wire(record)


@pytest.mark.wallclock
def test_a_recording_over_the_file_size_limit_ends_and_the_run_goes_on(tmp_path: Path) -> None:
    """A real SIGXFSZ (RLIMIT_FSIZE, from the write itself): the write fails with EFBIG,
    that recording ends with one line, and the drives are stopped as ever (exit 5)."""
    import resource

    cfg = tmp_path / "moving.yaml"
    cfg.write_text(MOVING)
    record = tmp_path / "run.log"

    def small_files() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (20_000, 20_000))

    proc = subprocess.Popen(
        [sys.executable, "-m", "abh3_supervisor", "run", str(cfg), "--headless", "--no-socket",
         "--status-interval", "0", "--record", str(record)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, stdin=subprocess.DEVNULL, text=True,
        cwd=tmp_path, preexec_fn=small_files,
    )  # fmt: skip
    assert proc.stderr is not None
    _until(proc.stderr, "the recording ends here")
    proc.send_signal(signal.SIGTERM)
    _, err = _finish(proc)
    assert proc.returncode == 5, err  # not killed by SIGXFSZ: the recording stopped early
    assert "stop frame confirmed by the drive" in err and "Traceback" not in err
    assert record.stat().st_size <= 20_000


@pytest.mark.wallclock
def test_a_fault_prints_where_it_happened(tmp_path: Path) -> None:
    """SIGSEGV cannot be survived (docs/signals.md): faulthandler says where, every
    thread; the frames cease and the drive's own command-zero timeout stops it."""
    proc, _ = _headless(tmp_path)
    proc.send_signal(signal.SIGSEGV)
    _, err = _finish(proc)
    assert proc.returncode == -signal.SIGSEGV, err
    assert "Fatal Python error: Segmentation fault" in err
    # every thread's stack, the loop's among them (alone, faulthandler says "Stack")
    assert "Current thread 0x" in err


@pytest.mark.wallclock
@pytest.mark.parametrize("sig", [signal.SIGUSR1, signal.SIGXCPU], ids=signals.name)
def test_abh3_run_on_a_terminal_stops_its_child_on_any_terminating_signal(
    tmp_path: Path, sig: int
) -> None:
    """The TUI's half leaves (SIGTERM to its child) on any of them, as on SIGTERM."""
    cfg = tmp_path / "two.yaml"  # two units: the terminal shows "online" twice when up
    cfg.write_text(
        MOVING + '  - {name: v, abh3_id: 3, host_id: 2, protocol: "2023", command_rate_hz: 50,\n'
        '     broadcast: {mask: 0x03, rate_hz: 4}, startup: ["SERVO ON ON", "START ON ON"]}\n'
    )
    # the child's log goes beside the socket as tui.sock.log: a recording named tui.log
    # (its name with .sock replaced, as the log once was) stays a recording
    record = tmp_path / "tui.log"
    sock = tmp_path / "tui.sock"
    pid, fd = in_a_terminal(["run", str(cfg), "--socket", str(sock), "--record", str(record)])
    os.kill(pid, sig)
    assert ended(pid, fd).code == 0
    _stopped_on_the_wire(record)
    v = commands_to(record, 3, LAYOUT.generation)
    assert v and is_stop(v[-1], LAYOUT)


# ---------------------------------------------------------------- abh3 commission

COMMISSION = ROOT / "configs" / "commission-demo.yaml"
SHORT = ["--jog-seconds", "0.3", "--step-seconds", "0.3"]


def _commission(tmp_path: Path) -> tuple[subprocess.Popen[str], Path]:
    record = tmp_path / "run.log"
    proc = _abh3(
        "commission", str(COMMISSION), "front", "--yes", "--wheels-off-ground",
        "--record", str(record), "--report", str(tmp_path / "r.html"), *SHORT, cwd=tmp_path,
    )  # fmt: skip
    assert proc.stdout is not None
    _until(proc.stdout, "jog motor A")
    deadline = time.monotonic() + 10
    while not _jogging(record):  # the recording is flushed every 0.5 s: then it shows
        assert time.monotonic() < deadline and proc.poll() is None, "the jog never went out"
        time.sleep(0.02)
    return proc, record


def _jogging(record: Path) -> bool:
    """Does the recording so far hold a DP0 command to drive 1 with a jog setpoint?"""
    wanted = f"{ids.dp0_command_id(1, 2):08X}#"
    for line in record.read_text().splitlines():  # `(t) channel ID#DATA T`, maybe cut short
        fields = line.split()
        frame = fields[2] if len(fields) == 4 else ""
        if frame.startswith(wanted) and len(frame) == len(wanted) + 16:
            data = bytes.fromhex(frame[len(wanted) :])
            cmd = frames.decode_dp0_command(data, flags.LAYOUT_2021.generation)
            if isinstance(cmd, frames.Dp0Command) and cmd.cmd_ay != 0:
                return True
    return False


def _commission_ended(
    proc: subprocess.Popen[str], record: Path, tmp_path: Path, first: int
) -> None:
    """Ended by ``first``, whatever came after: report, summary, stop frames, no traceback."""
    out, err = _finish(proc)
    assert proc.returncode == 128 + first, out + err
    assert "Traceback" not in err + out
    assert "unit front: stop confirmed" in out and "summary:" in out
    assert f"ended early: stopped by {signals.name(first)}" in out
    report = json.loads((tmp_path / "r.json").read_text())
    assert report["ended"] == f"stopped by {signals.name(first)}"
    assert report["units"]["front"]["stop"] == "confirmed"
    assert (tmp_path / "r.html").exists()
    layout = flags.LAYOUT_2021
    cmds = commands_to(record, 1, layout.generation)
    assert any(c.cmd_ay != 0 for c in cmds), "the jog never went out"
    assert is_stop(cmds[-1], layout), cmds[-1]


@pytest.mark.wallclock
@pytest.mark.parametrize("sig", [signal.SIGUSR1, signal.SIGQUIT], ids=signals.name)
def test_commission_stops_on_any_terminating_signal(tmp_path: Path, sig: int) -> None:
    proc, record = _commission(tmp_path)
    proc.send_signal(sig)
    _commission_ended(proc, record, tmp_path, sig)


@pytest.mark.wallclock
@pytest.mark.parametrize("second", [signal.SIGINT, signal.SIGTERM], ids=["INT,INT", "INT,TERM"])
def test_a_second_signal_while_commissioning_stops_changes_nothing(
    tmp_path: Path, second: int
) -> None:
    proc, record = _commission(tmp_path)
    proc.send_signal(signal.SIGINT)
    time.sleep(0.05)  # the gap is what is tested: a second Ctrl-C 50 ms after the first
    proc.send_signal(second)
    _commission_ended(proc, record, tmp_path, signal.SIGINT)


# ---------------------------------------------------------------- abh3 param

PARAM = """
buses:
  b: {interface: virtual, channel: param, simulate: true}
units:
  - {name: left, abh3_id: 1}
"""


@pytest.mark.wallclock
@pytest.mark.parametrize("sig", [signal.SIGUSR1, signal.SIGRTMIN + 2], ids=signals.name)
def test_param_on_its_own_bus_stops_on_any_terminating_signal(tmp_path: Path, sig: int) -> None:
    cfg = tmp_path / "p.yaml"
    cfg.write_text(PARAM)
    proc = _abh3(
        "param", "-c", str(cfg), "monitor", "left", "VELOCITY_AY", "--interval", "0.01",
        cwd=tmp_path,
    )  # fmt: skip
    assert proc.stdout is not None
    assert proc.stdout.readline().startswith("VELOCITY_AY=")  # running, on its own bus
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=10)
    assert proc.returncode == 128 + sig, err
    assert "Traceback" not in err and f"stopped by {signals.name(sig)}" in err
