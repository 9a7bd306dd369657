"""``abh3 ros2 build-interface``: ROS 2 helpers (clients/ros2_interface.py)."""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path

from abh3_supervisor.errors import RunError


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    ros2 = sub.add_parser("ros2", help="ROS 2 helpers")
    ros2.set_defaults(func=handle)
    helpers = ros2.add_subparsers(dest="ros2", required=True, metavar="COMMAND")
    build = helpers.add_parser(
        "build-interface",
        help="build abh3_can_interface (and, from the wheels, tf2_msgs) with cmake (no colcon) "
        "from a sourced ROS 2 or the wheels",
    )
    build.add_argument("--prefix", type=Path, required=True, help="install it here")
    build.add_argument(
        "--distro",
        choices=["kilted", "jazzy"],
        help="use this distro's wheels from the package registry (default: a sourced "
        "ROS 2 if there is one, else kilted)",
    )


def handle(args: argparse.Namespace, release: Callable[[], None]) -> int:
    from abh3_supervisor.clients import ros2_interface

    try:
        return ros2_interface.command(args.prefix, args.distro)
    except ros2_interface.BuildError as exc:
        raise RunError(str(exc)) from None
