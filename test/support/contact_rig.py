"""The contact rig: a rigid body on the ground (optionally a deck box) stepped at 400 Hz
with the contact model, and the bounce apex of a drop. Used by the deck_simulator tests."""

from __future__ import annotations

import math

from deck_simulator.contact import (
    ContactModel,
    ContactParams,
    GearGeometry,
    Surface,
    damping_ratio_for,
    ground_surface,
    prop_tip_points,
    step_with_contact,
)
from deck_simulator.rigid_body import RigidBody, RigidBodyParams

DT = 1.0 / 400.0
G = 9.81
HULL = prop_tip_points(0.225, 0.127, 0.05)


class Rig:
    """A body on the ground (and optionally a deck box), stepped at 400 Hz with the contact
    model's own sub-step count, as the world will do it."""

    def __init__(self, gravity=G, params=None, gear=None, deck=None, ground=True,
                 body_params=None, hull=HULL):
        self.bp = body_params or RigidBodyParams(gravity_mps2=gravity)
        self.gear = gear or GearGeometry()
        self.cp = params or ContactParams()
        self.surfaces = []
        if deck is not None:
            self.surfaces.append(deck)
        if ground:
            self.surfaces.append(ground_surface(self.cp.friction_ground))
        self.contact = ContactModel(self.cp, self.bp.mass_kg, self.bp.inertia_kgm2,
                                    self.gear.points(), hull, self.surfaces)
        self.points = self.gear.points() + tuple(hull)
        self.body = None
        self.t = 0.0

    def place(self, rpy=(0.0, 0.0, 0.0), velocity=(0.0, 0.0, 0.0), rates=(0.0, 0.0, 0.0),
              xy=(0.0, 0.0), gap_m=0.0, surface=None, yaw_on_surface=None):
        """Body with its lowest point ``gap_m`` above ``surface`` (default ground); with
        ``yaw_on_surface`` its attitude is the surface's turned by that yaw about its normal."""
        b = RigidBody(self.bp, (xy[0], xy[1], 0.0), rpy, velocity, rates)
        s = surface or self.surfaces[-1]
        if yaw_on_surface is not None:
            # columns u, w, n of the surface, turned by ψ about n
            c, sn = math.cos(yaw_on_surface), math.sin(yaw_on_surface)
            u, w = (s.ux, s.uy, s.uz), (s.wx, s.wy, s.wz)
            ex = tuple(c * a + sn * b_ for a, b_ in zip(u, w, strict=True))
            ey = tuple(-sn * a + c * b_ for a, b_ in zip(u, w, strict=True))
            b.set_quaternion(*quaternion_of((ex, ey, (s.nx, s.ny, s.nz))))
        low = min(s.local(*b.point_world(*p))[2] for p in self.points)
        b.x -= (low - gap_m) * s.nx
        b.y -= (low - gap_m) * s.ny
        b.z -= (low - gap_m) * s.nz
        self.body = b
        return b

    def run(self, seconds, deck_motion=None, monitor=None, armed=False, every=None,
            wrench=None):
        """``wrench(rig)`` → external (force world, torque body), held over each tick as the
        motors' output will be; ``armed`` a bool or ``armed(rig)``."""
        ext = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        for _ in range(round(seconds / DT)):
            n = self.contact.substeps(DT)
            h = DT / n
            if wrench is not None:
                ext = wrench(self)
            for _ in range(n):
                self.t += h
                if deck_motion is not None:
                    deck_motion(self.t)
                if monitor is None:
                    step_with_contact(self.body, self.contact, h, *ext)
                else:   # the monitor sees the contact states before they act (the wiring)
                    w = self.contact.wrench(self.body)
                    monitor.update(self.t, self.body, armed(self) if callable(armed) else armed)
                    self.body.step(h, *(a + b for a, b in zip(w, ext, strict=True)))
                if every is not None:
                    every(self)

    def energy(self):
        return self.body.energy_j() + self.contact.spring_energy_j(self.body)

    def lowest_gear_height(self, surface=None):
        s = surface or self.surfaces[-1]
        return min(s.local(*self.body.point_world(*p))[2] for p in self.gear.points())


def quaternion_of(columns):
    """Unit quaternion of the rotation whose columns are the body axes in the world."""
    (m00, m10, m20), (m01, m11, m21), (m02, m12, m22) = columns
    tr = m00 + m11 + m22
    if tr > 0:
        w = math.sqrt(1.0 + tr) / 2
        return w, (m21 - m12) / (4 * w), (m02 - m20) / (4 * w), (m10 - m01) / (4 * w)
    x = math.sqrt(max(0.0, 1.0 + m00 - m11 - m22)) / 2
    return (m21 - m12) / (4 * x), x, (m01 + m10) / (4 * x), (m02 + m20) / (4 * x)


def tilted_plane(theta_rad, mu):
    """A large static deck tilted by θ about world x (downhill toward −y), top through 0."""
    s = Surface('deck', 20.0, 20.0, 5.0, mu)
    s.set_pose((0.0, 0.0, 0.0), (0.0, -math.sin(theta_rad), math.cos(theta_rad)),
               (1.0, 0.0, 0.0))
    return s


def tilt_of(body, s):
    c = body.r02 * s.nx + body.r12 * s.ny + body.r22 * s.nz
    return math.acos(max(-1.0, min(1.0, c)))


def bounce_apex_m(cp, bp, v0):
    """Closed form of a flat drop's contact phase with gravity: δ̈ + 2σδ̇ + ω²δ = g,
    δ(0) = 0, δ̇(0) = v0; lift-off when ω²δ + 2σδ̇ = 0; apex = v_out²/2g − δ(t*) above the
    surface."""
    wn = math.sqrt(cp.stiffness_n_per_m / bp.mass_kg)
    zeta = damping_ratio_for(cp.restitution)
    sig, wd = zeta * wn, wn * math.sqrt(1 - zeta * zeta)
    ds = bp.gravity_mps2 / (wn * wn)
    b_, c_ = -ds, (v0 - sig * ds) / wd

    def delta(t):
        return ds + math.exp(-sig * t) * (b_ * math.cos(wd * t) + c_ * math.sin(wd * t))

    def ddelta(t):
        ex = math.exp(-sig * t)
        return ex * ((c_ * wd - sig * b_) * math.cos(wd * t) - (b_ * wd + sig * c_)
                     * math.sin(wd * t))

    def force(t):
        return wn * wn * delta(t) + 2 * sig * ddelta(t)

    lo = 0.5 * math.pi / wd
    hi = lo
    while force(hi) > 0:
        hi += 1e-4
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if force(mid) > 0 else (lo, mid)
    return ddelta(hi) ** 2 / (2 * bp.gravity_mps2) - delta(hi)
