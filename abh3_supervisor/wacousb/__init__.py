"""python-can interface ``wacousb``: the ABH3 maker's USB-CAN adapter (see bus.py)."""

from abh3_supervisor.wacousb.bus import WacoUsbBus

__all__ = ["WacoUsbBus"]
