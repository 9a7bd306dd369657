"""``abh3 plugins [CONFIG]``: the installed plugins, what each implements, which run.

Each plugin is imported to learn its hooks (nothing of it is called); one that cannot be
imported is listed with the reason in one line, and the others still are.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from abh3_supervisor.plugin_api import API_VERSION
from abh3_supervisor.plugin_host.host import installed
from abh3_supervisor.plugin_host.inventory import PluginInfo, compatible, describe


def api_version() -> str:
    """This supervisor's plugin API version (``abh3_supervisor.plugin_api.API_VERSION``)."""
    return API_VERSION


def listing(config: Path | None) -> dict[str, Any]:
    """Everything ``abh3 plugins`` says, as the JSON it prints with ``--json``."""
    enabled: set[str] | None = None
    if config is not None:
        from abh3_supervisor.config import load_config

        enabled = set(load_config(config).plugins)
    current = api_version()
    available = installed()
    rows = [_row(describe(name, ep), current, enabled) for name, ep in sorted(available.items())]
    for name in sorted((enabled or set()) - set(available)):
        rows.append(
            {"name": name, "error": "not installed", "enabled": True, "hooks": [], "problems": []}
        )
    return {
        "api_version": current,
        "config": None if config is None else str(config),
        "plugins": rows,
    }


def _row(info: PluginInfo, current: str | None, enabled: set[str] | None) -> dict[str, Any]:
    return {
        "name": info.name,
        "entry_point": info.target,
        "distribution": info.distribution,
        "version": info.version,
        "api_version": info.api_version,
        "compatible": compatible(info.api_version, current),
        "hooks": info.hooks,
        "enabled": None if enabled is None else info.name in enabled,
        "error": info.error,
        "problems": info.problems,
    }


def plugins_command(config: Path | None, as_json: bool) -> int:
    data = listing(config)
    if as_json:
        print(json.dumps(data, indent=2))
        return 0
    current = data["api_version"] or "unknown"
    print(f"plugin API {current}; {len(data['plugins'])} plugin(s)")
    for row in data["plugins"]:
        print("".join(_text(row, current, config is not None)))
    return 0


def _text(row: dict[str, Any], current: str, with_config: bool) -> list[str]:
    out = [row["name"]]
    if row.get("distribution"):
        out.append(f"  {row['distribution']} {row['version']}")
    if with_config:
        out.append("  enabled" if row["enabled"] else "  not enabled")
    if row.get("error"):
        if row.get("entry_point"):
            out.append(f"\n  failed to load: {row['error']}")
        else:
            out.append("\n  not installed (named in the configuration)")
        return out
    declared = row["api_version"]
    if declared is None:
        out.append("\n  API version: not declared")
    else:
        verdict = {True: "compatible", False: "NOT compatible", None: "unknown"}
        out.append(f"\n  API version: {declared} ({verdict[row['compatible']]} with {current})")
    out.append(f"\n  hooks: {', '.join(row['hooks']) or 'none'}")
    out += [f"\n  problem: {problem}" for problem in row["problems"]]
    return out
