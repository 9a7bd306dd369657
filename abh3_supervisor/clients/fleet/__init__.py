"""``abh3 fleet``: the robots on the plant's MQTT broker (docs/fleet.md, "The fleet view")."""
