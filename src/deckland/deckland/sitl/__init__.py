"""Real autopilots as processes for tests, demos and campaigns (PX4 SITL: :mod:`.px4`)."""
