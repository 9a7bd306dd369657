"""``abh3 fleet``: the robots on the plant's MQTT broker (docs/fleet-view.md)."""
