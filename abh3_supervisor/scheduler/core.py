"""The sans-I/O bus scheduler: frames and a clock in, frames out, events recorded.

One instance per bus. For each unit it keeps the DP0 exchange going at the unit's
command rate (also the keepalive the drive's command-zero timeout needs, doc §6), polls
its broadcast packets round-robin, matches replies ignoring the priority bits, and tracks
health. Commands always go before status polls. Nothing here reads a clock or touches a
bus: the caller passes ``now`` in and sends what :meth:`poll` returns.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Iterable, Mapping
from dataclasses import dataclass

from abh3_supervisor.config.model import UNITS_PER_TURN, Role, UnitConfig
from abh3_supervisor.core.foreign import Foreign, ForeignWatch
from abh3_supervisor.core.timing import next_on_grid
from abh3_supervisor.params.session import ParamChannel
from abh3_supervisor.protocol import frames
from abh3_supervisor.protocol.ids import (
    MATCH_MASK,
    broadcast_id,
    dp0_command_id,
    dp0_reply_id,
    request_id,
    without_priority,
)
from abh3_supervisor.scheduler.stats import UnitStats

OutFrame = tuple[int, bytes]
_DP0_REQUEST = frames.encode_request(frames.PGN_DP0)


@dataclass(frozen=True, slots=True)
class FeedbackEvent:
    unit: str
    t: float
    reply: frames.Dp0Reply | frames.Unknown
    sent_at: float | None  # when the answered request went out; None if unsolicited
    data: bytes = b""  # the reply's bytes: what they show of the drive's generation


@dataclass(frozen=True, slots=True)
class StatusEvent:
    unit: str
    t: float
    packet: int
    record: frames.Broadcast | frames.Unknown
    sent_at: float | None = None  # when the request it answers went; None: unasked


@dataclass(frozen=True, slots=True)
class HealthEvent:
    unit: str
    t: float
    online: bool


@dataclass(frozen=True, slots=True)
class GapEvent:
    """No DP0 exchange completed for the drive's timeout (``started``), or one did again.

    The drive has then stopped itself (command-zero timeout, doc §6); it must not resume
    with the old setpoint when frames flow again.
    """

    unit: str
    t: float
    started: bool


@dataclass(frozen=True, slots=True)
class MalformedEvent:
    """A frame with one of the unit's reply ids that is not a valid reply: not counted."""

    unit: str
    t: float
    kind: str  # "dp0 reply" or "broadcast N"
    reason: str


@dataclass(frozen=True, slots=True)
class ForeignEvent:
    """Another host's frames on the unit's drive began an episode (core/foreign.py): the
    record, updated in place as more of its frames come."""

    unit: str
    t: float
    host: Foreign


Event = FeedbackEvent | StatusEvent | HealthEvent | GapEvent | MalformedEvent | ForeignEvent
VALID_LENGTH = 8  # every DP0 reply and broadcast 0-6 carries 8 bytes (doc §3)
# a gap is declared this much before the drive's own timeout would fire, so a frame on its
# way when the timeout passes cannot reach a drive that has already stopped itself
GAP_MARGIN = 0.005
# no automatic restart, whatever the outage: a drive that lost its power and booted again
# within its own command-zero timeout would take our SERVO and START as if nothing had
# happened, so a silence this long (or two exchanges and a reply timeout, at a slow rate)
# is a gap too, at most the drive's timeout. A drive cannot lose power and boot in less (a
# real one takes about a second): docs/safety.md, "The robot decision"
OUTAGE_S = 0.5


class UnitSlot:
    """One unit's schedule and exchange state inside a :class:`BusScheduler`."""

    def __init__(self, cfg: UnitConfig, start: float) -> None:
        self.cfg = cfg
        self.period = 1.0 / cfg.command_rate_hz
        # One DP0 exchange in flight (replies carry no sequence number). It waits for its
        # reply at most ``exchange_timeout``, short enough that a lost reply never starves
        # the drive's command-zero timeout; ``timeout`` (the seed's) decides offline.
        self.timeout = cfg.timeout_ms / 1000
        self.exchange_timeout = min(self.timeout, cfg.reply_timeout_ms / 1000)
        self.commanding = cfg.role is Role.COMMAND
        self.command_id = (
            dp0_command_id(cfg.abh3_id, cfg.host_id, cfg.priority)
            if self.commanding
            else request_id(cfg.abh3_id, cfg.host_id, cfg.priority)
        )
        self.payload = frames.encode_dp0_command(0, 0, 0) if self.commanding else _DP0_REQUEST
        self.next_command = start
        self.dp0_sent_at: float | None = None
        self.last_sent: float | None = None
        self.polls = () if cfg.broadcast.listen_only else cfg.broadcast.packets
        self.poll_period = 1.0 / cfg.broadcast.rate_hz
        self.poll_id = request_id(cfg.abh3_id, cfg.host_id, cfg.priority)
        # every packet's request, built once: polls and on-demand requests cost no allocation
        self.poll_frames: list[OutFrame] = [
            (self.poll_id, frames.encode_request(frames.broadcast_pgn(cfg.brd_group, n)))
            for n in range(8)
        ]
        self.next_poll = start + self.period / 2  # interleave with the commands
        self.poll_index = 0
        self.poll_sent_at: float | None = None
        self.poll_packet = -1  # the packet asked for by the request in flight
        self.asked: list[int] = []  # on-demand requests (seed brd_num), before the polls
        self.online: bool | None = None  # None until first heard or first timed out
        # the drive's command-zero timeout, counted from the send time of the last answered
        # command (the latest instant the drive surely had it): never later than the drive's
        self.drive_timeout = cfg.drive_timeout_ms / 1000 if cfg.drive_timeout_ms else math.inf
        self.outage = min(
            self.drive_timeout, max(OUTAGE_S, 2 * self.period + self.exchange_timeout)
        )
        self.heard_at: float | None = None
        self.gap = False
        self.since = start
        self.stats = UnitStats(cfg.command_rate_hz)
        # when each DP0 exchange of ours ended without its reply (timed out, or replaced by
        # a stop frame sent at once): its reply may still come, late; see unasked()
        self.orphans: list[float] = []
        # the deadlines (deadlines()) and the earliest of them: kept by the scheduler
        # after every change to what they are computed from (refresh())
        self.command_at = self.poll_at = self.gap_at = self.offline_at = self.due = 0.0
        self.refresh()

    def orphan(self, now: float) -> None:
        """The exchange in flight ends unanswered (its reply may yet come)."""
        if self.dp0_sent_at is not None:
            self.orphans.append(now)

    def unasked(self, now: float) -> bool:
        """A DP0 reply came with no exchange of ours in flight: True if none of ours can
        explain it. Replies carry no sequence number, so a late reply answers whichever
        exchange is in flight when it comes, and the one after it then arrives with none:
        each exchange that ended unanswered within ``timeout`` (the seed's offline timeout,
        well beyond any reply's delay) accounts for one such reply."""
        self.orphans = [t for t in self.orphans if now - t <= self.timeout]
        if self.orphans:
            self.orphans.pop(0)
            return False
        return True

    def deadlines(self) -> tuple[float, float, float, float]:
        """When each thing of this unit falls due — the one place they are defined:

        * the next DP0 request: on its grid, after the one in flight ends;
        * the next status request: one in flight per unit, until it expires (an
          on-demand one as soon as allowed);
        * a gap: nothing heard for ``outage`` after the last answered command;
        * offline: nothing heard from the unit for ``timeout``."""
        command = self.next_command
        if self.dp0_sent_at is not None and self.dp0_sent_at + self.exchange_timeout > command:
            command = self.dp0_sent_at + self.exchange_timeout
        if not self.polls and not self.asked:
            poll = math.inf
        else:
            poll = -math.inf if self.asked else self.next_poll
            if self.poll_sent_at is not None and self.poll_sent_at + self.timeout > poll:
                poll = self.poll_sent_at + self.timeout
        if not self.commanding or self.gap or self.heard_at is None:
            gap = math.inf
        else:
            gap = self.heard_at + self.outage - GAP_MARGIN
        if self.online is False:
            offline = math.inf
        else:
            last = self.stats.last_seen
            offline = (last if last is not None else self.since) + self.timeout
        return command, poll, gap, offline

    def earliest_due(self) -> float:
        """When anything of this unit falls due: a command, a poll, a gap, going offline."""
        return min(self.deadlines())

    def refresh(self) -> None:
        """After any change to what the deadlines are computed from: the step reads
        these numbers instead of computing them again."""
        self.command_at, self.poll_at, self.gap_at, self.offline_at = at = self.deadlines()
        self.due = min(at)

    def zero_command(self) -> None:
        """The drive stopped itself (gap, offline): the very next frame must not carry the
        old command, so its command fields are zeroed here, before anything is sent; the
        input bits stay (the supervisor zeroes its setpoint too, when it hears of it)."""
        if self.commanding:
            self.payload = bytes(4) + self.payload[4:]

    def command_interval(self) -> float:
        # an offline unit is only probed once per timeout, so it costs the bus little
        return self.period if self.online is not False else max(self.period, self.timeout)


def turns(groups: list[tuple[str, int]], per_turn: int) -> dict[str, int]:
    """Each group's turn: groups (name, units) in order fill a turn up to ``per_turn``
    units, then the next; a group larger than that has a turn of its own (a robot's
    units always leave together)."""
    out: dict[str, int] = {}
    turn, filled = 0, 0
    for name, size in groups:
        if filled and filled + size > per_turn:
            turn, filled = turn + 1, 0
        out[name] = turn
        filled += size
    return out


class BusScheduler:
    """Multiplexes every unit of one bus; see the module docstring."""

    def __init__(
        self,
        units: Iterable[UnitConfig],
        now: float,
        together: Mapping[str, str] | None = None,
        units_per_turn: int = UNITS_PER_TURN,
    ) -> None:
        """``together``: unit → the name of the units it sends with (its robot): they share
        one phase, so a robot's frames leave in the same turn. Groups share a turn up to
        ``units_per_turn`` units (the bus's setting); the turns are staggered."""
        cfgs = list(units)
        group_of = {c.name: (together or {}).get(c.name, c.name) for c in cfgs}
        sizes = Counter(group_of.values())  # in first-seen order: the file's
        turn_of = turns(list(sizes.items()), units_per_turn)
        n_turns = max(turn_of.values(), default=0) + 1
        # the turns' offsets divide the bus's shortest period: a unit's grid then keeps its
        # turn's offset modulo that period whatever its own rate (a multiple of it), and
        # never lands on another turn's (each unit's own period would put a slower
        # unit's turn on a faster one's grid)
        base = min((1.0 / c.command_rate_hz for c in cfgs), default=1.0)
        self.slots: dict[str, UnitSlot] = {}
        self._routes: dict[int, tuple[UnitSlot, int]] = {}  # id → (slot, -1 DP0 | packet)
        self._senders: dict[int, UnitSlot] = {}  # our request ids → slot
        # parameter access (TelABH3 over J1939 TP), one channel per unit; its frames go
        # after every DP0 command and status poll of the same step (docs/parameters.md)
        self.params: dict[str, ParamChannel] = {}
        self._tp_routes: dict[int, tuple[ParamChannel, bool]] = {}  # drive's id → (ch, is DT)
        self._params_active = False  # some channel has a request queued or open
        self._tp_senders: dict[int, ParamChannel] = {}
        # other hosts on the drives we command (core/foreign.py), from unrouted frames
        self.foreign = ForeignWatch({c.abh3_id: c.name for c in cfgs if c.role is Role.COMMAND})
        for cfg in cfgs:
            # stagger the turns so that no more than a turn's frames hit the bus at once
            slot = UnitSlot(cfg, now + turn_of[group_of[cfg.name]] * base / n_turns)
            self.slots[cfg.name] = slot
            self._senders[slot.command_id] = slot
            self._senders[slot.poll_id] = slot
            self._routes[without_priority(dp0_reply_id(cfg.abh3_id, cfg.host_id))] = (slot, -1)
            for n in range(8):
                self._routes[without_priority(broadcast_id(cfg.abh3_id, cfg.brd_group, n))] = (
                    slot,
                    n,
                )
            channel = ParamChannel(cfg.abh3_id, cfg.host_id, cfg.priority, cfg.telabh3)
            channel.on_work = self._params_work
            self.params[cfg.name] = channel
            for is_dt, ident in zip((False, True), channel.peer_ids, strict=True):
                self._tp_routes[without_priority(ident)] = (channel, is_dt)
            for ident in channel.ids:
                self._tp_senders[ident] = channel
        self._slots = list(self.slots.values())  # in order: commands go in this order
        # each unit's partners in its group (its robot's other units on this bus)
        self._partners = {
            name: [self.slots[o] for o, g in group_of.items() if g == group and o != name]
            for name, group in group_of.items()
        }
        self.events: list[Event] = []

    # ------------------------------------------------------------ inputs

    def set_payload(self, unit: str, payload: bytes) -> None:
        """The DP0 command this unit sends from its next exchange on (8 bytes)."""
        self.slots[unit].payload = payload

    def on_frame(self, arbitration_id: int, data: bytes, now: float) -> None:
        route = self._routes.get(arbitration_id & MATCH_MASK)  # inline: the hot path
        if route is None:
            tp = self._tp_routes.get(arbitration_id & MATCH_MASK)
            if tp is not None:
                if data:
                    tp[0].on_frame(tp[1], data, now)
            else:
                for host in self.foreign.frame(arbitration_id, data, now):
                    self.events.append(ForeignEvent(host.unit, now, host))
            return
        slot, packet = route
        cfg = slot.cfg
        if packet == 7:  # not defined by the spec: kept for whoever reads it, proves nothing
            self.events.append(StatusEvent(cfg.name, now, 7, frames.Brd7(data)))
            return
        if len(data) != VALID_LENGTH:
            self._malformed(slot, packet, now, f"{len(data)} data bytes, expected 8")
            return
        if packet < 0:
            # DP0 replies carry no sequence number: a reply answers the one request in flight
            sent_at, slot.dp0_sent_at = slot.dp0_sent_at, None
            if sent_at is not None:
                slot.stats.on_reply(now, now - sent_at)
                slot.heard_at = sent_at
                if slot.gap:
                    slot.gap = False
                    self.events.append(GapEvent(cfg.name, now, False))
            else:
                slot.stats.unsolicited += 1
                slot.stats.last_seen = now
                if slot.commanding and slot.unasked(now):
                    unasked = self.foreign.unasked_reply(
                        cfg.abh3_id, cfg.host_id, arbitration_id, data, now
                    )
                    if unasked is not None:
                        self.events.append(ForeignEvent(cfg.name, now, unasked))
            reply = frames.decode_dp0_reply(data, cfg.protocol)
            self.events.append(FeedbackEvent(cfg.name, now, reply, sent_at, data))
        else:
            asked_at = None
            if slot.poll_sent_at is not None and slot.poll_packet == packet:
                asked_at, slot.poll_sent_at = slot.poll_sent_at, None
            slot.stats.broadcasts += 1
            slot.stats.last_seen = now
            record = frames.decode_broadcast(packet, data, cfg.protocol)
            self.events.append(StatusEvent(cfg.name, now, packet, record, asked_at))
        if slot.online is not True:
            slot.online = True
            # back online: resume the normal rate (an offline unit was probed slowly)
            if slot.last_sent is not None:
                slot.next_command = min(slot.next_command, max(now, slot.last_sent + slot.period))
            self.events.append(HealthEvent(cfg.name, now, True))
        slot.refresh()

    def on_bad_frame(self, arbitration_id: int, now: float, reason: str) -> None:
        """A frame with one of our reply ids that is no data frame we can use (an FD or a
        remote frame): counted, never taken as a reply."""
        route = self._routes.get(arbitration_id & MATCH_MASK)
        if route is not None:
            self._malformed(route[0], route[1], now, reason)

    def _malformed(self, slot: UnitSlot, packet: int, now: float, reason: str) -> None:
        slot.stats.malformed += 1
        kind = "dp0 reply" if packet < 0 else f"broadcast {packet}"
        self.events.append(MalformedEvent(slot.cfg.name, now, kind, reason))

    def on_send_failed(self, arbitration_id: int) -> None:
        """The bus refused a frame we returned from :meth:`poll`: it is not in flight."""
        slot = self._senders.get(arbitration_id)
        if slot is None:
            channel = self._tp_senders.get(arbitration_id)
            if channel is not None:
                channel.on_send_failed()
            return
        slot.stats.send_errors += 1
        if arbitration_id == slot.command_id:
            slot.dp0_sent_at = None
        else:
            slot.poll_sent_at = None
        slot.refresh()

    # ------------------------------------------------------------ outputs

    def poll(self, now: float) -> list[OutFrame]:
        """Frames due at ``now`` as ``(arbitration_id, data)``: commands first."""
        out: list[OutFrame] = []
        slots = [slot for slot in self._slots if now >= slot.due]  # nothing due: untouched
        for slot in slots:
            self._check_health(slot, now)
            if now >= slot.command_at:
                if slot.dp0_sent_at is not None:
                    slot.stats.timeouts += 1  # the previous exchange got no reply in time
                    slot.orphan(now)
                out.append((slot.command_id, slot.payload))
                slot.dp0_sent_at = slot.last_sent = now
                slot.stats.commands_sent += 1
                slot.next_command = next_on_grid(slot.next_command, slot.command_interval(), now)
        for slot in slots:
            if now < slot.poll_at:
                continue
            if slot.asked:  # an on-demand request takes the turn, the polls keep their grid
                slot.poll_packet = slot.asked.pop(0)
            else:
                slot.poll_packet = slot.polls[slot.poll_index]
                slot.poll_index = (slot.poll_index + 1) % len(slot.polls)
                slot.next_poll = next_on_grid(slot.next_poll, slot.poll_period, now)
            out.append(slot.poll_frames[slot.poll_packet])
            slot.poll_sent_at = now
            slot.stats.polls_sent += 1
        for slot in slots:
            slot.refresh()
        if self._params_active:  # parameter traffic is rare: idle channels cost nothing
            active = False
            for channel in self.params.values():
                if channel.next_deadline() <= now:
                    out += channel.poll(now)
                active |= channel.busy
            self._params_active = active
        return out

    def _params_work(self) -> None:
        self._params_active = True

    def read_by(self, now: float) -> float:
        """When the pump must read what comes from ``now`` on (scheduler/pump.py,
        ``Turns``): by the next command or status poll on a unit's grid, as if every
        reply in flight had been read (:meth:`next_deadline` waits for them); ``now``
        (as it comes) while an online unit's reply is late past its turn (its command
        waits for it), or a parameter session is queued or open, each of the drive's
        frames bringing our next. A late status reply holds back no command, and a unit
        not heard (offline, or not yet) keeps to its deadlines: neither is urgent."""
        if self._params_active:
            return now
        turn = math.inf
        for slot in self._slots:
            if slot.next_command > now:
                turn = min(turn, slot.next_command)
            elif slot.dp0_sent_at is not None and slot.online:
                return now
            if slot.polls and now < slot.next_poll < turn:
                turn = slot.next_poll
        return turn

    def request_status(self, unit: str, packet: int) -> None:
        """Ask for broadcast ``packet`` once, at the next free poll turn (seed ``brd_num``).

        A packet already waiting is not queued twice: a flood of requests costs one frame.
        """
        if not 0 <= packet <= 7:
            raise ValueError(f"broadcast packet {packet} is not 0-7")
        slot = self.slots[unit]
        if packet not in slot.asked:
            slot.asked.append(packet)
            slot.refresh()

    def send_now(self, unit: str, now: float) -> OutFrame:
        """The unit's DP0 frame, due now regardless of schedule (stop frames); in flight
        from now, so its reply confirms it."""
        slot = self.slots[unit]
        slot.orphan(now)  # the exchange in flight, if any, is replaced unanswered
        slot.dp0_sent_at = slot.last_sent = now
        slot.stats.commands_sent += 1
        slot.next_command = now + slot.command_interval()
        # the robot keeps one turn: a partner's next frame within this period is the grid
        # point this one joins (a robot's frames sent at once, one after the other, would
        # otherwise part its turn by the microseconds between them, for good)
        for other in self._partners[unit]:
            if other.period == slot.period and now < other.next_command < slot.next_command:
                slot.next_command = other.next_command
                break
        slot.refresh()
        return slot.command_id, slot.payload

    def _check_health(self, slot: UnitSlot, now: float) -> None:
        if now >= slot.gap_at:  # as in next_deadline (UnitSlot.deadlines)
            slot.gap = True
            slot.stats.gaps += 1
            slot.zero_command()
            self.events.append(GapEvent(slot.cfg.name, now, True))
        if now >= slot.offline_at:  # as in next_deadline
            slot.online = False
            slot.zero_command()
            self.events.append(HealthEvent(slot.cfg.name, now, False))

    def next_deadline(self) -> float:
        deadline = math.inf
        for slot in self._slots:
            if slot.due < deadline:
                deadline = slot.due
        if self._params_active:
            for channel in self.params.values():
                deadline = min(deadline, channel.next_deadline())
        return deadline

    def drain_events(self) -> list[Event]:
        events, self.events = self.events, []
        return events
