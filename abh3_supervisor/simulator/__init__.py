"""A simulated ABH3 that answers on a CAN bus as the drive does (sans-I/O model)."""

from abh3_supervisor.simulator.bus import SimBus
from abh3_supervisor.simulator.drive import SimDrive

__all__ = ["SimBus", "SimDrive"]
