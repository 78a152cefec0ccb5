"""False blobs: the horizontal tracker keeps rivals, reports ambiguity, resolves with the lidar,
and the planner does not descend on an ambiguous target."""

from __future__ import annotations

import math
import random

from apron_estimator.horizontal import HorizontalParams, HorizontalTracker
from deckland_common.contract import ApronState, Mode, VehicleState, VerticalState
from landing_planner.planner import LandingPlanner, PlannerParams

DT = 0.02
GLINT = (0.6, 0.0)      # glint minus beacon, ENU (m)


def _fly(tr: HorizontalTracker, t0: float, seconds: float, vehicle_xy, rng, surface_at,
         glint=True):
    """Static vehicle at vehicle_xy; beacon at the origin; frames at 50 Hz with noise."""
    t = t0
    for _ in range(round(seconds / DT)):
        t += DT
        vx, vy = vehicle_xy
        cands = [(-vx + rng.gauss(0, 0.01), -vy + rng.gauss(0, 0.01))]
        if glint:
            cands.append((GLINT[0] - vx + rng.gauss(0, 0.01), GLINT[1] - vy + rng.gauss(0, 0.01)))
        tr.on_accel(t, 0.0, 0.0)
        tr.update(t, cands, 1.5, surface_at(vx, vy))
    return t


def _move(tr, t0, seconds, a, b, rng, surface_at):
    """Fly slowly (straight line, constant speed) from a to b, frames as in _fly."""
    n = round(seconds / DT)
    t = t0
    for k in range(1, n + 1):
        f = k / n
        t = _fly(tr, t, DT, (a[0] + f * (b[0] - a[0]), a[1] + f * (b[1] - a[1])), rng,
                 surface_at)
    return t


def _deck_surface(x, y):
    return 0.6 if abs(x) <= 0.5 and abs(y) <= 0.4 else 0.0


def test_a_persistent_rival_makes_the_target_ambiguous_and_inflates_the_variance():
    rng = random.Random(1)
    tr = HorizontalTracker(HorizontalParams())
    _fly(tr, 0.0, 0.2, (0.0, 0.0), rng, lambda x, y: None, glint=False)
    t = _fly(tr, 0.2, 0.5, (0.0, 0.0), rng, lambda x, y: None)
    assert tr.tracked and tr.ambiguous
    x, y, *_rest = tr.state(t)
    var_x = _rest[2]
    assert math.hypot(x, y) < 0.05                 # still on the beacon (first acquired)
    assert var_x >= 0.6 ** 2 * 0.9                 # the spread of the two hypotheses


def test_the_rival_beside_the_deck_is_rejected_by_the_lidar_and_the_track_stays():
    rng = random.Random(2)
    tr = HorizontalTracker(HorizontalParams())
    _fly(tr, 0.0, 0.2, (0.0, 0.0), rng, _deck_surface, glint=False)
    t = _fly(tr, 0.2, 1.0, (0.0, 0.0), rng, _deck_surface)    # over the beacon: deck
    # the beacon's surface is sampled (deck), then the tracker probes the unvisited rival:
    # the track moves onto the glint, the beacon becomes the rival carrying its sample
    assert tr.ambiguous and tr.events['probes'] == 1
    assert [round(r.surface, 3) for r in tr.rivals] == [0.6] and tr.surface is None
    x, y, *_ = tr.state(t)
    assert math.hypot(x - GLINT[0], y - GLINT[1]) < 0.05
    # the planner follows: the vehicle hovers over the glint, the lidar sees the ground
    t = _move(tr, t, 3.0, (0.0, 0.0), GLINT, rng, _deck_surface)
    t = _fly(tr, t, 1.0, GLINT, rng, _deck_surface)
    assert not tr.ambiguous
    assert tr.events['switches'] == 1 and tr.events['rivals_rejected'] == 1
    x, y, _, _, var_x, var_y, *_ = tr.state(t)
    assert math.hypot(x + GLINT[0], y + GLINT[1]) < 0.05     # back on the beacon
    assert var_x < 0.01 and var_y < 0.01


def test_two_hypotheses_on_the_same_surface_stay_ambiguous():
    rng = random.Random(3)
    tr = HorizontalTracker(HorizontalParams())
    flat = lambda x, y: 0.6     # noqa: E731 - a glint on the deck itself
    _fly(tr, 0.0, 0.2, (0.0, 0.0), rng, flat, glint=False)
    t = _fly(tr, 0.2, 1.0, (0.0, 0.0), rng, flat)
    t = _move(tr, t, 3.0, (0.0, 0.0), GLINT, rng, flat)
    t = _fly(tr, t, 1.0, GLINT, rng, flat)
    assert tr.ambiguous and tr.events['rivals_rejected'] == 0


def test_flickering_blobs_never_confirm_a_rival():
    rng = random.Random(4)
    tr = HorizontalTracker(HorizontalParams())
    t = 0.0
    for _ in range(200):
        t += DT
        cands = [(rng.gauss(0, 0.01), rng.gauss(0, 0.01)),
                 (rng.uniform(-1, 1), rng.uniform(-1, 1))]
        tr.update(t, cands, 1.5, 0.6)
    assert tr.tracked and not tr.ambiguous


def _apron(t, var, rel=(0.0, 0.0)):
    v = VerticalState(True, 1.5, 0.0, 2.1, 0.0, 0.6, 0.0, 0.0, 0, 0.0)
    return ApronState(t, True, True, 0.0, rel, (0.0, 0.0), (var, var), rel, (0.0, 0.0),
                      rel, (0.0, 0.0), v)


def _plan(var: float, seconds: float = 4.0) -> LandingPlanner:
    pl = LandingPlanner(PlannerParams(landing_area_m=(0.0, 0.0)))
    pl.start_landing(0.0)
    t = 0.0
    while t < seconds:
        veh = VehicleState(t, (0.0, 0.0, 2.1), (0.0, 0.0, 0.0), 0.0, 0.0, 0.0)
        pl.step(t, 0.01, veh, _apron(t, var))
        t += 0.01
    return pl


def test_the_planner_does_not_descend_on_an_ambiguous_target():
    assert _plan(0.0025).mode is Mode.DESCEND                  # σ = 5 cm: descends
    ambiguous = _plan(0.36 + 0.0025)                            # rival 0.6 m away
    assert ambiguous.mode is Mode.ALIGN
    nan = _plan(math.nan)
    assert nan.mode is Mode.ALIGN


def test_an_ambiguity_in_descend_pauses_and_re_aligns():
    pl = _plan(0.0025)
    assert pl.mode is Mode.DESCEND
    t = 4.0
    veh = VehicleState(t, (0.0, 0.0, 2.0), (0.0, 0.0, 0.0), 0.0, 0.0, 0.0)
    pl.step(t, 0.01, veh, _apron(t, 0.5))
    assert pl.mode is Mode.ALIGN and 'ambiguous' in pl.reason


def _glint_first(top_m):
    """The vehicle hovers over a glint on the ground (GLINT from the beacon); the beacon on
    the 0.6 m deck shows for 1 s, then leaves the view for 3 s; ``top_m`` is the deck's level
    the estimator passes (decision 12d), None as before."""
    rng = random.Random(4)
    tr = HorizontalTracker(HorizontalParams())
    t = 0.0
    vx, vy = GLINT
    for _ in range(round(5.0 / DT)):
        t += DT
        cands = [(GLINT[0] - vx + rng.gauss(0, 0.01), GLINT[1] - vy + rng.gauss(0, 0.01))]
        if 0.4 <= t < 1.4:
            cands.append((-vx + rng.gauss(0, 0.01), -vy + rng.gauss(0, 0.01)))
        tr.on_accel(t, 0.0, 0.0)
        tr.update(t, cands, 1.5, _deck_surface(vx, vy), (0.0, 0.0), top_m)
    return tr, t, (vx, vy)


def test_a_track_verified_on_the_ground_below_the_deck_stays_ambiguous():
    """fault_false_blobs seed 100003 (pid): the track on a ground glint was verified (the
    ground under it) while the beacon, out of view, timed out; the glint was then the only,
    unambiguous hypothesis and was descended on (edge strike). With the deck's level known
    (decision 12d) a track sampled more than deck_rise_m below it keeps its rivals: the
    target stays ambiguous (the planner does not descend) and the rival is probed."""
    tr, t, _ = _glint_first(None)
    x, y, *_ = tr.state(t)
    assert math.hypot(x, y) < 0.05 and not tr.rivals and not tr.ambiguous   # on the glint
    tr, t, _ = _glint_first(0.6)
    assert tr.ambiguous and tr.events['probes'] >= 1 and tr.rivals
