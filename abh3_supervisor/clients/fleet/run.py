"""``abh3 fleet``: its options and its start — connect (or say why not, exit 1), then the
view until the user quits (exit 0)."""

from __future__ import annotations

import argparse
import asyncio
import getpass
import socket
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from abh3_supervisor.clients.fleet.broker import (
    BrokerOptions,
    FleetClient,
    check_files,
    default_client_id,
    parse_url,
    read_password,
)
from abh3_supervisor.clients.fleet.model import STALE_S
from abh3_supervisor.errors import Abh3Error, RunError
from abh3_supervisor.fleet import PREFIX

if TYPE_CHECKING:
    from abh3_supervisor.clients.fleet.app import FleetApp


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    from abh3_supervisor.clients.argtypes import positive

    p = sub.add_parser(
        "fleet",
        help="every robot on the plant's MQTT broker, with the fleet e-stop (the mqtt extra)",
        description="A view of every robot and unit the broker knows under the prefix "
        "(published by the supervisors' mqtt plugin): online/offline/connection broken, "
        "errors and alarms by name, speeds, owner, age (greyed when stale). Keys: e e-stop "
        "the selected robot, E e-stop all, c / C clear (asked), a attach its TUI over SSH. "
        "docs/fleet.md (The fleet view).",
    )
    p.add_argument(
        "--broker", required=True, metavar="URL", help="mqtt://host:1883 or mqtts://host:8883"
    )
    p.add_argument("--username", help="the broker user (its ACL decides what may be sent)")
    secret = p.add_mutually_exclusive_group()
    secret.add_argument("--password-env", metavar="VAR", help="the password is in $VAR")
    secret.add_argument(
        "--password-file", type=Path, metavar="F", help="the password is F's first line"
    )
    p.add_argument("--ca", type=Path, metavar="F", help="the CA that signed the broker (mqtts)")
    p.add_argument("--cert", type=Path, metavar="F", help="a client certificate (mqtts)")
    p.add_argument("--key", type=Path, metavar="F", help="its private key")
    p.add_argument("--prefix", default=PREFIX, help=f"topic prefix (default {PREFIX})")
    p.add_argument(
        "--protocol", choices=["5", "3.1.1"], default="5", help="MQTT version (default 5)"
    )
    p.add_argument(
        "--stale-s",
        type=positive,
        default=STALE_S,
        metavar="S",
        help=f"a unit not heard from for S seconds is greyed (default {STALE_S}: 4 periods "
        "of the default 2 Hz)",
    )
    p.add_argument(
        "--client-id",
        help="the MQTT client id, the commands' sender (default: abh3-fleet-USER-HOST-PID)",
    )


def options(args: argparse.Namespace) -> BrokerOptions:
    """The broker options of the command line; a mistake in them is exit 2."""
    tls, host, port = parse_url(args.broker)
    if not tls and (args.ca or args.cert or args.key):
        raise Abh3Error("--ca, --cert and --key need an mqtts:// broker")
    opts = BrokerOptions(
        host=host,
        port=port,
        tls=tls,
        protocol=args.protocol,
        username=args.username,
        password=read_password(args.password_env, args.password_file),
        ca=args.ca,
        cert=args.cert,
        key=args.key,
        client_id=args.client_id or default_client_id(),
    )
    check_files(opts)
    if opts.password is not None and opts.username is None:
        raise Abh3Error("a password needs --username")
    if any(c in args.prefix for c in "+#") or not args.prefix.strip("/"):
        raise Abh3Error(f"--prefix {args.prefix!r}: topic levels without wildcards (+, #)")
    return opts


def run(
    args: argparse.Namespace, opts: BrokerOptions, not_terminals: Callable[[], list[str]]
) -> int:
    """Connect (the broker's trouble said first: it is what a user came to find out), then
    the view on this terminal."""
    from abh3_supervisor.clients.fleet.app import FleetApp
    from abh3_supervisor.clients.fleet.commands import Commander
    from abh3_supervisor.clients.fleet.model import FleetModel

    prefix = args.prefix.rstrip("/")
    client = FleetClient(opts, prefix)
    client.connect()  # RunError (exit 1) when it cannot, said
    try:
        if redirected := not_terminals():
            raise RunError(f"{'/'.join(redirected)} not a terminal: abh3 fleet needs one")
        reason = f"abh3 fleet by {getpass.getuser()}@{socket.gethostname()}"
        app = FleetApp(
            FleetModel(prefix, args.stale_s),
            Commander(opts.client_id, prefix, v5=opts.v5),
            client,
            reason,
        )
        return asyncio.run(_view(app))
    finally:
        client.close()


async def _view(app: FleetApp) -> int:
    """The app until the user quits, or a signal or the terminal going away ends it (it
    holds nothing: leaving is always safe; the TUI's Departure bounds how long it takes)."""
    from abh3_supervisor.clients.tui.run import DETACH_S, Departure

    loop = asyncio.get_running_loop()
    with Departure(DETACH_S, forced_code=0) as leaving:
        leaving.on_leave(lambda: loop.call_soon_threadsafe(app.exit))
        if leaving.why is None:
            await app.run_async()
    return app.return_code or 0
