"""Mistakes pluggy accepts silently, refused while a plugin loads (``check`` and ``run``).

pluggy registers a method named like no hook as a hook of its own that is never called,
skips a hook method that lacks ``@hookimpl`` without a word, and a plugin that implements
no ``abh3_configure`` never sees its settings: each of these is a plugin that quietly does
nothing. Each is reported as a configuration problem at the plugin's section (FILE:LINE),
naming where in the plugin's code the method is.
"""

from __future__ import annotations

import inspect
from typing import Any

import pluggy

from abh3_supervisor.config.source import Source
from abh3_supervisor.errors import did_you_mean
from abh3_supervisor.plugin_host import tick

PREFIX = "abh3_"
# the host's keys, valid in every plugin section, with or without abh3_configure
HOST_KEYS = ("on_error", "critical", "start_timeout_s", tick.KEY)
DEFS = ("def ", "async def ")


def hook_names(pm: pluggy.PluginManager) -> list[str]:
    """The hooks ``pm`` has specs for."""
    return sorted(n for n, c in vars(pm.hook).items() if getattr(c, "spec", None) is not None)


def validate_plugin(
    src: Source, name: str, plugin: object, settings: Any, pm: pluggy.PluginManager
) -> None:
    """Report (``src.error``) each silently ignored hook method and settings nobody reads."""
    where = ("plugins", name)
    for problem in method_problems(name, plugin, pm):
        src.error(where, problem)
    if isinstance(settings, dict) and not _implements(pm, name, "abh3_configure"):
        for key in settings:
            if key not in HOST_KEYS:
                src.error(
                    (*where, str(key)),
                    f"plugin '{name}' takes no settings (it implements no abh3_configure)",
                )


def method_problems(name: str, plugin: object, pm: pluggy.PluginManager) -> list[str]:
    """The plugin's methods that pluggy would never call: a name that is no hook (with
    the closest hook), a hook method without ``@hookimpl``."""
    hooks = hook_names(pm)
    problems = []
    for attr, func in _methods(plugin):
        opts = pm.parse_hookimpl_opts(plugin, attr)
        hook = (opts.get("specname") if opts is not None else None) or attr
        if hook in hooks:
            if opts is None:
                problems.append(
                    f"plugin '{name}': {attr}{_at(func)} has no @hookimpl, so it is never "
                    "called (from abh3_supervisor.plugin_api import hookimpl)"
                )
            continue
        if opts is None and not attr.startswith(PREFIX):
            continue  # an ordinary method of the plugin's own
        hint = did_you_mean(hook, hooks)
        problems.append(f"plugin '{name}': {attr}{_at(func)} matches no hook{hint}")
    return problems


def _methods(plugin: object) -> list[tuple[str, Any]]:
    """The plugin's public callables that look like hooks: named abh3_*, or marked."""
    found = []
    for attr in dir(plugin):
        if attr.startswith("_"):
            continue
        try:
            value = inspect.getattr_static(plugin, attr)
        except AttributeError:
            continue
        if isinstance(value, staticmethod | classmethod):
            value = value.__func__
        if inspect.isfunction(value) or inspect.ismethod(value):
            found.append((attr, value))
    return found


def _implements(pm: pluggy.PluginManager, name: str, hook: str) -> bool:
    caller = getattr(pm.hook, hook, None)
    return caller is not None and any(i.plugin_name == name for i in caller.get_hookimpls())


def _at(func: Any) -> str:
    """`` (file.py:LINE)``: where the method is defined, when Python can say."""
    try:
        file = inspect.getsourcefile(func)
        lines, line = inspect.getsourcelines(func)
    except (OSError, TypeError):
        return ""
    # the `def` line, not its decorator's
    line += next((i for i, t in enumerate(lines) if t.lstrip().startswith(DEFS)), 0)
    return f" ({file}:{line})" if file else ""
