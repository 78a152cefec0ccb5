"""Heaving-deck and quadcopter simulator: physics, sensors, scenarios, and a hardware-
emulating node.
"""
