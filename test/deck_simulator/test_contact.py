"""Contact as physics against analytic cases: rigid body, gear contact, friction, tip-over.

The free rigid body (deck_simulator.rigid_body) against Newton–Euler invariants; the gear
contact (deck_simulator.contact) against the spring–damper's closed-form restitution, the
friction angle, the static stability angle, energy and a heaving / rolling deck.
"""

from __future__ import annotations

import math
import random

from contact_rig import DT, G, Rig, bounce_apex_m, tilt_of, tilted_plane
from deck_simulator.contact import (
    ContactParams,
    GearGeometry,
    Surface,
    damping_ratio_for,
    restitution_of,
)
from deck_simulator.rigid_body import RigidBody, RigidBodyParams
from deckland_common.frames import rot_body_to_world
import pytest

# --- rigid body ----------------------------------------------------------------------------------

def test_rotation_matches_frames_convention():
    rng = random.Random('contact:rotation')
    bp = RigidBodyParams()
    for _ in range(200):
        rpy = (rng.uniform(-3, 3), rng.uniform(-1.5, 1.5), rng.uniform(-3, 3))
        b = RigidBody(bp, attitude_rpy_rad=rpy)
        r = rot_body_to_world(*rpy)
        back = rot_body_to_world(*b.euler())
        for i in range(3):
            assert b.rotation()[i] == pytest.approx(r[i], abs=1e-12)
            assert back[i] == pytest.approx(r[i], abs=1e-9)


def test_free_body_follows_newton_and_euler():
    bp = RigidBodyParams()
    jy = bp.inertia_kgm2[1]
    # constant force and torque about a principal axis from rest: v = F t / m − g t, ω = τ t / J
    b = RigidBody(bp)
    for _ in range(400):
        b.step(DT, 3.0, 0.0, 0.0, 0.0, 0.02, 0.0)
    assert b.vx == pytest.approx(3.0 / bp.mass_kg, rel=1e-12)
    assert b.vz == pytest.approx(-G, rel=1e-12)
    assert b.q == pytest.approx(0.02 / jy, rel=1e-12) and b.p == 0.0 and b.r == 0.0
    # pitch angle after 1 s of constant α: θ = α t² / 2 (semi-implicit: + α h t / 2)
    alpha = 0.02 / jy
    assert b.euler()[1] == pytest.approx(0.5 * alpha * (1.0 + DT), rel=1e-9)


def test_torque_free_tumble_conserves_momentum_and_never_gains_energy():
    # spin near the intermediate axis: it tumbles, yet L (world) is constant and E ≤ E0
    # (Jy < Jx < Jz: x is the intermediate axis)
    b = RigidBody(RigidBodyParams(gravity_mps2=0.0), rates_radps=(3.0, 0.1, 0.1))

    def momentum():
        r = b.rotation()
        lb = (b.jx * b.p, b.jy * b.q, b.jz * b.r)
        return [sum(r[i][k] * lb[k] for k in range(3)) for i in range(3)]

    l0, e0 = momentum(), b.energy_j()
    flipped = False
    for _ in range(4000):
        b.step(DT, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        assert b.energy_j() <= e0 * (1.0 + 1e-12)
        flipped = flipped or b.p < 0.0
    assert flipped                       # the intermediate-axis flip happened
    l1 = momentum()
    # the implicit gyroscopic step dissipates O(h): 0.16 % of |L| in 10 s of tumbling at 3 rad/s
    assert math.dist(l0, l1) < 5e-3 * math.hypot(*l0)
    assert b.energy_j() > 0.995 * e0
    assert b.qw ** 2 + b.qx ** 2 + b.qy ** 2 + b.qz ** 2 == pytest.approx(1.0, abs=1e-12)


@pytest.mark.parametrize('kwargs, field', [
    ({'mass_kg': 0.0}, 'mass_kg'), ({'inertia_kgm2': (0.01, 0.01)}, 'inertia_kgm2'),
    ({'inertia_kgm2': (0.1, 0.01, 0.01)}, 'inertia_kgm2'), ({'gravity_mps2': -1.0}, 'gravity'),
])
def test_rigid_body_params_rejected_by_name(kwargs, field):
    with pytest.raises(ValueError, match=field):
        RigidBodyParams(**kwargs)


@pytest.mark.parametrize('kwargs, field', [
    ({'stiffness_n_per_m': 0.0}, 'stiffness'), ({'restitution': 1.0}, 'restitution'),
    ({'friction_deck': -0.1}, 'friction_deck'), ({'max_omega_h': 3.0}, 'max_omega_h'),
])
def test_contact_params_rejected_by_name(kwargs, field):
    with pytest.raises(ValueError, match=field):
        ContactParams(**kwargs)
    with pytest.raises(ValueError, match=r'gear\.kind'):
        GearGeometry(kind='wheels')


# --- normal force: restitution -------------------------------------------------------------------

def test_restitution_formula_limits_and_inverse():
    assert restitution_of(0.0) == pytest.approx(1.0, abs=1e-12)
    es = [restitution_of(z) for z in (0.05, 0.2, 0.4, 0.6, 0.8)]
    assert es == sorted(es, reverse=True)
    # the no-pull model bounces more than the textbook e = exp(−πζ/√(1−ζ²)) (which lets the
    # damper pull at the end of the contact)
    z = 0.3
    assert restitution_of(z) > math.exp(-math.pi * z / math.sqrt(1 - z * z))
    for e in (0.2, 0.5, 0.8):
        assert restitution_of(damping_ratio_for(e)) == pytest.approx(e, abs=1e-9)


@pytest.mark.parametrize('e, v0, k', [(0.5, 1.0, 4e4), (0.5, 0.3, 4e4), (0.3, 1.0, 4e4),
                                      (0.8, 2.0, 1e5)])
@pytest.mark.parametrize('finer', [1, 16])
def test_flat_drop_rebounds_at_restitution_without_gravity(e, v0, k, finer):
    # four feet in parallel on a rigid body: the vertical mode is the 1-DOF spring–damper,
    # e independent of v0 and k. Error O(h) from where in a step contact begins: within
    # 2.5 % at the default sub-step (measured over random phases: −2.3 … +1.5 %), 16× finer
    # within 0.4 %
    cp = ContactParams(stiffness_n_per_m=k, restitution=e,
                       max_omega_h=ContactParams().max_omega_h / finer)
    rig = Rig(gravity=0.0, params=cp)
    rig.place(velocity=(0.0, 0.0, -v0), gap_m=0.37 * v0 * DT)
    rig.run(0.1)
    assert sum(rig.contact.n_gear_contacts) == 0
    assert rig.body.vz == pytest.approx(e * v0, rel=0.025 if finer == 1 else 0.004)
    assert abs(rig.body.vx) < 1e-12 and abs(rig.body.p) < 1e-9




def test_dropped_vehicle_bounces_to_the_height_of_its_restitution_with_gravity():
    cp = ContactParams()
    bp = RigidBodyParams()
    h0 = 0.10
    apex = bounce_apex_m(cp, bp, math.sqrt(2 * G * h0))
    rig = Rig(params=ContactParams(max_omega_h=cp.max_omega_h / 8))   # e error < 0.5 %
    rig.place(gap_m=h0)
    best = [0.0, False]

    def watch(r):
        if sum(r.contact.n_gear_contacts):
            best[1] = True
        elif best[1]:
            best[0] = max(best[0], r.lowest_gear_height())

    rig.run(0.25, every=watch)
    # gravity acting through the ~25 ms contact costs height: e² h0 = 25 mm, here ~20 mm
    assert 0.7 * cp.restitution ** 2 * h0 < apex < cp.restitution ** 2 * h0
    assert best[0] == pytest.approx(apex, rel=0.03)


def test_contact_substep_is_set_by_the_stiffness():
    rig = Rig()
    n = rig.contact.substeps(DT)
    assert n == 4                                      # measured choice, docs/world/contact.md
    assert rig.contact.omega_max * DT / n <= rig.cp.max_omega_h
    stiff = Rig(params=ContactParams(stiffness_n_per_m=1.6e5))
    assert stiff.contact.substeps(DT) == 2 * n         # ω ∝ √k
    # resting (every touching point slower than 2 cm/s): half as many; an impact: all again
    rig.place(velocity=(0.0, 0.0, -0.5), gap_m=0.0005)
    rig.run(0.01)
    assert rig.contact.n_active == 4 and rig.contact.substeps(DT) == n
    rig.run(1.0)
    assert rig.contact.max_speed_mps < 0.02 and rig.contact.substeps(DT) == n // 2
    rig.body.vz = -0.3
    rig.run(DT)
    assert rig.contact.substeps(DT) == n


# --- friction ------------------------------------------------------------------------------------

@pytest.mark.parametrize('theta_deg', [10.0, 25.0, 30.0])
def test_vehicle_at_rest_on_a_slope_below_the_friction_angle_holds(theta_deg):
    mu = 0.6                                     # friction angle atan(0.6) = 30.96°
    deck = tilted_plane(math.radians(theta_deg), mu)
    rig = Rig(deck=deck, ground=False, params=ContactParams(friction_deck=mu))
    rig.place(surface=deck, yaw_on_surface=0.3)
    rig.run(0.5)                                 # settle the springs
    a0, b0, _ = deck.local(rig.body.x, rig.body.y, rig.body.z)
    rig.run(3.0)
    a1, b1, _ = deck.local(rig.body.x, rig.body.y, rig.body.z)
    assert math.hypot(a1 - a0, b1 - b0) < 1e-6                 # no creep
    assert math.hypot(rig.body.vx, rig.body.vy) < 1e-6
    assert sum(rig.contact.n_gear_contacts) == 4


@pytest.mark.parametrize('theta_deg, mu', [(40.0, 0.6), (20.0, 0.2), (35.0, 0.0)])
def test_vehicle_above_the_friction_angle_slides_at_g_sin_minus_mu_cos(theta_deg, mu):
    th = math.radians(theta_deg)
    deck = tilted_plane(th, mu)
    rig = Rig(deck=deck, ground=False, params=ContactParams(friction_deck=mu))
    rig.place(surface=deck, yaw_on_surface=0.0)
    rig.run(0.5)

    def downhill_speed():
        # along −w (w = n × u points uphill for this plane)
        b = rig.body
        return -(b.vx * deck.wx + b.vy * deck.wy + b.vz * deck.wz)

    v0 = downhill_speed()
    rig.run(1.0)
    a = downhill_speed() - v0
    assert a == pytest.approx(G * (math.sin(th) - mu * math.cos(th)), rel=0.01)
    assert tilt_of(rig.body, deck) < math.radians(2.0)    # slides upright, does not tip
    assert sum(rig.contact.n_gear_contacts) == 4


# --- tip-over ------------------------------------------------------------------------------------

@pytest.mark.parametrize('margin_deg, tips', [(-1.0, False), (1.0, True)])
def test_tip_over_at_the_static_stability_limit(margin_deg, tips):
    # the gear alone (no prop tips): balanced on the two right (−y) feet at the limit
    # atan(half-width / gear height) = 53.13°
    rig = Rig(hull=())
    limit = rig.gear.static_tip_angle_rad()
    assert limit == pytest.approx(math.atan2(0.2, 0.15), abs=1e-12)
    rig.place(rpy=(limit + math.radians(margin_deg), 0.0, 0.0))
    rig.run(3.0)
    tilt = tilt_of(rig.body, rig.surfaces[-1])
    if tips:
        assert tilt > math.radians(100.0)       # over its side (no props to stop it)
    else:
        assert tilt < math.radians(1.0)
        assert sum(rig.contact.n_gear_contacts) == 4


def test_props_strike_before_the_gear_tips():
    # 10-inch props on 0.225 m arms reach 0.352 m: at roll atan(0.2/0.152) = 52.8° < 53.13°
    # the right prop tip touches the ground first (a prop strike, never a quiet tip)
    seen = [False]

    def watch(r):
        seen[0] = seen[0] or r.contact.hull_contact

    rig = Rig()
    rig.place(rpy=(math.radians(51.0), 0.0, 0.0))
    rig.run(0.05, every=watch)
    assert not seen[0]
    rig.place(rpy=(math.radians(53.1), 0.0, 0.0))
    rig.run(0.05, every=watch)
    assert seen[0]


# --- energy --------------------------------------------------------------------------------------

@pytest.mark.parametrize('case', ['flat', 'spin', 'skid', 'edge', 'tumble'])
def test_contact_never_creates_energy(case):
    deck = None
    if case == 'edge':      # a raised pad: strike its side while moving sideways
        deck = Surface('deck', 0.5, 0.4, 0.6, 0.6)
        deck.set_pose((0.0, 0.0, 0.6), (0.0, 0.0, 1.0), (1.0, 0.0, 0.0))
    rig = Rig(deck=deck)
    if case == 'flat':
        rig.place(velocity=(0.0, 0.0, -1.5), gap_m=0.01)
    elif case == 'spin':
        rig.place(rpy=(0.3, -0.2, 1.0), velocity=(0.2, -0.4, -1.0), rates=(2.0, -3.0, 4.0),
                  gap_m=0.01)
    elif case == 'skid':
        rig.place(velocity=(2.0, 0.5, -0.3), gap_m=0.001)
    elif case == 'edge':
        rig.place(xy=(-0.9, 0.0), velocity=(1.5, 0.0, 0.0), gap_m=0.45)
    else:
        rig.place(rpy=(1.2, 0.0, 0.0), rates=(6.0, 1.0, 0.0), velocity=(0, 0, -2.0),
                  gap_m=0.05)
    e0 = rig.energy()
    worst = [-math.inf]

    def check(r):
        worst[0] = max(worst[0], r.energy() - e0)

    rig.run(1.0, every=check)
    assert worst[0] <= 1e-9 * abs(e0) + 1e-9
    assert rig.energy() < e0                      # and contact dissipates


# --- moving deck ---------------------------------------------------------------------------------

def test_vehicle_resting_on_a_heaving_deck_stays_on_it():
    deck = Surface('deck', 0.525, 0.425, 0.6, 0.6)
    amp, period = 0.15, 4.0           # |a| max = A ω² = 0.37 m/s² < g
    w = 2 * math.pi / period

    def motion(t):
        deck.set_pose((0.0, 0.0, 0.6 + amp * math.sin(w * t)), (0.0, 0.0, 1.0),
                      (1.0, 0.0, 0.0), (0.0, 0.0, amp * w * math.cos(w * t)))

    motion(0.0)
    rig = Rig(deck=deck)
    rig.place(surface=deck)
    worst = [0.0, 0.0]

    def watch(r):
        worst[0] = max(worst[0], r.lowest_gear_height(deck))
        a, b, _ = deck.local(r.body.x, r.body.y, r.body.z)
        worst[1] = max(worst[1], math.hypot(a, b))
        assert sum(r.contact.n_gear_contacts) == 4

    rig.run(8.0, deck_motion=motion, every=watch)
    assert worst[0] < 1e-3 and worst[1] < 1e-4


def test_vehicle_resting_on_a_rolling_deck_moves_with_it():
    # a ship-like pad rolling ±6° at 8 s about an axis 2 m below it: the pad swings sideways
    deck = Surface('deck', 2.0, 2.0, 1.0, 0.6)
    amp, period, arm = math.radians(6.0), 8.0, 2.0
    w = 2 * math.pi / period

    def motion(t):
        phi = amp * math.sin(w * t)
        dphi = amp * w * math.cos(w * t)
        c = (0.0, -arm * math.sin(phi), arm * math.cos(phi))
        v = (0.0, -arm * math.cos(phi) * dphi, -arm * math.sin(phi) * dphi)
        deck.set_pose(c, (0.0, -math.sin(phi), math.cos(phi)), (1.0, 0.0, 0.0), v,
                      (dphi, 0.0, 0.0))

    motion(0.0)
    rig = Rig(deck=deck, ground=False)
    rig.place(surface=deck, velocity=(deck.vx, deck.vy, deck.vz))
    rig.run(8.0, deck_motion=motion)
    a, b, _ = deck.local(rig.body.x, rig.body.y, rig.body.z)
    assert math.hypot(a, b) < 2e-4                 # elastic only: m g sin 6° / k_t ≈ 0.07 mm
    assert tilt_of(rig.body, deck) < math.radians(0.1)
    assert sum(rig.contact.n_gear_contacts) == 4


def test_foot_off_the_pad_falls_and_edge_strike_is_detected():
    deck = Surface('deck', 0.5, 0.4, 0.6, 0.6)
    deck.set_pose((0.0, 0.0, 0.6), (0.0, 0.0, 1.0), (1.0, 0.0, 0.0))
    # centre of mass beyond the pad's edge: two feet on the pad, two over the drop
    rig = Rig(deck=deck)
    rig.place(xy=(0.55, 0.0), surface=deck, gap_m=0.001)
    rig.run(2.0)
    assert rig.body.z < 0.5                        # fell over the apron's edge
    assert tilt_of(rig.body, deck) > rig.gear.static_tip_angle_rad()
    # running into the pad's side below its top
    rig = Rig(deck=deck)
    rig.place(xy=(-0.9, 0.0), velocity=(1.5, 0.0, 0.0), gap_m=0.3)   # gear below the top
    sides = [False]

    def watch(r):
        sides[0] = sides[0] or r.contact.side_contact

    rig.run(1.0, every=watch)
    assert sides[0]
    a, _, _ = deck.local(rig.body.x, rig.body.y, rig.body.z)
    assert a < -0.5                                 # pushed back: never inside the box


def test_skids_rest_and_slide_like_feet():
    gear = GearGeometry(kind='skids', skid_points=3)
    assert len(gear.points()) == 6
    rig = Rig(gear=gear)
    rig.place(gap_m=0.0)
    rig.run(1.0)
    assert rig.lowest_gear_height() == pytest.approx(
        -rig.bp.mass_kg * G / rig.cp.stiffness_n_per_m, rel=0.02)    # static deflection
    assert sum(rig.contact.n_gear_contacts) == 6


def test_contact_is_deterministic():
    def fly():
        rig = Rig()
        rig.place(rpy=(0.3, -0.2, 1.0), velocity=(0.4, -0.4, -1.0), rates=(2.0, -3.0, 4.0),
                  gap_m=0.01)
        rig.run(1.0)
        b = rig.body
        return [v.hex() for v in (b.x, b.y, b.z, b.vx, b.vy, b.vz, b.qw, b.qx, b.qy, b.qz,
                                  b.p, b.q, b.r)]
    assert fly() == fly()


def test_surface_pose_is_orthonormalised_and_rejects_bad_input():
    s = Surface('deck', 1.0, 1.0, 1.0, 0.5)
    assert s.set_pose((0, 0, 0), (0.0, 0.0, 2.0), (1.0, 0.0, 0.5))
    assert (s.nx, s.ny, s.nz) == (0.0, 0.0, 1.0)
    assert (s.ux, s.uy, s.uz) == (1.0, 0.0, 0.0) and (s.wx, s.wy, s.wz) == (0.0, 1.0, 0.0)
    # rejected and counted, the last good pose kept
    assert not s.set_pose((0, 0, 1), (0.0, 0.0, 1.0), (0.0, 0.0, 1.0))        # u along n
    assert not s.set_pose((0, 0, 1), (0.0, 0.0, math.nan), (1.0, 0.0, 0.0))
    assert not s.set_pose((0, 0, 1), (0.0, 0.0, 1.0), (1.0, 0.0, 0.0), (math.inf, 0, 0))
    assert not s.set_pose((0, 0, 1), (0.0, 0.0, 0.0), (1.0, 0.0, 0.0))
    assert s.rejected == 4 and s.cz == 0.0 and s.vx == 0.0
    with pytest.raises(ValueError, match='surface deck'):
        Surface('deck', 0.0, 1.0, 1.0, 0.5)
