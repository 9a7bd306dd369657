"""The public plugin API: the one module a plugin imports from abh3_supervisor.

Everything a plugin needs is here, importable at runtime: the ``hookimpl`` marker, the
records its hooks receive, the read-only supervisor view, input sources and their feed,
the section and schema helpers for its settings, and the few pure helpers the built-in
plugins use (kinematics, odometry, flag words, frames, diagnostics). Each name keeps the
module it is defined in (``help()`` says which); import it from here, never from there.

Compatibility (docs/plugins.md, "Compatibility"): ``API_VERSION`` is ``MAJOR.MINOR``.
Within one major version, nothing here is removed or renamed, no hook argument is removed
and no record field changes meaning; a minor version only adds (names, hooks, hook
arguments, record fields with defaults). Hooks are called with keyword arguments and a
plugin may take fewer than offered, so an added argument breaks no plugin. Anything
imported from another abh3_supervisor module may change in any release.

Facts an author asks for first (docs/plugins.md has the rest; tests/test_docs_claims.py
holds both to the code):

- The host's keys, valid in every ``plugins.<name>`` section and never shown to the
  plugin: ``on_error``, ``critical``, ``start_timeout_s``, ``tick_hz``.
- Order: plugins are called in the order the YAML's ``plugins:`` names them. At the
  start every ``abh3_threads``, then each plugin's ``abh3_start`` and its
  ``abh3_input_sources``, then each source's ``start(feed)`` as registered; on the way
  out the same order, not reversed: each source's ``stop()``, the workers' queues
  drained, each ``abh3_stop`` (a plugin whose start failed gets it too).
- ``abh3_stop`` has 2 s; an ``OSError`` there is an output failure (exit code 5, unless
  1 or 3 apply), any other exception or a block is logged and changes no exit code.
- :class:`InputFeed`, from any thread: ``twist(linear_x, angular_z)``,
  ``velocity_yx(y, x)``, ``velocity_ab(a, b)``, ``velocity(ay, bx)``, ``current(ay, bx)``,
  ``release()`` (arbitrated: repeat within the source's timeout); ``retarget(units)``,
  ``inputs(data, mask)``, ``command(text)`` and ``enable(on)`` (each a
  ``concurrent.futures.Future[str]``), ``request_status(packet)``,
  ``emergency_stop()``. Its ``hold``, ``execute``, ``holds`` and ``alive`` are the bus
  loop's, for control-socket clients: not for plugins.
- :class:`OwnerChange`'s ``old``/``new``: an input source's name (``str``) or ``None``
  (nobody: zero); :class:`EstopChange`'s ``source``: who latched or cleared it (``str``).
- A relative path in a section is the plugin's to resolve: nothing resolves it against
  the YAML's folder (``section.src.file``); ``Section.output_path`` checks it against the
  working directory.
"""

from __future__ import annotations

from abh3_supervisor import fleet
from abh3_supervisor.config import schema
from abh3_supervisor.config.model import Config, ControlMode, Role, UnitConfig, VelocityModel
from abh3_supervisor.config.source import Section
from abh3_supervisor.core import kinematics
from abh3_supervisor.core.commands import RESPONSE_INVALID, RESPONSE_OK
from abh3_supervisor.core.diagnostics import Health, Level, Status
from abh3_supervisor.core.inputs import DEFAULT_TIMEOUT, Feed, InputSource
from abh3_supervisor.core.odometry import Odometer, Pose, yaw_quaternion
from abh3_supervisor.core.robot import RobotConfig, from_geometry, motor_speeds
from abh3_supervisor.core.state import Feedback, Setpoint
from abh3_supervisor.core.supervisor import (
    EstopChange,
    FlagChange,
    Notice,
    OperatorAction,
    OwnerChange,
)
from abh3_supervisor.core.twist_limits import fastest_twist
from abh3_supervisor.errors import CommandError, PluginError
from abh3_supervisor.plugin_host import terminal
from abh3_supervisor.plugin_host.feed import InputFeed
from abh3_supervisor.plugin_host.hookspecs import PROJECT, THREADS_BELOW_LOOP, hookimpl
from abh3_supervisor.plugin_host.view import (
    BusCounters,
    ForeignHost,
    SupervisorView,
    UnitView,
    word_of,
)
from abh3_supervisor.protocol import flags, frames
from abh3_supervisor.protocol.frames import (
    Brd0,
    Brd1,
    Brd2,
    Brd3,
    Brd4,
    Brd5,
    Brd6,
    Brd7,
    Broadcast,
)
from abh3_supervisor.protocol.scaling import CURRENT, VELOCITY, Scale

# 1.1: fleet; SupervisorView.clear_emergency_stop, .bus_counters, .foreign_hosts
# 1.2: the abh3_threads hook, THREADS_BELOW_LOOP; PluginError (said as written)
# 1.3: abh3_feedback's inputs (the input word in force with the setpoint)
API_VERSION = "1.3"
"""``MAJOR.MINOR`` of this module's promise; a plugin may check the major it was written for."""

# the entry-point group a plugin registers under: [project.entry-points.abh3_supervisor]
GROUP = PROJECT

__all__ = [
    "API_VERSION",
    "CURRENT",
    "DEFAULT_TIMEOUT",
    "GROUP",
    "RESPONSE_INVALID",
    "RESPONSE_OK",
    "THREADS_BELOW_LOOP",
    "VELOCITY",
    "Brd0",
    "Brd1",
    "Brd2",
    "Brd3",
    "Brd4",
    "Brd5",
    "Brd6",
    "Brd7",
    "Broadcast",
    "BusCounters",
    "CommandError",
    "Config",
    "ControlMode",
    "EstopChange",
    "Feed",
    "Feedback",
    "FlagChange",
    "ForeignHost",
    "Health",
    "InputFeed",
    "InputSource",
    "Level",
    "Notice",
    "Odometer",
    "OperatorAction",
    "OwnerChange",
    "PluginError",
    "Pose",
    "RobotConfig",
    "Role",
    "Scale",
    "Section",
    "Setpoint",
    "Status",
    "SupervisorView",
    "UnitConfig",
    "UnitView",
    "VelocityModel",
    "fastest_twist",
    "flags",
    "fleet",
    "frames",
    "from_geometry",
    "hookimpl",
    "kinematics",
    "motor_speeds",
    "schema",
    "terminal",
    "word_of",
    "yaw_quaternion",
]
