"""``abh3 commission CONFIG [UNIT…]``: the commissioning sequence (abh3_supervisor/
commission/) on the configuration's own buses, in a :class:`Runtime` of its own.

Why its own runtime and not a running supervisor's socket: the sequence needs every DP0
answer the moment it arrives (the guard stops a unit from the answer that shows a fault,
not 100 ms later from a pushed snapshot) and the time each frame left (the e-stop figure);
and the runtime's way out — normal end, e-stop, Ctrl-C, SIGTERM, SIGHUP, an internal
error — already stops every commanded drive with the safe word and waits for the drive to
confirm it. Motion still goes through the input arbitration: one source per unit with a
short timeout, so a stalled sequence lets the jog lapse to zero.

Units not named are monitors (never commanded); no unit runs its ``startup:`` and no
plugin is loaded: only this sequence moves anything. On a terminal, ``e`` is the e-stop
at every moment, questions take ``y``/``n``, the robot step's one key per answer (which
wheel, which way) and a typed number (a measured distance or angle); without one,
``--wheels-off-ground`` and ``--yes`` are the operator's consent, the e-stop rehearsal
presses the key itself, and on real drives the robot step is not run (nobody to say
which wheel turned; in simulation the simulated robot tells).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import dataclasses
import datetime
import logging
import os
import sys
import termios
import tty
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path

from abh3_supervisor import __version__
from abh3_supervisor.commission.model import Settings, Verdict
from abh3_supervisor.commission.report import Session, html_text, json_text
from abh3_supervisor.commission.robot import RobotResult
from abh3_supervisor.commission.sequence import SOURCE_TIMEOUT_S, commission
from abh3_supervisor.commission.unit import Aborted, RobotView, UnitResult
from abh3_supervisor.config.model import Config, Role
from abh3_supervisor.core.inputs import InputSource
from abh3_supervisor.core.kinematics import ab_to_yx
from abh3_supervisor.core.verify import Verification
from abh3_supervisor.errors import Abh3Error, ConfigError, RunError
from abh3_supervisor.params import table
from abh3_supervisor.params.telabh3 import Command
from abh3_supervisor.plugin_host.feed import InputFeed
from abh3_supervisor.plugin_host.host import PluginHost
from abh3_supervisor.runtime import signals
from abh3_supervisor.runtime.bus_runtime import Runtime
from abh3_supervisor.runtime.listening import refuse_if_commanded
from abh3_supervisor.runtime.priority import Priority, bus_priority
from abh3_supervisor.runtime.recorder import check_format
from abh3_supervisor.runtime.recording import recorded, recording
from abh3_supervisor.runtime.stopping import EXIT_STOP_UNCONFIRMED
from abh3_supervisor.service.param_ops import ParamOps

log = logging.getLogger("abh3")
ESTOP_KEY_WAIT_S = 30.0  # the rehearsal waits this long for the key


class _Intermixed(argparse.ArgumentParser):
    """UNIT… may follow the options (`abh3 commission robot.yaml --yes front`): Python
    3.11's argparse gives a ``*`` positional its (empty) share at the first one."""

    _inside = False

    def parse_known_args(  # type: ignore[override]
        self, args: Sequence[str] | None = None, namespace: argparse.Namespace | None = None
    ) -> tuple[argparse.Namespace, list[str]]:
        if self._inside:  # the intermixed parse calls back here, twice
            return super().parse_known_args(args, namespace)
        self._inside = True
        try:
            return self.parse_known_intermixed_args(args, namespace)
        finally:
            self._inside = False


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    d = Settings()
    c = sub.add_parser(
        "commission",
        help="bring up drives step by step (identity, e-stop, wiring, step response) and report",
    )
    c.__class__ = _Intermixed
    c.add_argument("config", type=Path)
    c.add_argument("units", nargs="*", metavar="UNIT", help="the units to commission (all)")
    c.add_argument("--report", type=Path, metavar="FILE.html", help="the HTML report; .json beside")
    c.add_argument("--record", type=Path, metavar="FILE", help="record the session (.mcap, .log…)")
    c.add_argument(
        "--wheels-off-ground",
        action="store_true",
        help="confirm that every unit's wheels are off the ground (needed without a terminal)",
    )
    c.add_argument("--yes", "-y", action="store_true", help="run every jog and step without asking")
    bounds = Settings.BOUNDS
    for key, help_text in (
        ("jog_fraction", "jog and step speed, a fraction of limits.velocity"),
        ("jog_s", "each jog direction, s"),
        ("step_s", "the step's hold, s"),
        ("scale_tolerance", "pulses/rev against geometry.pulses_per_rev"),
    ):
        lo, hi, _ = bounds[key]
        c.add_argument(
            Settings.flag(key),
            dest=key,
            type=float,
            metavar="S" if key.endswith("_s") else "F",
            default=getattr(d, key),
            help=f"{help_text} ({lo:g}–{hi:g}; default {getattr(d, key):g})",
        )


def run(args: argparse.Namespace) -> int:
    from abh3_supervisor.config import load_config

    config = load_config(args.config)
    settings = Settings(
        jog_fraction=args.jog_fraction,
        jog_s=args.jog_s,
        step_s=args.step_s,
        scale_tolerance=args.scale_tolerance,
    ).check()
    units = _units(config, args.units)
    slow = [
        f"{config.file}: {why}"
        for u in units
        if config.units[u].role is Role.COMMAND
        and (why := settings.too_slow(u, config.units[u].limits.velocity))
    ]
    if slow:
        raise ConfigError(slow)
    if args.report is not None:
        if args.report.suffix.lower() not in (".html", ".htm"):
            raise Abh3Error(
                f"--report {args.report}: name the HTML file (FILE.html; FILE.json beside)"
            )
        _writable("--report", args.report)
        _writable("--report", args.report.with_suffix(".json"))
    if args.record is not None:
        check_format(args.record)  # as `abh3 run` does: exit 2 before anything opens
        _writable("--record", args.record)
    # the jogs and the e-stop figure are timed on the bus loop: as `abh3 run` runs it
    with bus_priority(Priority.AUTO) as priority:
        log.debug("%s", priority)  # -v; the figures in the report are what it shows
        return asyncio.run(_session(config, units, settings, args))


def _units(config: Config, named: Sequence[str]) -> list[str]:
    """The units to commission, each once in order (all when none is named); a robot's
    name stands for its units."""
    out: list[str] = []
    unknown = []
    for name in dict.fromkeys(named):  # each once
        robot = config.robots.get(name) if name not in config.units else None
        if name in config.units:
            out.append(name)
        elif robot is not None:
            print(f"robot {name}: its units {', '.join(robot.units)}", flush=True)
            out += robot.units
        else:
            unknown.append(name)
    if unknown:
        robots = [r for r, robot in config.robots.items() if not robot.implicit]
        what = "unit or robot" if robots else "unit"
        also = f"; robots: {', '.join(robots)}" if robots else ""
        raise ConfigError(
            [
                f"{config.file}: no {what} named {u!r} (units: {', '.join(config.units)}{also})"
                for u in unknown
            ]
        )
    return list(dict.fromkeys(out)) or list(config.units)


def _writable(option: str, path: Path) -> None:
    """Can ``path`` be written? Asked before anything opens or moves, not found out after
    the session (a report lost at the end of a bring-up); leaves no file behind."""
    existed = path.exists()
    try:
        with path.open("a", encoding="utf-8"):
            pass
    except OSError as exc:
        raise Abh3Error(f"{option} {path}: cannot write: {exc.strerror}") from None
    if not existed:
        path.unlink(missing_ok=True)


def for_commissioning(config: Config, units: Sequence[str]) -> Config:
    """Only the named units are commanded, none runs its start-up, no plugin loads."""
    out = {
        n: dataclasses.replace(u, startup=(), role=u.role if n in units else Role.MONITOR)
        for n, u in config.units.items()
    }
    return dataclasses.replace(config, units=out, plugins={})


class _Source(InputSource):
    def __init__(self, unit: str) -> None:
        super().__init__(f"commission:{unit}", (unit,), priority=100, timeout=SOURCE_TIMEOUT_S)
        self.feed: InputFeed | None = None

    def start(self, feed: InputFeed) -> None:
        self.feed = feed

    def stop(self) -> None:
        self.feed = None


class LiveBench:
    """The sequence's bench on a running :class:`Runtime`: real time, the arbitration, the
    frames each pump sent (with the loop's time at the send) and the parameter channel."""

    def __init__(self, rt: Runtime, plugins: PluginHost, units: Sequence[str]) -> None:
        self.rt, self.sup = rt, rt.supervisor
        self.loop = asyncio.get_running_loop()
        self.sent: list[tuple[float, int, bytes]] = []
        self.ops = ParamOps(self.sup, lambda bus: rt.pumps[bus].wake())
        self.sources: dict[str, _Source] = {}
        for unit in units:
            source = _Source(unit)
            plugins.attach(source)
            self.sources[unit] = source
        for pump in rt.pumps.values():
            pump.send = self._tap(pump.send)  # type: ignore[method-assign,assignment]

    def _tap(self, send: Callable[[int, bytes], bool]) -> Callable[[int, bytes], bool]:
        """The pump's send, noting when each frame left (the loop's clock, as the key's)."""

        def tapped(arbitration_id: int, data: bytes) -> bool:
            ok = send(arbitration_id, data)
            if ok:
                self.sent.append((self.loop.time(), arbitration_id, data))
            return ok

        return tapped

    def now(self) -> float:
        return self.loop.time()

    def estop(self) -> float:
        """The e-stop key, pressed now (its time returned): latched in the supervisor,
        which sends each commanded unit's stop frame at once (core/gate.py)."""
        t = self.now()
        self.sup.emergency_stop("commission")
        return t

    async def wait(self, seconds: float) -> None:
        await asyncio.sleep(max(0.0, seconds))

    def move(self, unit: str, a: float, b: float) -> None:
        feed = self.sources[unit].feed
        if feed is not None:
            y, x = ab_to_yx(a, b)
            feed.velocity_yx(y, x)

    def release(self, unit: str) -> None:
        feed = self.sources[unit].feed
        if feed is not None:
            feed.release()

    def twist(self, unit: str, linear_x: float, angular_z: float) -> None:
        feed = self.sources[unit].feed
        if feed is not None:
            feed.twist(linear_x, angular_z)

    def wire(self) -> Sequence[tuple[float, int, bytes]]:
        return self.sent

    async def identity(self, unit: str) -> str:
        return await self.ops.identity(unit, table.FIRMWARE_VERSION)

    async def read_param(self, unit: str, address: int) -> int:
        return await self.ops.read(unit, Command.PARAM, address)

    async def verification(self, unit: str) -> Verification:
        if self.rt.verifying is not None:  # the start-up check reads them once for all
            with contextlib.suppress(Exception):
                await asyncio.shield(self.rt.verifying)
        return self.sup.units[unit].verify

    def sim_robot(self, name: str) -> RobotView | None:
        for sim in self.rt.sims.values():
            if name in sim.robots:
                return sim.robots[name]
        return None


class TerminalOperator:
    """Questions and the e-stop on a terminal (``e`` at any moment; ``y``/``n``, one key
    per choice, a typed number), or the flags' consent without one."""

    def __init__(self, bench: LiveBench, args: argparse.Namespace, keys: bool) -> None:
        self.bench, self.args, self.keys = bench, args, keys
        self.interactive = keys
        self._answer: asyncio.Future[str] | None = None
        self._estop: asyncio.Future[float] | None = None
        self._keys = ""  # the keys the open question takes; "yn": a yes/no one
        self._line: list[str] | None = None  # a number being typed

    def say(self, text: str) -> None:
        print(text, flush=True)

    def key(self, char: str) -> None:
        """A key from the terminal (on the loop): the e-stop acts before anything else."""
        if char in ("e", "E"):
            t = self.bench.estop()
            asking = self._answer is not None and not self._answer.done()
            self.say(("\n" if asking else "") + "  E-STOP: every unit zero, START off")
            if self._estop is not None and not self._estop.done():
                self._estop.set_result(t)
            elif self._answer is not None and not self._answer.done():
                self._answer.set_exception(Aborted("e-stop pressed"))  # ends the session now
        elif self._answer is None or self._answer.done():
            return
        elif self._line is not None:
            self._typed(char)
        elif self._keys == "yn" and char in "yYnN\r\n":
            self._answer.set_result("y" if char in "yY" else "n")  # [y/N]: Enter is no
        elif self._keys != "yn" and char.lower() in self._keys:
            self._answer.set_result(char.lower())

    def _typed(self, char: str) -> None:
        """A number's keys: digits, a point, a minus; backspace; Enter ends it."""
        assert self._answer is not None and self._line is not None
        if char in "\r\n":
            self._answer.set_result("".join(self._line))
        elif char in ("\x7f", "\b") and self._line:
            self._line.pop()
            print("\b \b", end="", flush=True)
        elif char in "0123456789.-":
            self._line.append(char)
            print(char, end="", flush=True)

    async def confirm(self, question: str) -> bool:
        wheels = "OFF THE GROUND" in question
        if (wheels and self.args.wheels_off_ground) or (not wheels and self.args.yes):
            self.say(f"{question} yes ({'--wheels-off-ground' if wheels else '--yes'})")
            return True
        if not self.keys:
            flag = "--wheels-off-ground" if wheels else "--yes"
            self.say(f"{question} no (no terminal to ask: {flag} gives consent)")
            return False
        self._answer, self._keys = asyncio.get_running_loop().create_future(), "yn"
        print(f"{question} [y/N] ", end="", flush=True)
        answer = await self._answer
        self.say(answer)
        return answer == "y"

    async def choose(self, question: str, options: Sequence[tuple[str, str]]) -> str | None:
        if not self.keys:
            self.say(f"{question} (no terminal to ask)")
            return None
        self._answer = asyncio.get_running_loop().create_future()
        self._keys = "".join(k.lower() for k, _ in options)
        listed = ", ".join(f"{k} {meaning}" for k, meaning in options)
        print(f"{question} [{listed}] ", end="", flush=True)
        answer = await self._answer
        self.say(dict((k.lower(), m) for k, m in options)[answer])
        return answer

    async def measure(self, question: str) -> float | None:
        if not self.keys:
            self.say(f"{question} (no terminal to ask)")
            return None
        while True:
            self._answer, self._line = asyncio.get_running_loop().create_future(), []
            print(f"{question} ", end="", flush=True)
            try:
                text = await self._answer
            finally:
                self._line = None
            self.say("")
            if not text:
                return None
            try:
                return float(text)
            except ValueError:
                self.say(f"  {text!r} is not a number: again, or Enter to skip")

    async def press_estop(self, prompt: str) -> float | None:
        if not self.keys:
            self.say(f"{prompt} (no terminal: pressed by the tool itself)")
            return self.bench.estop()
        self._estop = asyncio.get_running_loop().create_future()
        self.say(prompt)
        try:
            async with asyncio.timeout(ESTOP_KEY_WAIT_S):
                return await self._estop
        except TimeoutError:
            return None
        finally:
            self._estop = None


@contextlib.contextmanager
def _keys(operator: TerminalOperator) -> Iterator[None]:
    """Single keys from the terminal, read on the loop; Ctrl-C still signals."""
    if not operator.keys:
        yield
        return
    fd = sys.stdin.fileno()
    saved = termios.tcgetattr(fd)
    loop = asyncio.get_running_loop()

    def readable() -> None:
        try:
            data = os.read(fd, 64)
        except OSError:
            data = b""
        if not data:
            loop.remove_reader(fd)
            return
        for char in data.decode(errors="replace"):
            operator.key(char)

    tty.setcbreak(fd)
    loop.add_reader(fd, readable)
    try:
        yield
    finally:
        loop.remove_reader(fd)
        termios.tcsetattr(fd, termios.TCSADRAIN, saved)


async def _session(
    config: Config, units: list[str], settings: Settings, args: argparse.Namespace
) -> int:
    # the signal handlers outlive the runtime's block: a signal during the stop, the
    # report or the recording's close changes nothing (the first one stopped the sequence)
    with contextlib.ExitStack() as handled:
        return await _commissioning(config, units, settings, args, handled)


async def _commissioning(
    config: Config,
    units: list[str],
    settings: Settings,
    args: argparse.Namespace,
    handled: contextlib.ExitStack,
) -> int:
    loop = asyncio.get_running_loop()
    began = datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")
    used = for_commissioning(config, units)
    plugins = PluginHost(used, available={})
    # two hosts commanding one drive fight over it: refused before anything is sent
    await refuse_if_commanded(used, units, "abh3 commission")
    if args.record is not None:
        print(recording(args.record), flush=True)
    # commissioning moves one wheel at a time: each drive is decided alone
    rt = Runtime(used, record=args.record, plugins=plugins, whole_robots=False)
    results: dict[str, UnitResult] = {}
    robots: dict[str, RobotResult] = {}
    ended: str | None = None
    stopped_by: list[int] = []  # the signal that ended the sequence
    async with rt:
        bench = LiveBench(rt, plugins, units)
        operator = TerminalOperator(bench, args, keys=sys.stdin.isatty() and sys.stdout.isatty())
        sequence: list[asyncio.Future[str | None]] = []  # once it has begun

        def on_signal(signum: int) -> None:
            # the first ends the sequence, and the way out follows as after any end; no
            # signal cancels anything else, so the stop, the report and the recording's
            # close run to their end whatever comes after (docs/signals.md)
            if not stopped_by and sequence and not sequence[0].done():
                stopped_by.append(signum)
                sequence[0].cancel()

        handled.enter_context(signals.on_loop(loop, on_signal))
        with _keys(operator):
            operator.say(
                f"commissioning {', '.join(units)} from {config.file}"
                + ("; e = E-STOP at any moment, Ctrl-C stops everything" if operator.keys else "")
            )
            fatal = asyncio.ensure_future(rt.fatal) if rt.fatal is not None else None
            startups = {u: config.units[u].startup for u in units}
            run = asyncio.ensure_future(
                commission(bench, operator, units, settings, results, startups, robots)
            )
            sequence.append(run)
            waiting = {run} | ({fatal} if fatal is not None else set())
            try:
                await asyncio.wait(waiting, return_when=asyncio.FIRST_COMPLETED)
            finally:
                if not run.done():
                    run.cancel()
                    ended = ended or "internal error: the run stopped"
                    with contextlib.suppress(asyncio.CancelledError, Exception):
                        await run
            if run.done() and not run.cancelled() and run.exception() is None:
                ended = run.result()
        if stopped_by:
            ended = f"stopped by {signals.name(stopped_by[0])}"
    stops = rt.stop_report
    if args.record is not None:
        print(recorded(rt, args.record))
    for unit in units:
        print(f"unit {unit}: stop {stops.get(unit, 'not commanded')}")
    session = Session(
        tool=f"abh3-supervisor {__version__}",
        time=began,
        config_file=str(config.file),
        yaml=config.text,
        settings=settings,
        results=results,
        ended=ended,
        stops=stops,
        record=str(args.record) if args.record else None,
        robots=robots,
    )
    _summary(session)
    if args.report is not None:
        _write(args.report, html_text(session))
        _write(args.report.with_suffix(".json"), json_text(session))
        print(f"report: {args.report} and {args.report.with_suffix('.json')}")
    if stopped_by:
        return 128 + stopped_by[0]
    if not rt.stops_confirmed:
        return EXIT_STOP_UNCONFIRMED
    verdicts = [r.verdict for r in results.values()] + [r.verdict for r in robots.values()]
    failed = ended is not None or Verdict.FAIL in verdicts
    return 1 if failed else 0


def _summary(s: Session) -> None:
    print("summary:")
    for name, r in s.results.items():
        fails = [c for c in r.checks if c.verdict is Verdict.FAIL]
        line = f"  {name}: {r.verdict.value.upper()}"
        if fails:
            line += " — " + "; ".join(f"{c.step}: {c.name}" for c in fails)
        print(line)
        for c in fails:
            if c.fix:
                print(f"    fix ({c.name}): {c.fix}")
    for name, robot in (s.robots or {}).items():
        fails = [c for c in robot.checks if c.verdict is Verdict.FAIL]
        print(f"  robot {name}: {robot.verdict.value.upper()}")
        for c in fails:
            print(f"    {c.name}: {c.measured}" + (f"\n    fix: {c.fix}" if c.fix else ""))
        if robot.ended:  # after the fails it may refer to ("fix the wheels above first")
            print(f"    {robot.ended}")
    if s.ended:
        print(f"  ended early: {s.ended}")


def _write(path: Path, text: str) -> None:
    try:
        path.write_text(text, encoding="utf-8")
    except OSError as exc:
        raise RunError(f"--report {path}: cannot write: {exc.strerror}") from exc
