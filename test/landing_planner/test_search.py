"""The search / retry machine (Steps 11-12) and the handler table of the landing planner."""

from deckland_common.contract import Mode
from landing_planner.planner import _STATES, PlannerParams
from landing_planner.search import SearchPattern
from planner_support import AREA, Driver
import pytest


def test_retry_grants_max_attempts_then_refuses_until_reset():
    s = SearchPattern(max_attempts=3, radius_m=1.0, hold_s=2.0)
    assert [s.retry() for _ in range(5)] == [True, True, True, False, False]
    assert s.attempts == 3
    s.reset()
    assert s.attempts == 0 and s.retry() and s.attempts == 1


def test_no_attempts_allowed_goes_straight_to_the_fallback():
    assert SearchPattern(max_attempts=0, radius_m=1.0, hold_s=2.0).retry() is False


def test_pattern_hovers_over_the_centre_then_flies_the_square_and_repeats():
    s = SearchPattern(max_attempts=3, radius_m=0.5, hold_s=2.0)
    c = (2.0, -1.0)
    assert s.begin(c) == c
    # the first leg (to the centre) is flown at t = 10: hover for hold_s from then on
    assert s.next_goal(10.0) is None
    assert s.next_goal(11.99) is None
    corners = [s.next_goal(12.0)] + [s.next_goal(20.0 + k) for k in range(4)]
    assert corners == [(2.5, -0.5), (1.5, -0.5), (1.5, -1.5), (2.5, -1.5), c]
    # back over the centre: the next round starts with a hover again
    assert s.next_goal(30.0) == c
    assert s.next_goal(30.5) is None
    assert s.next_goal(32.5) == (2.5, -0.5)


def test_begin_restarts_the_pattern_and_its_hover():
    s = SearchPattern(max_attempts=3, radius_m=1.0, hold_s=2.0)
    s.begin((0.0, 0.0))
    s.next_goal(0.0)
    s.next_goal(2.0)                            # on the way to the first corner
    assert s.begin((5.0, 5.0)) == (5.0, 5.0)
    assert s.next_goal(3.0) is None             # hovers again over the new centre
    assert s.next_goal(5.0) == (6.0, 6.0)


def test_every_mode_has_a_handler():
    assert set(_STATES) == set(Mode)
    world = {m for m, s in _STATES.items() if s.world_ramp}
    assert world == {Mode.DESCEND, Mode.FINAL}


def test_a_service_switch_runs_its_entry_on_the_next_steps_inputs():
    """takeoff() between steps: the TAKEOFF entry re-bases the reference on the height that
    the next step reads (1.0 m), not on the one known at the call (0.2 m)."""
    d = Driver(PlannerParams(landing_area_m=AREA), height=0.2)
    d.run(0.1)
    assert d.out.mode is Mode.IDLE
    assert d.p.takeoff(d.t)[0]
    d.height = 1.0
    out = d.step()
    assert out.mode is Mode.TAKEOFF
    assert out.z_d_m == pytest.approx(1.0, abs=1e-3)


def test_reasons_keep_the_step_numbers_through_a_search_cycle():
    params = PlannerParams(landing_area_m=AREA, search_timeout_s=5.0, max_searches=1)
    d = Driver(params, xy=AREA)
    d.p.start_landing(0.0)
    reasons = []
    for _ in range(1000):
        d.step()
        if not reasons or reasons[-1] != d.out.reason:
            reasons.append(d.out.reason)
    assert reasons == [
        'start_landing requested (Step 1)',
        'no target at the landing area (Step 3): search attempt 1 of 1 (Steps 11-12)',
        'search attempt 1 timed out (Step 13): 1 search attempts used, landing where it is '
        '(Step 14)',
    ]
    assert d.p.searches == 1
