"""Step 1 of a unit's commissioning, nothing moves: the drive answers, its firmware, its
CAN settings against the YAML, the DP0 exchange and broadcast rates achieved, errors and
alarms by name, the velocity model it reports, that it stands still and may be commanded.
A unit that fails here is refused: nothing after this step runs for it."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

from abh3_supervisor.commission.model import Verdict
from abh3_supervisor.commission.unit import UnitSteps
from abh3_supervisor.config.model import Config, Role, VelocityModel
from abh3_supervisor.core.supervisor import Supervisor
from abh3_supervisor.core.verify import State
from abh3_supervisor.errors import Abh3Error
from abh3_supervisor.params import table
from abh3_supervisor.protocol import flags
from abh3_supervisor.protocol.frames import Generation

RATE_WINDOW_S = 1.0
MOVING = 0.01  # of limits.velocity (at least 2 min⁻¹): a unit turning faster is refused
# what the report shows of the drive's set-up beside its CAN settings: the selected data
# set's speed, current, ramps and gains (data select 7 = set #0), which the fixes name
PARAMS_READ = (
    0x4100,
    0x4101,
    0x4102,
    0x4103,
    0x4105,
    0x4107,
    0x4117,
    0x4118,
    0x5000,
    0x5008,
    0x5010,
    0x5018,
    0x5020,
    0x5040,
    0x5060,
    0x5070,
)


def startup_motion(config: Config, unit: str, startup: Sequence[str]) -> str | None:
    """The first ``startup:`` line after which ``unit`` has a speed or current set (run on
    a supervisor that sends nothing), or None: such a unit moves as soon as a run starts."""
    cfg = dataclasses.replace(config.units[unit], role=Role.COMMAND, startup=tuple(startup))
    scratch = Supervisor(dataclasses.replace(config, units={unit: cfg}), clock=lambda: 0.0)
    for text in startup:
        scratch.startup(unit, text)  # as the run's start-up does: its input source's
        setpoint = scratch.units[unit].setpoint
        if setpoint.ay or setpoint.bx:
            return text
    return None


class IdentitySteps(UnitSteps):
    async def identity(self) -> bool:
        """Step 1; True when motion may follow."""
        cfg, state = self.cfg, self.state
        self.op.say(
            f"unit {self.unit}: drive {cfg.abh3_id} on bus {cfg.bus}, protocol "
            f"{cfg.protocol}, velocity_model {cfg.velocity_model}"
        )
        if cfg.role is not Role.COMMAND:
            self._check(
                "identity",
                "role",
                Verdict.FAIL,
                "role: monitor",
                "role: command",
                "commissioning moves the motors: a monitor unit is refused; set "
                "role: command for the bring-up",
            )
            self._skip(["e-stop", "motion"], "refused: role: monitor")
            return False
        online = await self._until(lambda: bool(state.online), cfg.timeout_ms / 1000 + 1.0)
        if not online:
            self._check(
                "identity",
                "online",
                Verdict.FAIL,
                "no answer",
                f"abh3_id {cfg.abh3_id}",
                "abh3 scan finds the drive's address and host; check abh3_id, host_id, "
                "the bus bitrate and wiring (docs/hardware.md, troubleshooting)",
            )
            self._skip(["e-stop", "motion"], "offline")
            return False
        self._check("identity", "online", Verdict.PASS, f"drive {cfg.abh3_id} answers")
        await self._firmware()
        await self._settings()
        await self._rates()
        ok = await self._flags()
        fb = state.feedback
        still = max(2.0, MOVING * cfg.limits.velocity)
        if fb is not None and max(abs(fb.vel_a), abs(fb.vel_b)) > still:
            self._check(
                "identity",
                "at rest",
                Verdict.FAIL,
                f"A {fb.vel_a:+.1f}, B {fb.vel_b:+.1f} min⁻¹",
                f"|v| ≤ {still:g} min⁻¹",
                "the unit is already moving: stop whatever drives it first",
            )
            ok = False
        selects = zip(("ay", "bx"), cfg.data_select, strict=True)
        stopped = [f"data_select.{k}" for k, s in selects if s == 0]
        if stopped:  # the drive holds that axis at zero whatever it is asked: nothing to judge
            self._check(
                "identity",
                "data select",
                Verdict.FAIL,
                f"{', '.join(stopped)}: 0 (set #7 & STOP)",
                "1–7",
                f"units.{self.unit}.{stopped[0]} in the YAML: 0 stops the axis; 7 is set #0",
            )
            ok = False
        moves = startup_motion(self.sup.config, self.unit, self.startup)
        if moves is not None:
            self._check(
                "identity",
                "at rest",
                Verdict.FAIL,
                f"startup: {moves!r} sets it moving when a run starts",
                "a unit at rest (no speed or current in startup:)",
                f"take the motion out of units.{self.unit}.startup in the YAML (or commission "
                "a copy without it): a bring-up begins with the robot still",
            )
            ok = False
        if state.verify.holds():
            why = "verify: refuse holds the unit at its idle word (its settings differ)"
            self._check(
                "identity",
                "commandable",
                Verdict.FAIL,
                why,
                "",
                "fix the settings above, or verify: warn",
            )
            ok = False
        if not ok:
            self._skip(["e-stop", "motion"], "identity checks failed")
        return ok

    async def _firmware(self) -> None:
        try:
            self.result.firmware = await self.bench.identity(self.unit)
        except Abh3Error as exc:
            self._check(
                "identity",
                "firmware version",
                Verdict.WARN,
                f"not read: {exc}",
                "",
                "the drive's parameter channel (docs/parameters.md)",
            )
            return
        self._check("identity", "firmware version", Verdict.PASS, self.result.firmware)
        for address in PARAMS_READ:
            try:
                word = await self.bench.read_param(self.unit, address)
            except Abh3Error as exc:
                self.result.params[address] = f"not read: {exc}"
                continue
            value = table.to_value(word, table.kind_of(address))
            self.result.params[address] = table.display(value)

    async def _settings(self) -> None:
        v = await self.bench.verification(self.unit)
        self.result.settings_rows = [row.to_json() for row in v.rows]
        if v.state is State.OK:
            self._check("identity", "CAN settings", Verdict.PASS, f"{len(v.rows)} agree with YAML")
        elif v.state is State.MISMATCH:
            for row in v.rows:
                if row.mismatch:
                    self._check(
                        "identity",
                        f"CAN setting 0x{row.address:04X} {row.name}",
                        Verdict.FAIL,
                        f"drive {row.drive}",
                        f"YAML {row.yaml}",
                        f"set the drive (abh3 param set {self.unit} "
                        f"0x{row.address:04X} …) or the YAML",
                    )
        else:
            self._check(
                "identity",
                "CAN settings",
                Verdict.WARN,
                f"{v.state}: {v.reason or ''}".rstrip(": "),
                "",
                "abh3 check CONFIG --drives once the drive answers parameter requests",
            )

    async def _rates(self) -> None:
        cfg = self.cfg
        before = self.collector.feedbacks, self.collector.statuses
        await self._wait(RATE_WINDOW_S)
        dp0 = (self.collector.feedbacks - before[0]) / RATE_WINDOW_S
        brd = (self.collector.statuses - before[1]) / RATE_WINDOW_S
        want = cfg.command_rate_hz
        verdict = Verdict.PASS if dp0 >= 0.9 * want else Verdict.WARN
        self._check(
            "identity",
            "DP0 exchange rate",
            verdict,
            f"{dp0:.1f} /s",
            f"{want:g} /s",
            ""
            if verdict is Verdict.PASS
            else "lower command_rate_hz or the bus load "
            "(`abh3 check` shows the plan); slow replies: 0x4105",
        )
        if cfg.broadcast.packets and not cfg.broadcast.listen_only:
            want = cfg.broadcast.rate_hz
            verdict = Verdict.PASS if brd >= 0.9 * want else Verdict.WARN
            self._check(
                "identity",
                "broadcast rate",
                verdict,
                f"{brd:.1f} /s",
                f"{want:g} /s",
                ""
                if verdict is Verdict.PASS
                else "broadcast.rate_hz, broadcast group 0x4107 (brd_group)",
            )

    async def _fresh(self, packet: int) -> None:
        since = self.bench.now()
        seen = self.state.status.get(packet)
        self.sup.request_status(self.unit, packet)
        await self._until(
            lambda: (
                (s := self.state.status.get(packet)) is not None and s is not seen and s[0] >= since
            ),
            self.cfg.timeout_ms / 1000,
        )

    async def _flags(self) -> bool:
        """Errors and alarms by name; the velocity model the drive reports."""
        await self._fresh(0)
        error = self.state.words.get("error")
        alarm = self.state.words.get("alarm", 0)
        ok = True
        if error is None:
            self._check("identity", "errors", Verdict.WARN, "broadcast 0 not answered")
        elif error:
            names = ", ".join(flags.FAULT.labels(error))
            self._check(
                "identity",
                "errors",
                Verdict.FAIL,
                names,
                "none",
                "remove the cause, then reset the error (SERVO OFF, error reset)",
            )
            ok = False
        else:
            self._check("identity", "errors", Verdict.PASS, "none")
        if alarm:
            self._check(
                "identity",
                "alarms",
                Verdict.WARN,
                ", ".join(flags.FAULT.labels(alarm)),
                "none",
                "see docs/hardware.md, troubleshooting",
            )
        else:
            self._check("identity", "alarms", Verdict.PASS, "none")
        if self.cfg.protocol is Generation.G2021:
            await self._fresh(1)
        else:
            await self._until(lambda: "control" in self.state.words, 0.5)
        if not self._generation():
            return False
        control = self.state.words.get("control")
        if control is None:
            self._check("identity", "velocity model", Verdict.WARN, "control word not read")
            return ok
        travel = bool(control & self.state.layout.travel_model)
        drive = VelocityModel.TRAVEL if travel else VelocityModel.MOTOR
        if drive is not self.cfg.velocity_model:
            self._check(
                "identity",
                "velocity model",
                Verdict.FAIL,
                f"drive: {drive}",
                f"YAML velocity_model: {self.cfg.velocity_model}",
                f"velocity_model: {drive} in the YAML (or the drive's axis model)",
            )
            return False
        self._check("identity", "velocity model", Verdict.PASS, str(drive))
        return ok

    def _generation(self) -> bool:
        """The drive's frames in the file's protocol generation's layout (False: named,
        with its fix). Bytes 4–7 of a DP0 reply tell: a 2021 drive puts its Y and X
        velocities there, (A ± B) / 2 of bytes 0–3; a 2023 drive its control word, never
        0 while the host writes a data select (the word reflects it)."""
        file, fb = self.cfg.protocol, self.state.feedback
        if fb is None:
            return True
        sent = self.state.inputs & self.state.layout.select_mask
        if file is Generation.G2021:
            first, second, y, x = fb.vel_a, fb.vel_b, fb.vel_y, fb.vel_x
            wrong = not _y_and_x(first, second, y, x)
            raw = _raw(y) | _raw(x) << 16
            what = f"DP0 reply bytes 4–7 0x{raw:08X} are no Y/X velocities of its A and B"
        else:
            control = fb.control or 0
            travel = self.cfg.velocity_model is VelocityModel.TRAVEL
            first, second = (fb.vel_y, fb.vel_x) if travel else (fb.vel_a, fb.vel_b)
            y, x = (_int16(control & 0xFFFF) * 0.2, _int16(control >> 16) * 0.2)
            moving = _y_and_x(first, second, y, x) and bool(first or second)
            wrong = moving or (bool(sent) and not control)
            what = (
                f"DP0 reply bytes 4–7 0x{control:08X}: Y/X velocities, not a control word "
                f"(which would reflect the data select written, 0x{sent:08X})"
            )
        if not wrong:
            self._check("identity", "protocol generation", Verdict.PASS, f"{file} frames")
            return True
        other = Generation.G2023 if file is Generation.G2021 else Generation.G2021
        self._check(
            "identity",
            "protocol generation",
            Verdict.FAIL,
            f"the drive answers in {other}'s layout: {what}",
            f'protocol: "{file}"',
            f'protocol: "{other}" for units.{self.unit} in the YAML: the flag words of the '
            f"two generations differ (a {file} word sent to a {other} drive sets the wrong "
            "bits, e.g. torque mode on both axes)",
        )
        return False


def _y_and_x(a: float, b: float, y: float, x: float) -> bool:
    """Are ``y`` and ``x`` the travel and turn velocities of motors ``a`` and ``b``
    (within the wire's rounding)?"""
    return abs(y - (a + b) / 2) <= 0.5 and abs(x - (a - b) / 2) <= 0.5


def _raw(value: float) -> int:
    return round(value / 0.2) & 0xFFFF


def _int16(word: int) -> int:
    return word - 0x10000 if word & 0x8000 else word
