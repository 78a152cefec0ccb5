"""The planner tests' kinematic stand-in (planner_support.StandIn) behaves physically."""

from deckland_common.contract import Mode
from planner_support import StandIn


def test_stand_in_hover_is_steady():
    """Sanity check of the stand-in itself: idle hover stays where it is."""
    sim = StandIn(start_xy=(-3.0, 0.0))
    sim.run(3.0)
    assert sim.planner.mode is Mode.IDLE
    assert abs(sim.x + 3.0) < 1e-6 and abs(sim.z - 2.0) < 1e-3


def test_stand_in_tilt_moves_toward_setpoint():
    """The horizontal loop in the stand-in drives the point mass to the setpoint."""
    sim = StandIn(start_xy=(-3.0, 0.0))
    sim.planner.start_landing(0.0)
    sim.run(4.0)
    assert sim.x > -2.0   # moved toward the landing area at (0, 0)
