"""The hooks a plugin may implement. Each is documented in docs/plugins.md; plugins
import them (and every record they name) from :mod:`abh3_supervisor.plugin_api`.

Call conventions: hooks are called with keyword arguments, and an implementation may
accept fewer arguments than its spec (pluggy's rule), so specs can grow without breaking
plugins. No hook runs on the main thread (where stop signals are handled): the schema,
configuration (while the file loads), threads, start, input-source and stop hooks run on a
thread of their own with a deadline (a plugin failing to start fails the run before any
frame is sent); the observation hooks (``abh3_feedback`` … ``abh3_tick``) run in the
plugin's own worker thread, so a slow plugin never delays the bus. ``sys.exit()`` or
``KeyboardInterrupt`` from a hook is the plugin's failure like any exception.
``supervisor`` is a read-only :class:`SupervisorView`, never the Supervisor itself.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import pluggy

from abh3_supervisor.config.model import Config
from abh3_supervisor.config.source import Section
from abh3_supervisor.core.inputs import InputSource
from abh3_supervisor.core.state import Feedback, Setpoint
from abh3_supervisor.core.supervisor import EstopChange, FlagChange, Notice, OwnerChange
from abh3_supervisor.plugin_host.view import SupervisorView
from abh3_supervisor.protocol.frames import Broadcast

PROJECT = "abh3_supervisor"
hookspec = pluggy.HookspecMarker(PROJECT)
hookimpl = pluggy.HookimplMarker(PROJECT)


@hookspec
def abh3_configure(section: Section, config: Config) -> None:
    """Validate this plugin's own ``plugins.<name>`` YAML section; report with ``section.error``.

    ``config`` is the rest of the file, already validated (units, buses), for cross-checks.
    """


@hookspec
def abh3_config_schema() -> dict[str, Any] | None:
    """The JSON Schema of this plugin's ``plugins.<name>`` section (for ``abh3 schema``).

    Build it with :mod:`abh3_supervisor.config.schema`'s builders; called without a run.
    """


THREADS_BELOW_LOOP = "below_loop"


@hookspec
def abh3_threads() -> str | None:
    """Where this plugin's threads run when the bus loop runs real-time: ``None`` or
    ``"normal"`` (the default: normal priority, as DDS and rclpy need) or
    ``"below_loop"`` (``SCHED_FIFO`` just below the loop: its start, its hooks, its tick
    and every thread it starts from them). Only for plugins whose threads do short,
    bounded work and sleep between: a normal-priority thread preempted while it holds
    the interpreter lock holds the loop up by milliseconds on a busy machine. Asked once,
    before ``abh3_start``, within the start deadline; a raise or a block is the plugin's
    failure (its threads then normal)."""


@hookspec
def abh3_start(supervisor: SupervisorView) -> None:
    """Before the first frame: open files, start threads; raise if you cannot (the run fails)."""


@hookspec
def abh3_input_sources(register: Callable[[InputSource], None], supervisor: SupervisorView) -> None:
    """Contribute input sources by calling ``register(source)`` for each."""


@hookspec
def abh3_feedback(unit: str, feedback: Feedback, setpoint: Setpoint, inputs: int) -> None:
    """After every DP0 reply: velocity feedback, and the setpoint and the input word
    (the bits the host commands) that were in force when it came."""


@hookspec
def abh3_status(unit: str, packet: int, record: Broadcast, t: float) -> None:
    """A broadcast status packet (0–7) arrived from a unit."""


@hookspec
def abh3_health(unit: str, online: bool, t: float) -> None:
    """A unit went online or offline."""


@hookspec
def abh3_flags(change: FlagChange) -> None:
    """A flag word (error, alarm, control, io, inputs) of a unit changed."""


@hookspec
def abh3_notice(notice: Notice) -> None:
    """Something for the operator: clamping, e-stop, model mismatch, plugin trouble."""


@hookspec
def abh3_estop(event: EstopChange) -> None:
    """The e-stop was latched (``event.latched``) or cleared, and by whom (``event.source``)."""


@hookspec
def abh3_owner(change: OwnerChange) -> None:
    """The input source whose command a unit has changed (taken over, let go, stopped)."""


@hookspec
def abh3_tick(t: float) -> None:
    """Periodically, at the section's ``tick_hz`` (default 10): ``t`` on the events' clock."""


@hookspec
def abh3_stop(supervisor: SupervisorView) -> None:
    """Every way out, after the drives were stopped: flush and close everything."""
