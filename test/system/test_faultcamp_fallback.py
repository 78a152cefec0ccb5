"""The planner's safe-mode FALLBACK over the deck keeps the vehicle over the deck (issue 6,
`fault_lidar_dropout` seed 100027: an edge strike at 0.06 m/s).

The lidar drops out in FINAL; after the grace period the planner falls back to a slow descent
"where it is". It used to latch that place as a GPS position: the camera still saw the beacon,
but the setpoint no longer followed it, and the GPS error (bias random walk, ~0.3 m in 2 s in
that run) carried the vehicle to the pad's edge. The deck is where the camera sees the beacon;
the GPS error moves the vehicle's reported position and the beacon's (vehicle + camera offset)
together, so a setpoint that follows the beacon is immune to it.
"""

from __future__ import annotations

import math

from deckland_common.contract import Mode
from landing_planner.planner import LandingPlanner, PlannerParams
from planner_support import make_apron, make_vehicle, make_vertical

DT = 0.01


class _Final:
    """A planner in FINAL over a beacon at the true origin; the GPS error ``e`` shifts the
    reported vehicle position and the reported beacon position alike (the camera offset is
    relative and true)."""

    def __init__(self) -> None:
        self.p = LandingPlanner(PlannerParams(landing_area_m=(0.0, 0.0)))
        self.t = 0.0
        self.e = (0.0, 0.0)
        self.height = 2.0
        self.valid = True
        self.beacon = True
        self.p.start_landing(0.0)
        self.out = None

    def step(self):
        ex, ey = self.e
        vert = make_vertical(self.height, 0.0, 0.6, valid=self.valid)
        veh_xy = (0.01 + ex, 0.0 + ey)                  # true vehicle 1 cm off the beacon
        apron = make_apron(self.t, veh_xy, (ex, ey) if self.beacon else None, vert)
        veh = make_vehicle(self.t, veh_xy, self.height + 0.6)
        self.out = self.p.step(self.t, DT, veh, apron)
        self.t = round(self.t + DT, 9)
        return self.out

    def run(self, seconds, drift_mps=(0.0, 0.0)):
        for _ in range(round(seconds / DT)):
            self.e = (self.e[0] + drift_mps[0] * DT, self.e[1] + drift_mps[1] * DT)
            self.step()

    def steer_error_m(self) -> float:
        """Where the setpoint steers the vehicle, in truth, relative to the beacon."""
        sx, sy = self.out.setpoint_m
        return math.hypot(sx - self.e[0], sy - self.e[1])


def _in_final() -> _Final:
    f = _Final()
    f.run(1.0)
    assert f.out.mode is Mode.DESCEND
    f.height = 0.45
    f.run(0.05)
    assert f.out.mode is Mode.FINAL
    return f


def test_a_lidar_dropout_in_final_falls_back_over_the_deck_and_follows_it():
    f = _in_final()
    f.valid = False
    f.run(0.6)
    assert f.out.mode is Mode.FALLBACK
    # the GPS error wanders 0.3 m in 2 s during the slow descent: the setpoint must stay
    # over the beacon in truth (the vehicle follows its GPS position to the setpoint)
    f.run(2.0, drift_mps=(0.0, 0.15))
    assert f.out.mode is Mode.FALLBACK
    assert f.steer_error_m() < 0.05
    assert f.out.z_d_dot_mps < 0.0 and f.out.thrust_enabled     # still a slow descent


def test_the_fallback_over_the_deck_holds_the_last_setpoint_when_the_beacon_is_lost():
    """As FINAL: continues blind on the last setpoint (not a jump to the GPS position)."""
    f = _in_final()
    f.valid = False
    f.run(0.6)
    assert f.out.mode is Mode.FALLBACK
    sp = f.out.setpoint_m
    f.beacon = False
    f.run(1.0, drift_mps=(0.0, 0.15))
    assert f.out.setpoint_m == sp


def test_a_fallback_without_the_target_still_holds_its_gps_position():
    """FALLBACK after the searches (nothing tracked on entry): unchanged, a GPS hold; a blob
    seen later during that descent is not followed (a slew near the ground could reach an
    edge)."""
    f = _Final()
    f.beacon = False
    f.run(0.5)
    f.p._switch_to(Mode.FALLBACK, f.t, 'test: searches used up')
    f.run(0.1)
    sp = f.out.setpoint_m
    f.beacon = True
    f.e = (0.5, 0.0)
    f.run(1.0)
    assert f.out.mode is Mode.FALLBACK and f.out.setpoint_m == sp


def test_a_track_beyond_the_area_gate_is_still_refused():
    """The gate stays (it also guards against a diverging estimate: sea_state_4)."""
    f = _Final()
    f.e = (3.5, 0.0)                                           # first seen 3.5 m off the area
    f.run(2.5)
    assert f.out.mode is not Mode.ALIGN and f.p.mode is not Mode.DESCEND


def test_a_fallback_after_the_searches_over_the_tracked_deck_follows_it():
    """`fault_gps_jump` seed 200032: GPS bias + a 1.5 m jump put the reported apron ~3 m from
    the landing area, at `max_xy_dist_m`: the target flickered out of that gate, three
    'lost' searches, then a FALLBACK from 3.3 m right over the beacon on a GPS hold that
    drifted onto the pad's edge. 'Land where it is' is the deck: the FALLBACK follows the
    camera's beacon down (the GPS error moves the reported vehicle and beacon together)."""
    f = _Final()
    f.run(0.5)
    f.p._search.attempts = f.p.params.max_searches
    f.p._search_or_fallback(f.t, 'test: target lost')
    assert f.p.mode is Mode.FALLBACK
    f.run(2.0, drift_mps=(0.0, 0.15))
    assert f.steer_error_m() < 0.05
