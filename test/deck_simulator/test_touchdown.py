"""Touchdown monitor: the landing record and the outcome rules over the whole contact sequence.

Landings are flown with motors off on the contact cores (tests/test_sim_contact.Rig): the
first-contact figures against the set-up speeds, bounces against the restitution, and every
rule a pilot would call a failure against a case that breaks it.
"""

from __future__ import annotations

import dataclasses
import math

from contact_rig import DT, G, Rig, bounce_apex_m
from deck_simulator.contact import ContactParams, Surface
from deck_simulator.rigid_body import RigidBodyParams
from deck_simulator.touchdown import OutcomeRules, Pad, TouchdownMonitor
import pytest

TOP_M = 0.6


def apron(mu=0.6, half=(0.525, 0.425)):
    """The paper's apron (1.05 × 0.85 m, Table 3 / paper.yaml) raised 0.6 m on its actuators."""
    s = Surface('deck', half[0], half[1], TOP_M, mu)
    s.set_pose((0.0, 0.0, TOP_M), (0.0, 0.0, 1.0), (1.0, 0.0, 0.0))
    return s


def land(velocity=(0.0, 0.0, -0.3), rpy=(0.0, 0.0, 0.0), xy=(0.0, 0.0), gap_m=0.002,
         seconds=2.5, rules=None, deck=None, pad=None, armed=False, mu=0.6, deck_motion=None,
         over_deck=True):
    deck = deck or apron(mu)
    rig = Rig(deck=deck, params=ContactParams(friction_deck=mu))
    rig.place(rpy=rpy, velocity=velocity, xy=xy, gap_m=gap_m,
              surface=deck if over_deck else None)
    mon = TouchdownMonitor(rules or OutcomeRules(), rig.contact, pad or Pad(),
                           rig.gear.static_tip_angle_rad())
    rig.run(seconds, deck_motion=deck_motion, monitor=mon, armed=armed)
    return mon.record(rig.body), mon, rig


def test_gentle_landing_is_a_success_with_its_first_contact_figures():
    rec, mon, _ = land(velocity=(0.1, 0.0, -0.3))
    assert rec.outcome == 'deck' and rec.success and not rec.crash
    assert rec.contact_kind == 'pad'
    f = rec.first
    # seen before the contact force acts, at the first sub-step below the surface (up to
    # v h = 0.2 mm further down): the speeds of the fall
    assert f.normal_speed_mps == pytest.approx(math.sqrt(0.3 ** 2 + 2 * G * 0.002), rel=0.01)
    assert f.lateral_speed_mps == pytest.approx(0.1, rel=1e-9)
    assert f.tilt_rad < 1e-9
    assert rec.bounces == 0 and len(rec.impacts) == 1
    assert rec.settled and mon.done and rec.settled_t_s < 1.6   # 1 s still after the impact
    assert rec.feet_on_pad and not (rec.tipped or rec.edge_strike or rec.prop_strike)
    assert rec.reasons == ('landed on the pad',)


def test_feet_positions_include_yaw():
    rec, _, _ = land(rpy=(0.0, 0.0, math.radians(45.0)), xy=(0.1, -0.05))
    assert rec.yaw_rel_rad == pytest.approx(math.radians(45.0), abs=1e-6)
    r = 0.2 * math.sqrt(2.0)
    expected = sorted((round(0.1 + r * math.cos(a), 3), round(-0.05 + r * math.sin(a), 3))
                      for a in (0.0, math.pi / 2, math.pi, -math.pi / 2))
    assert sorted((round(a, 3), round(b, 3)) for a, b in rec.feet_pad_m) == expected
    assert rec.feet_on_pad and rec.success


def test_impact_above_the_crash_speed_is_a_crash():
    rec, mon, _ = land(velocity=(0.0, 0.0, -1.3), seconds=1.0)
    assert rec.outcome == 'crash' and rec.crash and not rec.success
    assert mon.done
    assert rec.first.normal_speed_mps == pytest.approx(math.hypot(1.3, math.sqrt(2 * G * 0.002)),
                                                       rel=0.01)
    assert any(r.startswith('impact 1.3') and '> 1.00' in r for r in rec.reasons)


def test_bounce_counted_with_its_height():
    # a 10 cm drop (1.4 m/s, crash speed raised): a first hop of ≈ 20 mm (the closed form
    # with gravity), then ≈ 4 mm (< 1 cm: not a bounce)
    rules = OutcomeRules(crash_speed_mps=3.0)
    rec, _, _ = land(velocity=(0.0, 0.0, 0.0), gap_m=0.1, seconds=3.0, rules=rules)
    assert rec.bounces == 1
    hop = bounce_apex_m(ContactParams(), RigidBodyParams(), math.sqrt(2 * G * 0.1))
    assert rec.max_bounce_height_m == pytest.approx(hop, rel=0.06)
    assert len(rec.impacts) >= 2 and rec.impacts[1].after_bounce_m == rec.max_bounce_height_m
    assert rec.success                   # bounces are reported, not failed, by default
    strict = land(velocity=(0.0, 0.0, 0.0), gap_m=0.1, seconds=3.0,
                  rules=dataclasses.replace(rules, max_bounce_height_m=0.01))[0]
    assert strict.outcome == 'failed' and any(r.startswith('bounce') for r in strict.reasons)


@pytest.mark.parametrize('lateral, ok', [(0.3, True), (0.7, False)])
def test_lateral_speed_rule(lateral, ok):
    rec, _, _ = land(velocity=(lateral, 0.0, -0.3), xy=(-0.2, 0.0))
    assert rec.first.lateral_speed_mps == pytest.approx(lateral, rel=1e-9)
    assert rec.success is ok
    if not ok:
        assert rec.outcome == 'failed' and any('lateral' in r for r in rec.reasons)


def test_tilted_touchdown_fails_the_tilt_rule():
    rec, _, _ = land(rpy=(math.radians(15.0), 0.0, 0.0))
    assert rec.first.tilt_rad == pytest.approx(math.radians(15.0), abs=1e-3)
    assert rec.outcome == 'failed' and any(r.startswith('tilt 15') for r in rec.reasons)


def test_foot_over_the_edge_is_never_a_success():
    # centre of mass on the pad, front feet beyond its edge: it tips over the edge
    rec, _, _ = land(xy=(0.43, 0.0), seconds=2.0)
    assert not rec.success and rec.outcome == 'crash'
    assert rec.tipped or rec.edge_strike or rec.left_deck


def test_slid_over_the_edge_of_a_flush_pad():
    # a ship deck (large, flush) with a 1.0 × 0.8 m pad marked on it; slippery: slides off
    deck = apron(mu=0.05, half=(5.0, 5.0))
    pad = Pad(surface_index=0, half_u_m=0.5, half_w_m=0.4)
    # 0.45 m/s (under the lateral limit), μ g = 0.49 m/s²: slides 0.21 m, the front feet
    # from 0.35 to ≈ 0.56 m, over the pad's edge at 0.5 m
    rec, _, _ = land(velocity=(0.45, 0.0, -0.2), xy=(0.15, 0.0), deck=deck, pad=pad,
                     mu=0.05, seconds=3.0)
    assert rec.contact_kind == 'pad'
    assert rec.slid_off_pad and not rec.feet_on_pad
    assert rec.outcome == 'failed' and 'slid over the pad edge' in rec.reasons
    assert 'a foot off the pad' in rec.reasons


def test_sliding_off_a_raised_apron_is_a_crash():
    rec, _, _ = land(velocity=(0.45, 0.0, -0.2), xy=(0.25, 0.0), mu=0.05, seconds=3.0)
    assert rec.outcome == 'crash'
    assert rec.left_deck or rec.tipped


def test_edge_strike():
    rec, mon, _ = land(velocity=(1.5, 0.0, 0.0), xy=(-0.9, 0.0), gap_m=0.3, seconds=1.0,
                       over_deck=False)
    assert rec.edge_strike and rec.outcome == 'crash' and mon.done
    assert rec.contact_kind in ('edge', 'hull')


def test_landing_on_the_ground_is_a_fallback():
    rec, _, _ = land(xy=(2.0, 0.0), over_deck=False)
    assert rec.contact_kind == 'ground' and rec.outcome == 'fallback' and not rec.success


def test_armed_vehicle_never_settles():
    rec, mon, _ = land(armed=True)
    assert not rec.settled and not mon.done
    assert rec.outcome == 'failed' and 'not settled' in rec.reasons


def test_no_contact_record():
    rec, mon, _ = land(gap_m=0.5, seconds=0.1)
    assert rec.contact_kind == 'none' and rec.first is None and rec.outcome == 'none'
    assert not mon.done and not mon.in_contact


def test_resting_on_the_papers_heaving_apron_is_no_bounce():
    # Table 3: 300 mm stroke at 90 mm/s, reversing instantly (a 0.18 m/s relative step)
    deck = apron()
    stroke, speed = 0.30, 0.09
    period = 2 * stroke / speed

    def motion(t):
        s = (t / period + 0.25) % 1.0
        if s < 0.5:
            z, vz = -stroke / 2 + speed * s * period, speed
        else:
            z, vz = stroke / 2 - speed * (s - 0.5) * period, -speed
        deck.set_pose((0.0, 0.0, TOP_M + z), (0.0, 0.0, 1.0), (1.0, 0.0, 0.0), (0.0, 0.0, vz))

    motion(0.0)
    rec, _, rig = land(deck=deck, deck_motion=motion, gap_m=0.0, velocity=(0.0, 0.0, deck.vz),
                       seconds=8.0)
    assert rec.bounces == 0 and rec.success and rec.settled
    for imp in rec.impacts[1:]:        # the re-touches after a reversal: small and harmless
        assert imp.normal_speed_mps <= 2 * speed + 0.01
    assert rig.body.z > deck.cz


def test_powered_descent_touches_down_then_disarms_and_settles():
    # motors keep pushing (a PD on the descent rate at 0.3 m/s) until the vehicle has been
    # on its gear for 0.5 s, then disarm: thrust 0
    deck = apron()
    rig = Rig(deck=deck)
    rig.place(gap_m=0.3, surface=deck)
    mon = TouchdownMonitor(OutcomeRules(), rig.contact, Pad(), rig.gear.static_tip_angle_rad())
    m = rig.bp.mass_kg
    state = {'down_since': None}

    def armed(r):
        return state['down_since'] is None or r.t - state['down_since'] < 0.5

    def motors(r):
        if mon.in_contact and state['down_since'] is None:
            state['down_since'] = r.t
        if not armed(r):
            return (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        thrust = m * (G + 4.0 * (-0.3 - r.body.vz))
        return (r.body.r02 * thrust, r.body.r12 * thrust, r.body.r22 * thrust, 0.0, 0.0, 0.0)

    rig.run(3.5, monitor=mon, armed=armed, wrench=motors)
    rec = mon.record(rig.body)
    assert rec.first.normal_speed_mps == pytest.approx(0.3, abs=0.02)
    assert rec.success and rec.settled and rec.bounces == 0
    # settled 1 s after the disarm, resting at the static deflection m g / k
    assert rec.settled_t_s == pytest.approx(state['down_since'] + 0.5 + 1.0, abs=0.2)
    assert rig.lowest_gear_height(deck) == pytest.approx(
        -m * G / rig.cp.stiffness_n_per_m, rel=0.02)


def test_outcome_rules_rejected_by_name():
    with pytest.raises(ValueError, match='crash_speed_mps'):
        OutcomeRules(crash_speed_mps=0.0)
    with pytest.raises(ValueError, match='max_tilt_rad'):
        OutcomeRules(max_tilt_rad=2.0)
    assert DT == 1.0 / 400.0
