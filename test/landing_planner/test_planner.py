"""Each guarded transition of the landing state machine, driven with hand-made states."""

import itertools
import math
import random

from deckland_common.contract import Mode
from landing_planner.planner import LandingPlanner, PlannerParams
from planner_support import (
    AREA,
    DT,
    Driver,
    aligned_driver,
    make_apron,
    make_vehicle,
    make_vertical,
)
import pytest


def test_params_validation_names_the_field():
    with pytest.raises(ValueError, match='acceptance_radius_m'):
        PlannerParams(acceptance_radius_m=-0.1)
    with pytest.raises(ValueError, match='descent_profile'):
        PlannerParams(descent_profile='yolo')
    with pytest.raises(ValueError, match='landing_area_m'):
        PlannerParams(landing_area_m=(math.nan, 0.0))
    with pytest.raises(ValueError, match='final_approach_height_m'):
        PlannerParams(final_approach_height_m=3.0)
    with pytest.raises(ValueError, match='max_searches'):
        PlannerParams(max_searches=-1)


def test_services_follow_trigger_semantics():
    p = LandingPlanner(PlannerParams())
    assert p.abort(0.0)[0] is False               # nothing to abort in IDLE
    assert p.start_landing(0.0) == (True, 'landing started')
    assert p.mode is Mode.APPROACH
    ok, msg = p.start_landing(0.1)
    assert not ok and 'already landing' in msg
    assert p.takeoff(0.1)[0] is False
    assert p.abort(0.2)[0] and p.mode is Mode.HOLD
    assert p.abort(0.3) == (True, 'already holding')
    assert p.start_landing(0.4)[0] and p.mode is Mode.APPROACH


def test_approach_to_align_when_target_tracked_near_the_area():
    d = Driver(xy=(-3.0, 0.0))
    d.p.start_landing(0.0)
    d.run(1.0)
    assert d.out.mode is Mode.APPROACH
    d.beacon = (3.5, 0.0)                      # tracked but 3.5 m from the area (> 3 m)
    d.run(1.0)
    assert d.out.mode is Mode.APPROACH
    d.beacon = (0.3, -0.2)
    d.step()
    assert d.out.mode is Mode.ALIGN and 'Step 3' in d.out.reason


def test_approach_setpoint_moves_at_limited_speed_along_the_line():
    params = PlannerParams(landing_area_m=(6.0, 8.0))
    d = Driver(params, xy=(0.0, 0.0))
    d.p.start_landing(0.0)
    sps = [d.step().setpoint_m for _ in range(1200)]
    steps = [math.dist(a, b) / DT for a, b in itertools.pairwise(sps)]
    assert max(steps) <= params.approach_speed_mps + 1e-9          # no setpoint jump
    assert steps[0] < 0.01                                          # starts from rest
    # the acceleration of the setpoint is bounded too
    acc = [abs(b - a) / DT for a, b in itertools.pairwise(steps)]
    assert max(acc) <= params.approach_accel_mps2 + 1e-6
    # straight line toward the area (cross-track zero) and ends on it
    for x, y in sps:
        assert abs(x * 0.8 - y * 0.6) < 1e-9
    assert sps[-1] == pytest.approx((6.0, 8.0), abs=1e-6)
    assert d.out.velocity_ff_mps == pytest.approx((0.0, 0.0), abs=1e-9)


def test_align_to_descend_after_hold_time_in_radius_only():
    d = aligned_driver()
    d.run(0.3)
    assert d.out.mode is Mode.ALIGN            # 0.5 s hold not yet elapsed
    # leaves the 0.15 m radius for longer than the debounce (0.3 s): the timer restarts
    d.beacon = (0.3, 0.0)
    d.run(0.4)
    d.beacon = (0.05, 0.0)
    d.run(0.45)
    assert d.out.mode is Mode.ALIGN
    d.run(0.1)
    assert d.out.mode is Mode.DESCEND and 'Step 5 → Step 6' in d.out.reason
    assert d.out.z_d_dot_mps <= 0.0


def test_a_short_excursion_out_of_the_radius_does_not_restart_the_hold():
    # issue 13, part 5: one noisy sample (here 0.1 s of them) must not restart the timer
    d = aligned_driver()
    d.run(0.3)
    d.beacon = (0.3, 0.0)
    d.run(0.1)
    d.beacon = (0.05, 0.0)
    d.run(0.15)
    assert d.out.mode is Mode.DESCEND


def test_align_holds_height_and_tracks_the_target_with_feed_forward():
    d = aligned_driver()
    d.beacon = (0.5, 0.0)
    out = d.run(0.5)
    assert out.z_d_m == pytest.approx(2.0, abs=1e-9) and out.z_d_dot_mps == 0.0
    assert out.setpoint_m[0] == pytest.approx(0.5, abs=1e-9)


def test_descend_pauses_and_realigns_when_drifting_out_of_the_hysteresis_radius():
    d = aligned_driver()
    d.run(0.6)
    assert d.out.mode is Mode.DESCEND
    d.run(1.0)
    d.beacon = (0.2, 0.0)                       # 0.2 < 0.15 × 1.5: keep descending
    d.run(0.2)
    assert d.out.mode is Mode.DESCEND
    d.beacon = (0.3, 0.0)                       # 0.3 > 0.225: pause and re-align
    d.step()
    assert d.out.mode is Mode.ALIGN and 're-align' in d.out.reason
    z_before = d.out.z_d_m
    d.run(2.0)
    # height held: the reference brakes to a stop within the jerk-limited stopping distance
    # v (v/A + A/J) / 2 = 0.21 m from 0.4 m/s, and never climbs
    assert d.out.z_d_dot_mps == pytest.approx(0.0, abs=1e-9)
    assert z_before - 0.22 < d.out.z_d_m <= z_before


def test_descend_to_final_when_vertically_close_and_final_continues_blind():
    # a committed final descent (here: untimed, committed on entry) goes on blind
    d = aligned_driver(timed_touchdown=False)
    d.run(0.6)
    d.height = 0.49
    d.step()
    assert d.out.mode is Mode.FINAL and 'Step 9' in d.out.reason
    sp = d.out.setpoint_m
    d.beacon = None                             # lost below the final-approach height
    d.run(3.0)
    assert d.out.mode is Mode.FINAL             # keeps descending
    assert d.out.setpoint_m == sp and d.out.velocity_ff_mps == (0.0, 0.0)
    assert d.out.z_d_dot_mps < 0.0


def test_final_hold_climbs_when_the_target_is_lost_and_searches_after_three_timeouts():
    # the timed FINAL hold (not committed) waits for a window: blind there, the estimate
    # drifts with the wind off the pad (gusty seed 100020). It climbs to the final-approach
    # height first (a wider view), then searches as DESCEND does.
    d = aligned_driver(commit_timeout_s=60.0)   # (no prediction here: never a window)
    p = d.p.params

    def follow(duration, until=None):         # the vehicle flies the height reference
        end = d.t + duration
        while d.t < end - 1e-9:
            d.height = d.out.z_d_m
            d.step()
            if until is not None and d.out.mode is until:
                break
        return d.out

    d.run(0.6)
    assert d.out.mode is Mode.DESCEND
    follow(10.0, until=Mode.FINAL)
    assert d.out.mode is Mode.FINAL and not d.p._l.committed
    follow(6.0)                                 # settle onto the hold height
    hold = p.gear_height_m + p.commit_clearance_m
    assert d.out.z_d_m == pytest.approx(hold, abs=0.01)
    d.beacon = None
    follow(p.target_lost_timeout_s - 0.05)
    assert d.out.mode is Mode.FINAL and d.out.z_d_m == pytest.approx(hold, abs=0.01)
    follow(1.0)
    assert d.out.mode is Mode.FINAL and d.out.z_d_dot_mps > 0.0      # lost: climbs
    d.beacon = (0.02, 0.0)                      # seen again: back down to the hold
    follow(6.0)
    assert d.out.mode is Mode.FINAL
    assert d.out.z_d_m == pytest.approx(hold, abs=0.01)
    d.beacon = None
    out = follow(3.0 * p.target_lost_timeout_s + 0.1, until=Mode.SEARCH)
    assert out.mode is Mode.SEARCH and 'FINAL hold' in out.reason
    assert d.p.searches == 1
    assert max(d.height, out.z_d_m) > hold + 0.1    # it had climbed toward 0.5 m


def test_final_to_landed_by_height_speed_and_pressing_reference_for_the_hold_time():
    d = aligned_driver()
    d.run(0.6)
    d.height = 0.4
    d.run(0.05)
    assert d.out.mode is Mode.FINAL
    d.height, d.closing = 0.17, 0.0             # at gear height (0.15 + 0.05 tolerance)
    press = d.p.params.landed_press_m
    # The vehicle rests while the reference keeps descending at the final speed; LANDED only
    # once the reference is landed_press_m below the height, then held for landed_hold_s.
    t_press = None
    for _ in range(3000):
        d.step()
        if t_press is None and d.out.z_d_m <= 0.17 - press:
            t_press = d.t
        if d.out.mode is Mode.LANDED:
            break
    assert t_press is not None and d.out.mode is Mode.LANDED and not d.out.thrust_enabled
    assert d.t - t_press == pytest.approx(d.p.params.landed_hold_s, abs=0.03)
    assert 'Step 15' in d.out.reason


def test_hovering_at_gear_height_with_the_reference_there_is_not_landed():
    """A centimetre of height bias must not cut the motors above the deck."""
    d = aligned_driver()
    d.run(0.6)
    d.height = 0.4
    d.run(0.05)
    for _ in range(3000):                       # the vehicle follows the reference exactly
        d.height = max(d.out.z_d_m, 0.17)
        d.closing = d.out.z_d_dot_mps if d.out.z_d_m > 0.17 else 0.0
        d.step()
        if d.out.z_d_m > 0.17 - d.p.params.landed_press_m:
            assert d.out.mode is Mode.FINAL


def test_autopilot_landed_flag_lands_immediately():
    d = aligned_driver()
    d.run(0.6)
    d.height = 0.4
    d.run(0.05)
    d.landed_flag = True
    d.step()
    assert d.out.mode is Mode.LANDED


def test_lost_in_align_goes_to_search_after_timeout():
    d = aligned_driver()
    d.beacon = None
    d.run(0.95)
    assert d.out.mode is Mode.ALIGN
    d.run(0.1)
    assert d.out.mode is Mode.SEARCH and d.out.searches == 1
    d.run(1.5)
    assert d.out.z_d_dot_mps > 0.0              # climbing to the search height
    d.run(6.0)
    assert d.out.z_d_m == pytest.approx(3.5, abs=1e-9)


def test_search_attempts_then_fallback():
    params = PlannerParams(landing_area_m=AREA, search_timeout_s=5.0, max_searches=2)
    d = Driver(params, xy=AREA)
    d.p.start_landing(0.0)
    d.run(2.5)                                  # at the area, nothing seen for 2 s
    assert d.out.mode is Mode.SEARCH and d.out.searches == 1
    d.run(5.0)
    assert d.out.mode is Mode.SEARCH and d.out.searches == 2
    d.run(5.0)
    assert d.out.mode is Mode.FALLBACK and d.out.searches == 2
    assert 'Step 14' in d.out.reason


def test_search_reacquires_to_align():
    d = Driver(PlannerParams(landing_area_m=AREA), xy=AREA)
    d.p.start_landing(0.0)
    d.run(3.0)
    assert d.out.mode is Mode.SEARCH
    d.beacon = (0.8, 0.4)
    d.step()
    assert d.out.mode is Mode.ALIGN and 'Step 13' in d.out.reason


def test_search_pattern_stays_around_the_area():
    params = PlannerParams(landing_area_m=(2.0, 1.0), search_timeout_s=60.0)
    d = Driver(params, xy=(2.0, 1.0))
    d.p.start_landing(0.0)
    pts = []
    for _ in range(4000):
        d.step()
        pts.append(d.out.setpoint_m)
    assert d.out.mode is Mode.SEARCH
    xs = [p[0] for p in pts]
    ys = [p[1] for p in pts]
    r = params.search_radius_m
    assert max(xs) == pytest.approx(2.0 + r, abs=1e-6) and min(xs) == pytest.approx(2.0 - r,
                                                                                      abs=1e-6)
    assert max(ys) == pytest.approx(1.0 + r, abs=1e-6) and min(ys) == pytest.approx(1.0 - r,
                                                                                      abs=1e-6)


def test_surface_rebase_shifts_z_d_without_a_rate_step():
    d = aligned_driver()
    d.run(0.6)
    d.run(1.0)                                  # descending at speed
    before = d.out
    assert before.mode is Mode.DESCEND and before.z_d_dot_mps < -0.1
    # the deck slid under the vehicle: the surface below jumped up by 0.6 m
    d.height -= 0.6
    d.surface += 0.6
    d.epoch, d.rebase = 1, 0.6
    after = d.step()
    expected = before.z_d_m - 0.6 + before.z_d_dot_mps * DT
    assert after.z_d_m == pytest.approx(expected, abs=2e-4)
    assert abs(after.z_d_dot_mps - before.z_d_dot_mps) <= 0.5 * DT + 1e-9
    assert d.p.rebases == 1
    # the same epoch again does nothing
    again = d.step()
    assert again.z_d_m == pytest.approx(after.z_d_m + after.z_d_dot_mps * DT, abs=2e-4)


def test_constant_rate_profile_flies_a_world_ramp():
    params = PlannerParams(landing_area_m=AREA, descent_profile='constant_rate')
    d = Driver(params)
    d.surface = 0.7
    d.height = 2.0
    d.beacon = (0.0, 0.0)
    d.p.start_landing(0.0)
    d.run(0.55)
    rel = d.out
    assert rel.mode is Mode.DESCEND or d.run(0.1).mode is Mode.DESCEND
    out = d.run(4.0)
    assert out.vertical_mode == 'world_rate'
    assert out.z_d_dot_mps == pytest.approx(-params.constant_rate_mps, abs=1e-9)
    assert out.z_d_m < 2.7                     # world altitude = height + surface at entry


def test_world_frame_switch_keeps_the_rate_continuous():
    params = PlannerParams(landing_area_m=AREA, descent_profile='constant_rate')
    d = Driver(params)
    d.surface = 0.7
    d.beacon = (0.0, 0.0)
    d.p.start_landing(0.0)
    outs = [d.step() for _ in range(200)]
    i = next(k for k, o in enumerate(outs) if o.vertical_mode == 'world_rate')
    a, b = outs[i - 1], outs[i]
    assert b.z_d_m == pytest.approx(a.z_d_m + 0.7 + a.z_d_dot_mps * DT, abs=1e-4)
    assert abs(b.z_d_dot_mps - a.z_d_dot_mps) <= params.vertical_accel_mps2 * DT + 1e-9


def test_abort_climbs_to_approach_height_and_holds_position():
    d = aligned_driver()
    d.run(0.6)
    d.run(2.0)
    assert d.out.mode is Mode.DESCEND
    d.xy = (0.1, -0.1)
    ok, _ = d.p.abort(d.t)
    assert ok
    out = d.run(0.05)
    assert out.mode is Mode.HOLD and 'abort' in out.reason
    assert out.setpoint_m == (0.1, -0.1)
    out = d.run(8.0)
    assert out.z_d_m == pytest.approx(2.0, abs=1e-9)
    assert d.p.start_landing(d.t)[0]


def test_invalid_vertical_state_holds_above_final_height():
    d = aligned_driver()
    d.run(0.6)
    d.run(0.5)
    z0 = d.out.z_d_m
    d.valid = False
    d.run(0.4)
    assert d.out.mode is Mode.DESCEND           # grace period: descent paused
    assert d.out.z_d_m >= z0 - 0.2
    d.run(0.2)
    assert d.out.mode is Mode.HOLD and 'invalid' in d.out.reason
    assert all(map(math.isfinite, (d.out.z_d_m, d.out.z_d_dot_mps, d.out.z_d_ddot_mps2)))


def test_invalid_vertical_state_in_final_falls_back_to_slow_descent():
    d = aligned_driver()
    d.run(0.6)
    d.height = 0.45
    d.run(0.05)
    assert d.out.mode is Mode.FINAL
    d.valid = False
    d.run(0.45)
    assert d.out.mode is Mode.FINAL
    d.run(0.1)
    assert d.out.mode is Mode.FALLBACK
    d.run(1.0)
    assert d.out.z_d_dot_mps < 0.0 and d.out.thrust_enabled


def test_nan_inputs_never_reach_the_output():
    d = aligned_driver()
    d.run(0.6)
    good = d.out
    p = d.p
    nan_vert = make_vertical(math.nan, 0.0)
    apron = make_apron(d.t, AREA, (math.nan, 0.0), nan_vert)
    veh = make_vehicle(d.t, (math.nan, 0.0), math.nan)
    out = p.step(d.t, DT, veh, apron)
    assert p.rejected['nan'] >= 2
    for v in (*out.setpoint_m, *out.velocity_ff_mps, out.z_d_m, out.z_d_dot_mps,
              out.z_d_ddot_mps2, out.yaw_rad):
        assert math.isfinite(v)
    assert out.setpoint_m == good.setpoint_m
    # out-of-order stamp: rejected, last output returned unchanged
    stale = p.step(d.t - 1.0, DT, make_vehicle(d.t - 1.0), make_apron(d.t - 1.0))
    assert stale is out and p.rejected['out_of_order'] == 1
    assert p.step(math.nan, DT, veh, apron) is out
    assert p.step(d.t + DT, 0.0, veh, apron) is out and p.rejected['bad_dt'] == 1


def test_takeoff_from_landed_climbs_then_holds():
    d = Driver(PlannerParams(landing_area_m=AREA), height=0.15)
    d.landed_flag = True
    out = d.step()
    assert out.mode is Mode.IDLE and not out.thrust_enabled
    assert d.p.takeoff(d.t)[0]
    d.landed_flag = False
    zs = []
    for _ in range(800):
        out = d.step()
        zs.append(out.z_d_m)
        d.height = out.z_d_m                     # a perfect vertical loop
        if out.mode is Mode.HOLD:
            break
    assert out.mode is Mode.HOLD and out.reason == 'takeoff complete'
    assert zs[0] == pytest.approx(0.15, abs=1e-4) and out.thrust_enabled


def test_fast_fly_through_the_contact_band_is_not_landed():
    d = aligned_driver()
    d.run(0.6)
    d.height = 0.4
    d.run(0.05)
    d.height, d.closing = 0.18, -0.4            # in the height band but still closing fast
    d.run(1.0)
    assert d.out.mode is Mode.FINAL
    d.closing = -0.25                           # slow: estimator noise on deck is ±0.2 m/s
    d.run(25.0)                                 # reference presses below, then the hold
    assert d.out.mode is Mode.LANDED


def test_heading_is_latched_at_start_and_held():
    p = LandingPlanner(PlannerParams(landing_area_m=AREA))
    p.start_landing(0.0)
    apron = make_apron(0.0)
    out = p.step(0.0, DT, make_vehicle(0.0, yaw=0.7), apron)
    assert out.yaw_rad == 0.7
    out = p.step(DT, DT, make_vehicle(DT, yaw=0.9), make_apron(DT))
    assert out.yaw_rad == 0.7
    bad = make_vehicle(2 * DT, yaw=math.nan)
    assert p.step(2 * DT, DT, bad, make_apron(2 * DT)).yaw_rad == 0.7


def test_idle_does_not_latch_a_hold_height_before_the_first_valid_height():
    """Invalid states before the estimator is up must not become the IDLE hold height."""
    d = Driver(xy=(0.0, 0.0))
    d.valid = False                            # the estimator has not got a height yet
    d.run(0.5)
    d.valid = True                             # now a valid 2.0 m height arrives
    outs = [d.step() for _ in range(200)]
    assert all(o.mode is Mode.IDLE for o in outs)
    assert min(o.z_d_m for o in outs) > 1.95   # holds where it is, does not sink


def _final_at(height, **params):
    """A driver in FINAL whose vehicle followed the reference exactly down to ``height``."""
    d = aligned_driver(**params)
    d.run(0.6)
    d.height = 0.45
    d.step()
    assert d.out.mode is Mode.FINAL
    while d.out.z_d_m > height:
        d.height, d.closing = max(d.out.z_d_m, height), d.out.z_d_dot_mps
        d.step()
    d.height, d.closing = height, 0.0
    return d


def test_final_reference_is_leashed_to_the_measured_height():
    """The vehicle stops following (the deck fell away, the estimate lagged): z_d stays
    within final_leash_m below h, so the altitude law's catch-up Λ·e_z stays bounded, and
    ż_d keeps asking for the final speed (a rate reference, no pause)."""
    d = _final_at(0.35)
    pp = d.p.params
    for _ in range(300):
        d.step()
        assert d.out.z_d_m >= 0.35 - pp.final_leash_m - 1e-9
    assert d.out.mode is Mode.FINAL
    assert d.out.z_d_dot_mps == pytest.approx(-pp.final_speed_mps)
    # following again: descends with the vehicle, never more than the leash below it
    for _ in range(100):
        d.height -= pp.final_speed_mps * DT
        d.step()
        assert d.out.z_d_m >= d.height - pp.final_leash_m - 1e-9


def test_a_noisy_height_does_not_ratchet_the_leash():
    """A vehicle resting 0.35 m above the deck with a height estimate noisy at 1.5 cm (lidar
    noise x3): held to the raw height the 5 mm leash lifts z_d to each noise spike and z_d
    rides the noise's upper envelope, above the vehicle (no descent is ever asked for); held
    to the height low-passed over leash_filter_s it stays below the vehicle, asking for the
    final descent."""
    def mean_reference_above_vehicle(leash_filter_s):
        d = _final_at(0.35, leash_filter_s=leash_filter_s)
        rng = random.Random(7)
        excess = []
        for _ in range(300):
            d.height = 0.35 + rng.gauss(0.0, 0.015)
            d.step()
            excess.append(d.out.z_d_m - 0.35)
        assert d.out.mode is Mode.FINAL
        return sum(excess[100:]) / len(excess[100:])

    assert mean_reference_above_vehicle(1e-6) > 0.01          # the ratchet (raw height)
    assert mean_reference_above_vehicle(PlannerParams().leash_filter_s) < 0.0


def test_leash_only_bounds_the_reference_from_below():
    """A vehicle below the reference (the deck came up at it) is not pulled down: z_d runs
    on at its own rate, the law keeps asking it to climb relative to the deck."""
    d = _final_at(0.35)
    d.height = 0.30
    z0 = d.out.z_d_m
    d.run(0.2)
    pp = d.p.params
    assert d.out.z_d_m == pytest.approx(z0 - 0.2 * pp.final_speed_mps, abs=1e-6)


def test_leash_ignores_a_stale_height():
    """Vertical state invalid: the leash must not pin the reference to the last height."""
    d = _final_at(0.35)
    d.valid = False
    d.run(0.4)                                  # < invalid_timeout_s: still FINAL
    assert d.out.mode is Mode.FINAL
    assert d.out.z_d_m < 0.35 - 2 * d.p.params.final_leash_m


def test_leash_lets_go_on_the_deck_after_the_travel_it_took_back():
    """Resting in the landed band: the leash takes back landed_press − final_leash of asked
    travel, then lets go; LANDED then needs the usual landed_press_m below h and the hold.
    The leash can only delay LANDED, by (landed_press − final_leash) / final_speed."""
    d = _final_at(0.17)
    pp = d.p.params
    v = pp.final_speed_mps
    z0, t0 = d.out.z_d_m, d.t
    took_back = pp.landed_press_m - pp.final_leash_m
    d.run(0.9 * ((z0 - 0.17 + pp.final_leash_m) + took_back) / v)
    assert d.out.z_d_m >= 0.17 - pp.final_leash_m - 1e-9     # still leashed
    d.run(10.0, until=Mode.LANDED)
    assert d.out.mode is Mode.LANDED
    unleashed = (z0 - 0.17 + pp.landed_press_m) / v + pp.landed_hold_s
    assert d.t - t0 == pytest.approx(unleashed + took_back / v, abs=0.03)
