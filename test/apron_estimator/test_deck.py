"""The estimator's moving-deck fusion (apron_estimator.deck): beacon > telemetry > prediction,
the GNSS offset learnt while the beacon is tracked, delayed and lossy telemetry on a real ship
track (ship_ss3), and the path without telemetry (beacon and prediction alone)."""

from __future__ import annotations

import math
import random

from apron_estimator.deck import DeckFusion, DeckFusionParams
from apron_estimator.estimator import ApronEstimator
from apron_estimator.loop import EstimatorLoop
from deck_simulator.scenario import load_scenario
from deck_simulator.ship import ShipMotion
from deck_simulator.ship_link import ShipLink, ShipTelemetryParams
from deckland_common.contract import ApronState, VerticalState
from mavlink_bridge.ship import DeckOdomAssembler, ShipDecodeParams, ShipTelemetryDecoder
import pytest

VEHICLE_BIAS = (0.6, -0.4)     # the vehicle's local-position error: the beacon's frame


def beacon_state(t: float, tracked: bool, pos=(0.0, 0.0), vel=(0.0, 0.0),
                 rel=(0.05, -0.05)) -> ApronState:
    """An estimator output: ``pos``/``vel`` the beacon-derived apron (vehicle + rel); the
    vehicle hovers ``rel`` beside the beacon."""
    z = (0.0, 0.0)
    return ApronState(t, tracked, tracked, 0.0 if tracked else 5.0, rel, z, (1e-4, 1e-4), z, z,
                      pos, vel, VerticalState.invalid())


def ship_track(seed: int = 1):
    sc = load_scenario('ship_ss3')
    assert sc.apron.ship is not None
    return ShipMotion(sc.apron.ship, random.Random(f'{seed}:ship'), 200.0)


def fly(fusion: DeckFusion, ship: ShipMotion, link: ShipLink, beacon_until_s: float,
        telemetry_until_s: float, end_s: float, seed: int = 0, min_latency_s: float = 0.1):
    """100 Hz: the beacon (truth + vehicle bias + 2 cm noise) while t < beacon_until_s, the
    ship's telemetry through the link and the bridge's decode while t < telemetry_until_s.
    Returns [(t, state, truth position in the beacon frame, truth velocity)]."""
    rng = random.Random(seed)
    dec = ShipTelemetryDecoder(ShipDecodeParams(min_latency_s=min_latency_s))
    asm = DeckOdomAssembler()
    out = []
    for k in range(1, round(end_s * 100) + 1):
        t = k * 0.01
        for t_rx, m in link.poll(t):
            s = dec.on_message(t_rx, 17, m)
            o = asm.on_sample(s) if s is not None and t < telemetry_until_s else None
            if o is not None:
                fusion.on_telemetry(o.t_s, o.position_m, o.velocity_mps, o.attitude_valid,
                                    o.rpy_rad, o.yaw_rate_radps, o.rates_flu_radps)
        ps = ship.pad_state(t)
        truth = (ps.position_m[0] + VEHICLE_BIAS[0], ps.position_m[1] + VEHICLE_BIAS[1])
        if t < beacon_until_s:
            pos = (truth[0] + rng.gauss(0.0, 0.02), truth[1] + rng.gauss(0.0, 0.02))
            vel = (ps.velocity_mps[0] + rng.gauss(0.0, 0.05),
                   ps.velocity_mps[1] + rng.gauss(0.0, 0.05))
            st = fusion.fuse(beacon_state(t, True, pos, vel))
        else:
            st = fusion.fuse(beacon_state(t, False))
        out.append((t, st, truth, ps.velocity_mps[:2], ps))
    return out


def test_sources_in_order_and_the_gnss_offset_learnt_on_a_ship():
    """ship_ss3's pad at 2.5 m/s; telemetry at 5/10 Hz, 0.15 s + jitter, 5 % loss, GNSS bias
    ~0.8 m (held nearly constant here, τ 3000 s: the offset's target is then one number).
    Beacon for 30 s, then telemetry only for 30 s, then nothing."""
    ship = ship_track()
    link = ShipLink(ShipTelemetryParams(position_bias_tau_s=3000.0), ship.pad_state,
                    '1:ship_link')
    fusion = DeckFusion()
    # the decoder told the link's true fastest delay: the offset is then the GNSS errors only
    # (with a wrong one it also takes in velocity × the stamp error, as the next tests have)
    rows = fly(fusion, ship, link, beacon_until_s=30.0, telemetry_until_s=60.0, end_s=90.0,
               min_latency_s=0.15)
    by_t = {round(t * 100): (st, truth, v) for t, st, truth, v, _ in rows}
    assert all(by_t[k][0].source == 'beacon' for k in range(100, 3000))
    # the offset: ship GNSS frame → the beacon's frame = vehicle bias − ship GNSS bias
    bx, by, _ = link.position_bias_m
    want = (VEHICLE_BIAS[0] - bx, VEHICLE_BIAS[1] - by)
    assert fusion.offset_samples > 100
    assert math.dist(fusion.offset_m, want) < 0.15, (fusion.offset_m, want)
    # telemetry only: every estimate within 0.35 m of the deck (the offset error, the
    # 0.05 m GNSS noise, the delay the velocity carries over while the ship heaves and sways)
    tel = [by_t[k] for k in range(3010, 6000)]
    assert all(st.source == 'telemetry' for st, _, _ in tel)
    errs = [math.dist(st.apron_position_m, truth) for st, truth, _ in tel]
    assert max(errs) < 0.35 and sum(errs) / len(errs) < 0.2
    verr = [math.dist(st.apron_velocity_mps, v) for st, _, v in tel]
    assert sum(verr) / len(verr) < 0.15
    # the deck's attitude (telemetry only): roll and pitch within 1°, heading within 0.5°
    for st, _, _ in tel[::50]:
        assert st.deck_attitude_valid
    rpy_err = [max(abs(st.deck_rpy_rad[i] - ps.rpy_rad[i]) for i in range(2))
               for t, st, _, _, ps in rows[3010:6000]]
    assert max(rpy_err) < math.radians(1.0)
    yaw_err = [abs(math.remainder(st.deck_rpy_rad[2] - ps.rpy_rad[2], 2 * math.pi))
               for t, st, _, _, ps in rows[3010:6000]]
    assert max(yaw_err) < math.radians(1.0)
    # then the constant-velocity prediction, and after its timeout nothing
    pred = [by_t[k][0] for k in range(6200, 7900)]
    assert all(st.source == 'prediction' for st in pred)
    assert not by_t[7900][0].deck_attitude_valid
    assert by_t[8300][0].source == 'none'
    # 5 s into the prediction: within the ship's speed variation × 5 s
    st, truth, _ = by_t[6500]
    assert math.dist(st.apron_position_m, truth) < 2.0


def test_a_biased_beacon_is_not_what_telemetry_without_the_offset_would_give():
    """Without the learnt offset the telemetry would be off by the combined GNSS errors."""
    ship = ship_track(2)
    link = ShipLink(ShipTelemetryParams(), ship.pad_state, '2:ship_link')
    fusion = DeckFusion()
    rows = fly(fusion, ship, link, beacon_until_s=20.0, telemetry_until_s=40.0, end_s=40.0)
    bx, by, _ = link.position_bias_m
    raw_offset = math.hypot(VEHICLE_BIAS[0] - bx, VEHICLE_BIAS[1] - by)
    errs = [math.dist(st.apron_position_m, truth) for t, st, truth, _, _ in rows if t > 20.1]
    assert raw_offset > 0.5          # the case is not trivial
    assert sum(errs) / len(errs) < 0.4 * raw_offset


def test_telemetry_loss_and_delay_bound_the_error():
    """Heavier loss (30 %), a longer delay (0.4 s + jitter) than the decoder's nominal 0.1 s
    and the default GNSS bias wander (τ 300 s): within 0.7 m for 30 s after the beacon."""
    ship = ship_track(3)
    p = ShipTelemetryParams(loss_probability=0.3, latency_s=0.4, jitter_s=0.1)
    link = ShipLink(p, ship.pad_state, '3:ship_link')
    fusion = DeckFusion()
    rows = fly(fusion, ship, link, beacon_until_s=30.0, telemetry_until_s=60.0, end_s=60.0)
    tel = [(st, truth) for t, st, truth, _, _ in rows if t > 30.1]
    assert all(st.source == 'telemetry' for st, _ in tel)
    errs = [math.dist(st.apron_position_m, truth) for st, truth in tel]
    assert max(errs) < 0.7 and sum(errs) / len(errs) < 0.4


def _barge(fusion, accel=None):
    """10 s of a barge accelerating at 0.3 m/s² east, beacon only; ``accel``: the beacon
    filter's deck acceleration passed along (None: not known)."""
    rng = random.Random(4)
    st = None
    for k in range(1, 1001):
        t = k * 0.01
        pos = (0.15 * t * t + rng.gauss(0.0, 0.02), 1.0 + rng.gauss(0.0, 0.02))
        vel = (0.3 * t + rng.gauss(0.0, 0.05), rng.gauss(0.0, 0.05))
        st = fusion.fuse(beacon_state(t, True, pos, vel), accel)
    return st


def test_the_beacon_filters_deck_acceleration_is_published_and_preferred_to_telemetry():
    """While tracked, the acceleration published is the beacon filter's (D6) when it is
    known, telemetry's otherwise (0 without either); ``beacon_accel`` off: telemetry's."""
    st = _barge(DeckFusion(DeckFusionParams(prediction_timeout_s=10.0)))
    assert st.source == 'beacon' and st.apron_accel_mps2 == (0.0, 0.0)
    assert st.apron_velocity_mps[0] == pytest.approx(3.0, abs=0.2)   # the velocity still is
    st = _barge(DeckFusion(DeckFusionParams(prediction_timeout_s=10.0)), (0.3, -0.02))
    assert st.apron_accel_mps2 == (0.3, -0.02)
    f = DeckFusion(DeckFusionParams(prediction_timeout_s=10.0, accel_tau_s=0.2))
    for k in range(1, 301):                      # telemetry says the deck accelerates north
        t = k * 0.01
        if k % 20 == 0:
            f.on_telemetry(t, (0.0, 0.5 * t * t, 0.0), (0.0, 1.0 * t, 0.0))
        st = f.fuse(beacon_state(t, True), None if k < 250 else (0.3, 0.0))
        if k == 249:
            assert st.apron_accel_mps2[0] == 0.0
            assert st.apron_accel_mps2[1] == pytest.approx(1.0, abs=0.05)
    assert st.apron_accel_mps2 == (0.3, 0.0)
    off = DeckFusion(DeckFusionParams(beacon_accel=False))
    assert _barge(off, (0.3, 0.0)).apron_accel_mps2 == (0.0, 0.0)
    with pytest.raises(ValueError, match='beacon_accel'):
        DeckFusionParams(beacon_accel=1)


def test_without_telemetry_a_lost_beacon_is_predicted_at_constant_velocity():
    """Beacon only: when it is lost the deck is predicted at the last velocity (constant-
    velocity model, no acceleration) for ``prediction_timeout_s``, then nothing."""
    fusion = DeckFusion(DeckFusionParams(prediction_timeout_s=10.0))
    st = _barge(fusion, (0.3, 0.0))
    assert st is not None and st.source == 'beacon' and not st.deck_attitude_valid
    last_pos, last_vel = st.apron_position_m, st.apron_velocity_mps
    p2 = fusion.fuse(beacon_state(12.0, False))
    assert p2.source == 'prediction' and p2.apron_accel_mps2 == (0.0, 0.0)
    assert p2.apron_velocity_mps == last_vel
    assert p2.apron_position_m[0] == pytest.approx(last_pos[0] + last_vel[0] * 2.0)
    assert fusion.fuse(beacon_state(20.5, False)).source == 'none'


def test_the_offset_is_learnt_only_close_above_the_beacon():
    """From beside the deck the beacon's offset is scaled by the wrong height (the sea below):
    2 m away at 2.25x (deck 2.5 m above the water) it is 2.5 m off. Such estimates must not
    teach the offset; once above the beacon they do."""
    f = DeckFusion()
    for k in range(1, 301):                      # 3 s beside: beacon 2.5 m off, 2 m away
        t = k * 0.01
        f.fuse(beacon_state(t, True, (10.0 + 2.5, 0.0), rel=(2.0, 0.0)))
        if k % 10 == 0:
            f.on_telemetry(t - 0.05, (10.0, 0.0, 2.5), (0.0, 0.0, 0.0))
    assert f.offset_samples == 0 and f.offset_m == (0.0, 0.0)
    for k in range(301, 801):                    # 5 s above it: the beacon right, 0.4 m east
        t = k * 0.01
        f.fuse(beacon_state(t, True, (10.4, 0.0), rel=(0.1, 0.0)))
        if k % 10 == 0:
            f.on_telemetry(t - 0.05, (10.0, 0.0, 2.5), (0.0, 0.0, 0.0))
    assert f.offset_samples > 30 and f.offset_m == pytest.approx((0.4, 0.0), abs=1e-6)


def test_bad_telemetry_is_refused_and_the_loop_counts_it():
    loop = EstimatorLoop(ApronEstimator())
    assert loop.on_deck_odom(10.0, 9.5, (1.0, 2.0, 3.0), (0.0, 0.0, 0.0))
    assert not loop.on_deck_odom(10.0, 9.4, (1.0, 2.0, 3.0), (0.0, 0.0, 0.0))    # older
    assert not loop.on_deck_odom(10.0, 9.6, (math.nan, 2.0, 3.0), (0.0, 0.0, 0.0))
    assert not loop.on_deck_odom(10.0, 11.0, (1.0, 2.0, 3.0), (0.0, 0.0, 0.0))   # future
    assert loop.rejected['out_of_order'] == 1 and loop.rejected['non_finite'] == 1
    assert loop.rejected['future_stamp'] == 1
    assert loop.deck.rejected['out_of_order'] == 1 and loop.deck.rejected['non_finite'] == 1
    # a telemetry sample 1.2 s old is still the deck (the timeout is 1.5 s), 2 s is not
    f = DeckFusion()
    f.on_telemetry(0.0, (5.0, 0.0, 0.0), (1.0, 0.0, 0.0))
    s = f.fuse(beacon_state(1.2, False))
    assert s.source == 'telemetry' and s.apron_position_m[0] == pytest.approx(6.2)
    assert f.fuse(beacon_state(2.0, False)).source == 'prediction'


def test_a_new_beacon_track_starts_from_the_telemetry_velocity_while_it_is_fresh():
    """The loop hands the estimator the ship's velocity as the prior of a new track (README
    D7); without fresh telemetry the deck is assumed at rest."""
    loop = EstimatorLoop(ApronEstimator())
    priors = []
    loop.estimator.on_camera = lambda t, blocks, deck_v: priors.append(deck_v)
    assert loop.on_deck_odom(10.0, 10.0, (5.0, 0.0, 0.0), (2.0, 0.5, 0.0))
    loop.on_camera(10.2, 10.1, [])
    assert priors[-1] == pytest.approx((2.0, 0.5))
    loop.on_camera(12.0, 12.0, [])      # the telemetry is 2 s old: timed out (1.5 s)
    assert priors[-1] == (0.0, 0.0)
