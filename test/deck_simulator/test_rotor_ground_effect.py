"""Partial ground effect per rotor against the published multirotor model.

Sanchez-Cuevas, Heredia, Ollero 2017 (level quadrotor over a plane) is the reference; the
per-rotor generalisation must reduce to it, to Cheeseman–Bennett for one rotor, measure
heights perpendicular to a tilted deck, and give only the rotors over the pad a gain.
"""

from __future__ import annotations

import math

from deck_simulator.contact import Surface, ground_surface
from deck_simulator.rigid_body import RigidBody, RigidBodyParams
from deck_simulator.rotor_ground_effect import (
    RotorGroundEffect,
    RotorGroundEffectParams,
    multirotor_gain_level,
)
from dob_altitude.ground_effect import ground_effect_gain
import pytest

R, L, HR = 0.127, 0.225, 0.05          # paper Table 2: prop radius, arm, rotor plane height
ROTORS = ((L, 0.0, HR), (0.0, L, HR), (-L, 0.0, HR), (0.0, -L, HR))   # plus: 1 nose, 2 left
CENTRE = (0.0, 0.0, HR)


def model(kb=2.0, **kw):
    return RotorGroundEffect(RotorGroundEffectParams(body_coeff=kb, **kw), ROTORS, CENTRE)


def body_at(z_origin, rpy=(0.0, 0.0, 0.0), xy=(0.0, 0.0)):
    return RigidBody(RigidBodyParams(), (xy[0], xy[1], z_origin), rpy)


@pytest.mark.parametrize('zp', [0.15, 0.2, 0.3, 0.5, 1.0, 2.0])
@pytest.mark.parametrize('kb', [0.0, 2.0])
def test_level_quadrotor_reproduces_the_published_formula(zp, kb):
    ge = model(kb)
    ge.update(body_at(zp - HR), [ground_surface(0.6)])
    # d: adjacent-rotor spacing √2 L; b: rotor to centre L
    expected = multirotor_gain_level(zp, R, math.sqrt(2.0) * L, L, kb)
    for i in range(4):
        assert ge.height_m[i] == pytest.approx(zp, abs=1e-12)
        assert ge.gain[i] == pytest.approx(min(expected, 1.5), rel=1e-12)


def test_published_values_by_hand():
    # z = 0.2 m (at contact): own 0.02520, 2 neighbours 0.02416, diagonal 0.00739,
    # body (K_b = 2) 0.13347 → γ = 1 / (1 − 0.19022) = 1.2349
    assert multirotor_gain_level(0.2, R, math.sqrt(2) * L, L, 2.0) == pytest.approx(
        1.2349, abs=1e-4)
    # today's single γ of (4) with ρ = 1.4 at the same height: 1.0366
    assert ground_effect_gain(1.4, R, 0.2) == pytest.approx(1.0366, abs=1e-4)


def test_one_rotor_without_body_is_cheeseman_bennett():
    ge = RotorGroundEffect(RotorGroundEffectParams(body_coeff=0.0), ((0.0, 0.0, 0.0),))
    for z in (0.1, 0.2, 0.5, 1.0):
        ge.update(body_at(z), [ground_surface(0.6)])
        assert ge.gain[0] == pytest.approx(ground_effect_gain(1.0, R, z, 0.05, 1.5), rel=1e-12)


def test_heights_are_perpendicular_to_a_tilted_deck():
    th = math.radians(10.0)
    deck = Surface('deck', 3.0, 3.0, 1.0, 0.6)
    deck.set_pose((0.0, 0.0, 1.0), (0.0, -math.sin(th), math.cos(th)), (1.0, 0.0, 0.0))
    # vehicle parallel to the deck, rotor plane 0.25 m from it along its normal
    zp = 0.25
    b = body_at(0.0, rpy=(th, 0.0, 0.0))
    off = zp - HR
    b.x, b.y, b.z = off * deck.nx, off * deck.ny, 1.0 + off * deck.nz
    ge = model()
    ge.update(b, [deck, ground_surface(0.6)])
    expected = multirotor_gain_level(zp, R, math.sqrt(2) * L, L, 2.0)
    for i in range(4):
        assert ge.surface_index[i] == 0
        assert ge.height_m[i] == pytest.approx(zp, abs=1e-12)
        assert ge.gain[i] == pytest.approx(expected, rel=1e-9)


def test_partial_ground_effect_only_rotors_over_the_pad_gain_and_it_pitches_away():
    # the pad's edge between the nose rotor and the others: rotor 1 over the pad top,
    # rotors 2, 3, 4 over the ground 0.8 m further down
    deck = Surface('deck', 0.5, 0.5, 0.8, 0.6)
    deck.set_pose((0.5 + 0.1, 0.0, 0.8), (0.0, 0.0, 1.0), (1.0, 0.0, 0.0))
    ge = model()
    ge.update(body_at(0.8 + 0.15), [deck, ground_surface(0.6)])
    assert ge.surface_index == [0, 1, 1, 1]
    over = ge.gain[0]
    assert over > 1.02
    for i in (1, 2, 3):
        assert 1.0 < ge.gain[i] < 1.02 < over
    # alone over the pad, the nose rotor gets its own image only (+ nothing from the others)
    assert over == pytest.approx(ground_effect_gain(1.0, R, 0.2, 0.05, 1.5), rel=1e-12)
    # thrust F per motor: (1) u_θ = L (T3 − T1) < 0 — the nose is pushed up, away from the pad
    u_theta = L * (ge.gain[2] - ge.gain[0])
    assert u_theta < 0.0


def test_clamped_near_contact_and_far_from_everything():
    ge = model(kb=2.0)
    ge.update(body_at(0.0), [ground_surface(0.6)])       # rotor plane 5 cm: the clamp
    assert ge.height_m == [0.05] * 4
    assert ge.gain == [1.5] * 4
    deck = Surface('deck', 0.5, 0.5, 0.8, 0.6)
    deck.set_pose((10.0, 0.0, 0.8), (0.0, 0.0, 1.0), (1.0, 0.0, 0.0))
    ge.update(body_at(50.0), [deck])                     # no surface below any rotor
    assert ge.gain == [1.0] * 4 and ge.surface_index == [-1] * 4


def test_params_rejected_by_name():
    with pytest.raises(ValueError, match='body_coeff'):
        RotorGroundEffectParams(body_coeff=-1.0)
    with pytest.raises(ValueError, match='max_gain'):
        RotorGroundEffectParams(max_gain=0.5)


def test_far_from_every_surface_the_gains_are_held_between_updates():
    ge = model(far_update_every=8, full_rate_below_m=0.6)
    ground = [ground_surface(0.6)]
    ge.update(body_at(1.0), ground)                 # all rotors 1.05 m up: held 7 calls
    far = ge.gain[0]
    assert far == pytest.approx(multirotor_gain_level(1.05, R, math.sqrt(2) * L, L, 2.0))
    for _ in range(7):
        ge.update(body_at(0.3), ground)
        assert ge.gain[0] == far
    ge.update(body_at(0.3), ground)                 # the 8th call: near, full rate again
    near = multirotor_gain_level(0.35, R, math.sqrt(2) * L, L, 2.0)
    assert ge.gain[0] == pytest.approx(near, rel=1e-12)
    ge.update(body_at(0.2), ground)
    assert ge.gain[0] == pytest.approx(multirotor_gain_level(0.25, R, math.sqrt(2) * L, L,
                                                             2.0), rel=1e-12)
