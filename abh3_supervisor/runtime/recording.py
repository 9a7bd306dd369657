"""What ``--record`` says: where it records, and at the end how many frames it holds."""

from __future__ import annotations

from pathlib import Path

from abh3_supervisor.runtime.bus_runtime import Runtime
from abh3_supervisor.runtime.recorder import GuardedRecorder


def recording(path: Path) -> str:
    return f"recording all bus traffic to {path.resolve()}"


def recorded(rt: Runtime, path: Path) -> str:
    """Every frame the buses' pumps sent or received went to the recording (the stop
    frames included), unless writing failed."""
    sent = sum(p.frames_sent for p in rt.pumps.values())
    received = sum(p.frames_received for p in rt.pumps.values())
    failed = {
        p.recorder.failed
        for p in rt.pumps.values()
        if isinstance(p.recorder, GuardedRecorder) and p.recorder.failed
    }
    if failed:
        return f"recording {path.resolve()} ended early: {'; '.join(sorted(failed))}"
    return (
        f"recorded {sent + received} frames ({sent} sent, {received} received) to {path.resolve()}"
    )
