"""``abh3 enable`` and ``abh3 disable``: a running supervisor's robots switched on or off
(SERVO and START of every wheel axis of their drives, as one act)."""

from __future__ import annotations

import argparse
from collections.abc import Callable

from abh3_supervisor.clients.cli import connecting


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    for verb, what in (("enable", "on"), ("disable", "off")):
        robot_switch = sub.add_parser(
            verb,
            help=f"switch a running supervisor's robot {what}: SERVO and START of every wheel "
            "axis of its drives, as one act",
            description="Switch SERVO and START of every wheel axis of every drive of each "
            f"ROBOT (or of the robot of a unit named) {what}, as one act: refused whole, naming "
            "the drive, when one cannot take it."
            + (
                " Exit 0 once every drive reports it on; 1 naming the drive that did not "
                "follow within 0.5 s."
                if verb == "enable"
                else " Axes that drive no wheel are never switched on."
            ),
        )
        robot_switch.add_argument("robots", nargs="+", metavar="ROBOT")
        connecting(robot_switch)
        robot_switch.set_defaults(func=handle)


def handle(args: argparse.Namespace, release: Callable[[], None]) -> int:
    from abh3_supervisor.clients import control

    path = control.find_socket(args.connect)
    return control.enable(path, args.robots, on=args.cmd == "enable")
