"""``abh3 check CONFIG --drives``: read every drive's CAN settings on the configuration's
own buses and compare them with the file (core/verify.py), nothing else; ``abh3 verify
UNIT…``: the same asked of a running supervisor, which acts on it (``verify: refuse``).

The buses open as ``abh3 param -c`` opens them: every unit a monitor without start-up
commands, so nothing is commanded and a supervisor driving the same units is not fought.
Exit: 0 every drive agrees, 1 a mismatch, a drive not verified or a bus that cannot open,
2 a mistake in the file.
"""

from __future__ import annotations

import asyncio
import json
import sys
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from abh3_supervisor.clients.ssh import Endpoint
    from abh3_supervisor.config import Config
    from abh3_supervisor.core.verify import Verification

HEADER = ("unit", "address", "name", "drive", "YAML", "verdict")


def check_drives(config: Config, as_json: bool) -> int:
    from abh3_supervisor.clients.param import monitor_only

    results = {n: v.to_json() for n, v in asyncio.run(_read(monitor_only(config))).items()}
    where = {n: f"{n} (bus {u.bus}, drive {u.abh3_id})" for n, u in config.units.items()}
    code = _report(results, where, as_json)
    if elsewhere := _simulated_elsewhere_unheard(config, results):
        print(
            f"{', '.join(elsewhere)}: no drive answered, and the file's drives there are "
            f"simulated in another process: is `abh3 simulate {config.file}` running?",
            file=sys.stderr,
        )
    return code


def _simulated_elsewhere_unheard(config: Config, results: dict[str, dict[str, Any]]) -> list[str]:
    """The units none of whose values was read, on a bus whose drives `abh3 simulate`
    runs (docs/simulator.md)."""
    return [
        name
        for name, v in results.items()
        if not any(r["drive"] for r in v["rows"])
        and (sim := config.buses[config.units[name].bus].simulate) is not None
        and sim.external
    ]


def verify_running(path: Endpoint, units: list[str], as_json: bool) -> int:
    """``abh3 verify UNIT…``: a running supervisor compares those drives with its file
    again (a unit ``verify: refuse`` holds is released when they now agree)."""
    from abh3_supervisor.clients.control import ControlClient

    client = ControlClient(path, timeout=10.0)
    try:
        known = client.units(units)
        results = {unit: client.call("verify", unit=unit) for unit in units}
    finally:
        client.close()
    where = {n: f"{n} (bus {known[n]['bus']}, drive {known[n]['abh3_id']})" for n in units}
    return _report(results, where, as_json)


def _report(results: dict[str, dict[str, Any]], where: dict[str, str], as_json: bool) -> int:
    if as_json:
        print(json.dumps(results, indent=2))
    else:
        for line in table(results, where):
            print(line)
    return 0 if all(v["state"] == "ok" for v in results.values()) else 1


async def _read(config: Config) -> dict[str, Verification]:
    from abh3_supervisor.core.verifying import verify_units
    from abh3_supervisor.runtime.bus_runtime import Runtime
    from abh3_supervisor.runtime.listening import refuse_if_commanded

    # its parameter sessions would be another host's to a supervisor commanding these
    # drives, which would stop its robot: refused before anything is sent (exit 2)
    await refuse_if_commanded(config, list(config.units), "abh3 check --drives")
    async with Runtime(config) as rt:
        return await verify_units(rt.supervisor, list(config.units), act=False)


def table(results: dict[str, dict[str, Any]], where: dict[str, str]) -> list[str]:
    """The rows of every unit (as ``Verification.to_json`` gives them), then one verdict
    line per unit (with its TelABH3 form)."""
    rows = [HEADER]
    for name, v in results.items():
        rows += [
            (
                name,
                f"0x{r['address']:04X}",
                r["name"],
                r["drive"] or "–",
                r["yaml"] or "–",
                r["verdict"],
            )
            for r in v["rows"]
        ]
    widths = [max(len(row[i]) for row in rows) for i in range(len(HEADER))]
    out = ["  ".join(c.ljust(w) for c, w in zip(row, widths, strict=True)).rstrip() for row in rows]
    for name, v in results.items():
        verdict = {
            "ok": "agrees with the file",
            "mismatch": f"{len(v['mismatches'])} setting(s) differ from the file",
        }.get(v["state"], f"{v['state']}: {v['reason']}")
        out.append(f"{where[name]}: {verdict}")
        if v["held"]:
            out.append(f"{where[name]}: HELD: {v['held']}")
        if v["form"] is not None:
            out.append(f"{where[name]}: TelABH3 form {v['form']}")
    return out
