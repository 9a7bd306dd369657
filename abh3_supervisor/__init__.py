"""abh3-supervisor: supervise Waco Giken ABH3 two-axis drives on CAN buses."""

__version__ = "0.1.0"
