"""What is installed: each plugin's distribution, version, declared API version and hooks.

For ``abh3 plugins`` and the run's first log line. Describing a plugin imports it (its
hooks are only known then); one that fails to import is described by its error.
"""

from __future__ import annotations

import inspect
import sys
from dataclasses import dataclass, field
from importlib.metadata import EntryPoint

import pluggy

from abh3_supervisor.plugin_host import hookspecs, validate

DECLARED = "ABH3_API_VERSION"  # on the plugin object, or in its module


@dataclass
class PluginInfo:
    name: str
    target: str  # the entry point's "module:object"
    distribution: str | None = None
    version: str | None = None
    api_version: str | None = None  # the API it says it was written for
    hooks: list[str] = field(default_factory=list)
    error: str | None = None  # why it could not be loaded
    problems: list[str] = field(default_factory=list)  # methods pluggy would never call


def distribution(ep: EntryPoint) -> tuple[str | None, str | None]:
    """The name and version of the distribution that installed ``ep``."""
    dist = getattr(ep, "dist", None)
    if dist is None:
        return None, None
    return dist.metadata["Name"], dist.version


def describe(name: str, ep: EntryPoint) -> PluginInfo:
    """Import the plugin and register it alone; nothing of it is called."""
    info = PluginInfo(name, ep.value, *distribution(ep))
    pm = pluggy.PluginManager(hookspecs.PROJECT)
    pm.add_hookspecs(hookspecs)
    try:
        target = ep.load()
        plugin = target() if isinstance(target, type) else target
        pm.register(plugin, name=name)
    except Exception as exc:  # its own fault: said in one line, the others still listed
        info.error = f"{type(exc).__name__}: {exc}"
        return info
    info.api_version = declared_api(plugin)
    known = validate.hook_names(pm)
    info.hooks = sorted(c.name for c in pm.get_hookcallers(plugin) or () if c.name in known)
    info.problems = validate.method_problems(name, plugin, pm)
    return info


def declared_api(plugin: object) -> str | None:
    """``ABH3_API_VERSION`` on the plugin object, else in the module that defines it."""
    value = getattr(plugin, DECLARED, None)
    if value is None and not inspect.ismodule(plugin):
        module = sys.modules.get(getattr(plugin, "__module__", "") or "")
        value = getattr(module, DECLARED, None)
    return None if value is None else str(value)


def compatible(declared: str | None, current: str | None) -> bool | None:
    """Same major version (the compatibility policy, docs/plugins.md); None: unknown."""
    if declared is None or current is None:
        return None
    return declared.split(".")[0] == current.split(".")[0]


def loaded_line(names: list[str], available: dict[str, EntryPoint]) -> str:
    """The run's log line: which plugins run, each with its distribution's version."""
    shown = []
    for name in names:
        ep = available.get(name)
        dist, version = distribution(ep) if ep is not None else (None, None)
        shown.append(f"{name} ({dist} {version})" if dist else f"{name} (registered in-process)")
    return "plugins loaded: " + (", ".join(shown) or "none")
