"""The fleet's e-stop and clear: the payloads sent, and what became of each, said only as
far as it was seen.

Witnesses, weakest first: the broker took it (MQTT 5: PUBACK reason code under 0x80;
under 3.1.1 a refusal is silent, so it stays "sent, not confirmed"); the broker refused
it (MQTT 5 reason code, e.g. "Not authorized": the ACL); the robot's own word — its
``fleet_command`` event naming this sender and seq (obeyed) or its
``fleet_command_refused`` event, and every unit of it publishing, live, the e-stop
latched (or cleared) after we sent it. Pure: the view feeds it acknowledgements and the model.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from abh3_supervisor.clients.fleet.model import FleetModel
from abh3_supervisor.fleet import ALL, PREFIX, Topics, payloads

REFUSED_KIND = "fleet_command_refused"
OBEYED_KIND, OBEYED = "fleet_command", "obeyed"  # the robot's event: it obeyed this one
NO_SUBSCRIBERS = 0x10  # MQTT 5: taken, but nobody subscribes to the topic
SENDING, TAKEN, UNCONFIRMED = "sending", "taken by the broker", "sent, not confirmed"


@dataclass
class Sent:
    """One command sent: to one robot (``target``) or all (None), and its outcome."""

    clear: bool
    target: str | None
    seq: int
    time: float  # our clock, as in its payload
    topic: str
    payload: bytes
    robots: tuple[str, ...]  # those shown when it was sent: whose word is awaited
    broker: str = SENDING
    refused: str | None = None  # the broker's reason code, when it refused
    robot_said: dict[str, str] = field(default_factory=dict)  # fleet_id: confirmed/refused …

    @property
    def done(self) -> str:
        """What the robot shows once it holds: the latch, not proof it was our command
        that set it (it may have been latched already)."""
        return "cleared" if self.clear else "latched"

    @property
    def what(self) -> str:
        verb = "clear" if self.clear else "e-stop"
        return f"{verb} {self.target or 'all'} (seq {self.seq})"

    def summary(self) -> str:
        """One line: what is known of it, and no more."""
        if self.refused is not None:
            return f"{self.what}: REFUSED by the broker: {self.refused}"
        held = [f for f, said in self.robot_said.items() if said == self.done]
        obeyed = [f for f, said in self.robot_said.items() if said == OBEYED]
        refused = {f: s for f, s in self.robot_said.items() if s not in (self.done, OBEYED)}
        if self.robots and len(held) + len(obeyed) == len(self.robots):
            parts = [f"{self.done} on {_count(held)}"] if held else []
            parts += [f"obeyed by {_count(obeyed)} (not yet seen {self.done})"] if obeyed else []
            return f"{self.what}: " + "; ".join(parts)
        parts = [self.broker]
        total = len(self.robots)
        parts += [f"{self.done} on {len(held)} of {total}"] if held else []
        parts += [f"obeyed by {len(obeyed)} of {total}"] if obeyed else []
        parts += [f"{f} refused: {s}" for f, s in refused.items()]
        waiting = [f for f in self.robots if f not in self.robot_said]
        if waiting and not self.robot_said and self.broker != SENDING:
            parts.append(f"no word yet from {_count(waiting)}")
        return f"{self.what}: " + "; ".join(parts)


def _count(fleet_ids: list[str]) -> str:
    return fleet_ids[0] if len(fleet_ids) == 1 else f"{len(fleet_ids)} robots"


class Commander:
    """Builds commands with one ``sender`` and a rising ``seq``, and follows them."""

    def __init__(self, sender: str, prefix: str = PREFIX, *, v5: bool = True) -> None:
        self.sender, self.prefix, self.v5 = sender, prefix, v5
        self.seq = 0
        self.sent: list[Sent] = []

    def build(
        self, model: FleetModel, target: str | None, *, clear: bool, reason: str, now: float
    ) -> Sent:
        """The command for ``target`` (a fleet_id, or None: every robot)."""
        self.seq += 1
        robots = (target,) if target else tuple(sorted(model.robots))
        sent = Sent(
            clear=clear,
            target=target,
            seq=self.seq,
            time=now,
            topic=Topics(target or ALL, self.prefix).command(
                "estop_clear" if clear else "estop", everyone=target is None
            ),
            payload=payloads.encode(
                payloads.estop_command(self.seq, now, sender=self.sender, reason=reason)
            ),
            robots=robots,
        )
        self.sent.append(sent)
        return sent

    def acknowledged(self, sent: Sent, code: int, name: str) -> None:
        """The broker's PUBACK: MQTT 5 reason ``code`` (and its ``name``); under 3.1.1 it
        is always 0, as taking and silently dropping look alike there."""
        if code >= 0x80:
            sent.refused = f"{name} (0x{code:02X})"
        elif code == NO_SUBSCRIBERS:
            sent.broker = "taken by the broker, but no robot subscribes (allow_estop off?)"
        else:
            sent.broker = TAKEN if self.v5 else UNCONFIRMED

    def observe(self, model: FleetModel) -> None:
        """What the robots have said since each command was sent. A robot's refusal is
        its last word, even after its units showed the state asked for: a robot never
        latched shows "cleared" whether it obeyed a clear or refused it."""
        for sent in self.sent[-10:]:  # the recent ones are still being watched
            for fid in sent.robots:
                robot = model.robots.get(fid)
                if robot is None or sent.robot_said.get(fid) not in (None, OBEYED, sent.done):
                    continue  # unseen, or refused
                for event in robot.events:
                    if event.received < sent.time:
                        continue
                    if event.kind == REFUSED_KIND and _ours(event.data, self.sender, sent):
                        reason = event.data.get("reason")
                        sent.robot_said[fid] = reason if isinstance(reason, str) else event.text
                        break
                    if event.kind == OBEYED_KIND and _obeyed(event.data, self.sender, sent):
                        sent.robot_said.setdefault(fid, OBEYED)
                if sent.robot_said.get(fid) not in (None, OBEYED):
                    continue
                units = [robot.units[n] for n in model.unit_names(robot) if n in robot.units]
                if (
                    units
                    and len(units) == len(model.unit_names(robot))
                    and all(
                        not u.retained and u.received >= sent.time and u.estop != sent.clear
                        for u in units
                    )
                ):
                    sent.robot_said[fid] = sent.done

    def latest(self) -> Sent | None:
        return self.sent[-1] if self.sent else None


def _ours(data: dict[str, object], sender: str, sent: Sent) -> bool:
    """The plugin's refusal names the topic and, under MQTT 5, the sender (our user
    property); it has no ``seq``. Under 3.1.1 its ``sender`` is null: a refusal on this
    command's topic after it was sent is taken as this one's. A count of refusals beyond
    the robot's event rate (``refused_unsaid`` alone) names no command."""
    if data.get("topic") != sent.topic:
        return False
    said = data.get("sender")
    return said is None or said == sender


def _obeyed(data: dict[str, object], sender: str, sent: Sent) -> bool:
    """An obeyed event says whose command and which: only an exact match counts."""
    kind = "estop_clear" if sent.clear else "estop"
    return data.get("sender") == sender and data.get("seq") == sent.seq and data.get("kind") == kind
