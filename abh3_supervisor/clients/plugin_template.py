"""``abh3 plugin new NAME``: a pip-installable plugin package that passes its own test.

The package holds a module with an example output hook (and, commented out, an input
source and an e-stop), its pyproject.toml with the entry point, a README and a test that
runs it on the simulator with :mod:`abh3_supervisor.plugin_testing`. It imports only
``abh3_supervisor.plugin_api`` and the harness.
"""

from __future__ import annotations

import re
from pathlib import Path

from abh3_supervisor.errors import Abh3Error

NAME = re.compile(r"[a-z][a-z0-9_]{0,39}")
DEFAULT_API = "1.0"  # the plugin API a template targets when it cannot ask (not installed)


def new_plugin(name: str, directory: Path) -> Path:
    """Write the package for plugin ``name`` into ``directory``; its folder."""
    if not NAME.fullmatch(name):
        fixed = re.sub(r"[^a-z0-9_]", "_", name.lower())
        did = f"; did you mean '{fixed}'?" if NAME.fullmatch(fixed) else ""
        raise Abh3Error(
            f"'{name}' cannot name a plugin: lowercase letters, digits and _, starting with a "
            f"letter, at most 40 (it is the key under plugins: in the YAML){did}"
        )
    module = name if name.startswith("abh3_") else f"abh3_{name}"
    package = directory / module.replace("_", "-")
    if package.exists():
        raise Abh3Error(f"{package} exists already: choose another --dir or name")
    from abh3_supervisor.clients.plugins import api_version

    fields = {
        "name": name,
        "module": module,
        "dist": package.name,
        "cls": "".join(p.capitalize() for p in name.split("_") if p) + "Plugin",
        "api": api_version() or DEFAULT_API,
    }
    files = {
        "pyproject.toml": PYPROJECT,
        f"{module}.py": MODULE,
        "README.md": README,
        f"tests/test_{module}.py": TEST,
    }
    try:
        for relative, text in files.items():
            path = package / relative
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(text.format(**fields), encoding="utf-8")
    except OSError as exc:
        raise Abh3Error(f"cannot write {package}: {exc.strerror or exc}") from exc
    return package


PYPROJECT = """\
[build-system]
requires = ["setuptools>=68"]
build-backend = "setuptools.build_meta"

[project]
name = "{dist}"
version = "0.1.0"
description = "An abh3-supervisor plugin"
requires-python = ">=3.11"
dependencies = ["abh3-supervisor"]

[project.optional-dependencies]
test = ["pytest>=8"]

# This is what makes it a plugin: `plugins: {{{name}: ...}}` in the YAML loads this object
[project.entry-points.abh3_supervisor]
{name} = "{module}:{cls}"

[tool.setuptools]
py-modules = ["{module}"]

[tool.pytest.ini_options]
testpaths = ["tests"]
"""

MODULE = '''\
"""{name}: an abh3-supervisor plugin (written by `abh3 plugin new`).

An output: it counts each unit's velocity feedback and keeps its fastest speed, and logs
both when the run ends. Below it, commented out: an input source (commands from a thread
of its own) and a safety watchdog that latches the e-stop. docs/plugins.md has the API.
"""

from __future__ import annotations

import logging
import threading

from abh3_supervisor.plugin_api import Feedback, Setpoint, hookimpl

# the plugin API this was written against: `abh3 plugins` says whether it still fits
ABH3_API_VERSION = "{api}"

log = logging.getLogger(__name__)


class {cls}:
    """The object the entry point names (pyproject.toml); one per run."""

    def __init__(self) -> None:
        self.samples: dict[str, int] = {{}}
        self.fastest: dict[str, float] = {{}}
        self._lock = threading.Lock()  # hooks run on this plugin's own thread

    @hookimpl
    def abh3_feedback(self, unit: str, feedback: Feedback, setpoint: Setpoint) -> None:
        """After every reply of a drive (about 50 a second per unit): keep it short."""
        with self._lock:
            self.samples[unit] = self.samples.get(unit, 0) + 1
            speed = max(abs(feedback.vel_a), abs(feedback.vel_b))
            self.fastest[unit] = max(self.fastest.get(unit, 0.0), speed)

    @hookimpl
    def abh3_stop(self) -> None:
        """Every way out, after the drives were stopped: flush and close what you opened."""
        with self._lock:
            for unit, count in sorted(self.samples.items()):
                fastest = self.fastest[unit]
                log.info("%s: %d replies, fastest %.1f min-1", unit, count, fastest)

    # An input source: add it from this hook (it needs `from abh3_supervisor.plugin_api
    # import InputSource`, and the class below).
    #
    # @hookimpl
    # def abh3_input_sources(self, register) -> None:
    #     register(Waypoints(units=("left",)))


# class Waypoints(InputSource):
#     """Plays speeds on its units, then lets go. Commands lapse to zero after `timeout`
#     seconds without a new one: a stuck source stops its units."""
#
#     def __init__(self, units: tuple[str, ...]) -> None:
#         super().__init__("{name}", units, timeout=0.5)
#         self.done = threading.Event()
#
#     def start(self, feed) -> None:  # return at once: the work is on a thread of its own
#         def play() -> None:
#             for speed in (100.0, 200.0, 0.0):  # A/B velocities [min-1], 1 s each
#                 for _ in range(10):
#                     if self.done.is_set():
#                         return
#                     feed.velocity(speed, 0.0)
#                     # a safety watchdog calls this instead, from any thread: every
#                     # unit gets zero and START off, latched until an operator clears it
#                     #     feed.emergency_stop()
#                     self.done.wait(0.1)
#             feed.release()  # its units stop now
#
#         threading.Thread(target=play, name="{name} waypoints", daemon=True).start()
#
#     def stop(self) -> None:  # every way out, after the drives were stopped
#         self.done.set()
'''

TEST = '''\
"""{name} on the simulator: the run as `abh3 run` makes it, for a second."""

from __future__ import annotations

from abh3_supervisor.plugin_testing import run_with_plugin

from {module} import {cls}

# any configuration runs: the harness puts every bus on the built-in simulator
CONFIG = """
buses:
  b: {{interface: socketcan, channel: can0}}
units:
  - {{name: left, abh3_id: 1}}
  - {{name: right, abh3_id: 3}}
"""


def test_it_hears_every_unit_and_the_run_ends_cleanly() -> None:
    plugin = {cls}()
    run = run_with_plugin(CONFIG, plugin, "{name}", seconds=1.0)
    assert run.exit_code == 0, run.error or "\\n".join(run.log)
    heard = {{unit for unit, _, _ in run.feedback}}  # what the plugins received
    assert heard == {{"left", "right"}}
    assert plugin.samples.keys() == heard and min(plugin.samples.values()) >= 10
    assert max(plugin.fastest.values()) < 1.0  # nothing commanded motion
    assert any("right: " in line and "replies, fastest" in line for line in run.log)
    assert run.frames  # and what went on the wire, both ways
'''

README = """\
# {dist}

An [abh3-supervisor](https://pypi.org/project/abh3-supervisor/) plugin, written by
`abh3 plugin new {name}`. Enable it in a configuration:

```yaml
plugins:
  {name}: {{}}
```

## Develop

```sh
pip install -e '.[test]'   # into the environment abh3-supervisor is installed in
abh3 plugins               # lists {name}: its version, API version and hooks
abh3 check my.yaml         # a typo'd hook or a missing @hookimpl fails here
pytest                     # tests/test_{module}.py
```

The module `{module}.py` has an output hook (`abh3_feedback`) and, commented out, an
input source and the e-stop. It imports only `abh3_supervisor.plugin_api`, the public
API; `ABH3_API_VERSION` says which version of it the plugin was written for.

## Test

`abh3_supervisor.plugin_testing.run_with_plugin(config, plugin, name, seconds)` runs a
configuration as `abh3 run --headless` does — every bus on the built-in simulator — with
your plugin object loaded as `name`, for `seconds` of real time, and returns a
`PluginRun`: the records every plugin received (`feedback`, `status`, `health`, `flags`,
`notices`), the input sources that took part (`sources`), the frames on the wire
(`frames`: `t`, `bus`, `arbitration_id`, `data`), the log lines (`log`), and the
`exit_code` `abh3 run` would give (`error` says why when it ended before it began: 2 for
settings, 1 for a plugin that cannot start). Settings go in the YAML's
`plugins.{name}` section or as `settings={{...}}`.

To act while the run goes on, use the context manager and wait for a condition (never
sleep):

```python
from abh3_supervisor.plugin_testing import running

with running(CONFIG, plugin, "{name}", seconds=2.0) as run:
    assert run.wait_for(lambda r: len(r.feedback) >= 10)
```

The same function is the pytest fixture `abh3_run`: put
`pytest_plugins = ["abh3_supervisor.plugin_testing"]` in a `conftest.py` next to
pyproject.toml.
"""
