"""``mqtt``: each robot on the plant's MQTT broker (docs/fleet.md): its status with the
broker's last will, each unit's state, events and health; e-stops, their clearing and
motion from the fleet only when allowed. Network I/O lives in paho's threads: the hooks
only queue (outbox.py)."""
