"""What ``--record`` says: where it records, at the end how many frames it holds, and
what stopped early on a write error."""

from __future__ import annotations

import time
from pathlib import Path

from abh3_supervisor.plugin_host.host import PluginHost
from abh3_supervisor.runtime.bus_runtime import Runtime
from abh3_supervisor.runtime.recorder import GuardedRecorder


def recording(path: Path) -> str:
    return f"recording all bus traffic to {path.resolve()}"


def _recorder(rt: Runtime) -> GuardedRecorder | None:
    return rt.recording  # kept after the run: its outcome (the pumps may hold a live feed)


def recorded(rt: Runtime, path: Path) -> str:
    """Every frame the buses' pumps sent or received went to the recording (the stop
    frames included), unless writing failed."""
    recorder = _recorder(rt)
    if recorder is not None and recorder.failed is not None:
        at = time.strftime("%H:%M:%S", time.localtime(recorder.failed_at or time.time()))
        return (
            f"recording {path.resolve()} stopped early, at {at}, on a write error "
            f"({recorder.failed}): it holds the frames written before"
        )
    sent = sum(p.frames_sent for p in rt.pumps.values())
    received = sum(p.frames_received for p in rt.pumps.values())
    return (
        f"recorded {sent + received} frames ({sent} sent, {received} received) to {path.resolve()}"
    )


def write_failures(rt: Runtime, plugins: PluginHost | None) -> list[str]:
    """What stopped recording early on a write error (a full disk): ``--record``, and each
    plugin whose output failed."""
    failed = []
    recorder = _recorder(rt)
    if recorder is not None and recorder.failed is not None:
        failed.append(f"--record {recorder.path}")
    if plugins is not None:
        failed += [f"plugin {name}'s output" for name in sorted(plugins.output_failures)]
    return failed
