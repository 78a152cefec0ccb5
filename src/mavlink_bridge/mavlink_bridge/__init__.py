"""MAVLink bridge between the deckland graph and a PX4/ArduPilot autopilot (pymavlink)."""
