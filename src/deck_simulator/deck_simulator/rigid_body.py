"""Free rigid body for contact, tip-over and large angles (pure, plain floats, mypyc-clean).

State: position and velocity of the centre of mass (the body origin) in world ENU, attitude as
a unit quaternion (w, x, y, z) taking FLU body vectors to ENU, angular velocity (p, q, r) in
the body frame. Newton ``m v̇ = F − m g e3`` (F in world), Euler ``J ω̇ = τ − ω × J ω`` (τ in
body, J the principal inertia). One :meth:`RigidBody.step` of h is semi-implicit Euler: v
then x with the new v; ω with the torque impulse, then the gyroscopic term implicitly (one
Newton step, so spin never gains energy); then q ← q ⊗ exp(ω h / 2) and renormalised.
"""

from __future__ import annotations

from dataclasses import dataclass
import math

from deckland_common.frames import Mat3, Vec3, euler_to_quaternion, quaternion_to_euler
from deckland_common.validate import finite_tuple, positive, require


@dataclass(frozen=True, slots=True)
class RigidBodyParams:
    """Mass properties (defaults: the paper's Table 2, as ``VehicleParams``)."""

    mass_kg: float = 2.71
    inertia_kgm2: tuple[float, float, float] = (0.0172, 0.0143, 0.0221)
    gravity_mps2: float = 9.81

    def __post_init__(self) -> None:
        positive('mass_kg', self.mass_kg)
        finite_tuple('inertia_kgm2', self.inertia_kgm2, 3)
        for v in self.inertia_kgm2:
            positive('inertia_kgm2', v)
        jx, jy, jz = self.inertia_kgm2
        # principal moments of a real body obey the triangle inequality
        require(jx <= jy + jz and jy <= jx + jz and jz <= jx + jy, 'inertia_kgm2',
                'must satisfy the triangle inequality (Jx <= Jy + Jz, ...)', self.inertia_kgm2)
        require(isinstance(self.gravity_mps2, int | float) and math.isfinite(self.gravity_mps2)
                and self.gravity_mps2 >= 0.0, 'gravity_mps2', 'must be a finite number >= 0',
                self.gravity_mps2)


class RigidBody:
    """Rigid-body state and its integrator; the rotation matrix is kept in ``r00`` … ``r22``."""

    __slots__ = ('g', 'inv_m', 'jx', 'jy', 'jz', 'm', 'p', 'q', 'qw', 'qx', 'qy', 'qz', 'r',
                 'r00', 'r01', 'r02', 'r10', 'r11', 'r12', 'r20', 'r21', 'r22', 'vx', 'vy',
                 'vz', 'x', 'y', 'z')

    def __init__(self, params: RigidBodyParams, position_m: Vec3 = (0.0, 0.0, 0.0),
                 attitude_rpy_rad: Vec3 = (0.0, 0.0, 0.0),
                 velocity_mps: Vec3 = (0.0, 0.0, 0.0),
                 rates_radps: Vec3 = (0.0, 0.0, 0.0)) -> None:
        self.m = params.mass_kg
        self.inv_m = 1.0 / params.mass_kg
        self.jx, self.jy, self.jz = params.inertia_kgm2
        self.g = params.gravity_mps2
        self.x, self.y, self.z = float(position_m[0]), float(position_m[1]), float(position_m[2])
        self.vx, self.vy, self.vz = (float(velocity_mps[0]), float(velocity_mps[1]),
                                     float(velocity_mps[2]))
        self.p, self.q, self.r = (float(rates_radps[0]), float(rates_radps[1]),
                                  float(rates_radps[2]))
        self.qw = 1.0
        self.qx = self.qy = self.qz = 0.0
        self.r00 = self.r01 = self.r02 = self.r10 = self.r11 = 0.0
        self.r12 = self.r20 = self.r21 = self.r22 = 0.0
        self.set_attitude(attitude_rpy_rad[0], attitude_rpy_rad[1], attitude_rpy_rad[2])

    # --- attitude ------------------------------------------------------------------------

    def set_attitude(self, roll_rad: float, pitch_rad: float, yaw_rad: float) -> None:
        """Z-Y-X Euler angles (FLU in ENU, as deckland_common.frames)."""
        w, x, y, z = euler_to_quaternion(roll_rad, pitch_rad, yaw_rad)
        self.set_quaternion(w, x, y, z)

    def set_quaternion(self, w: float, x: float, y: float, z: float) -> None:
        n = math.sqrt(w * w + x * x + y * y + z * z)
        if not (n > 0.0 and math.isfinite(n)):
            raise ValueError(f'quaternion must be finite and non-zero, got {(w, x, y, z)!r}')
        self.qw, self.qx, self.qy, self.qz = w / n, x / n, y / n, z / n
        self._update_rotation()

    def _update_rotation(self) -> None:
        w, x, y, z = self.qw, self.qx, self.qy, self.qz
        xx, yy, zz = x * x, y * y, z * z
        xy, xz, yz = x * y, x * z, y * z
        wx, wy, wz = w * x, w * y, w * z
        self.r00 = 1.0 - 2.0 * (yy + zz)
        self.r01 = 2.0 * (xy - wz)
        self.r02 = 2.0 * (xz + wy)
        self.r10 = 2.0 * (xy + wz)
        self.r11 = 1.0 - 2.0 * (xx + zz)
        self.r12 = 2.0 * (yz - wx)
        self.r20 = 2.0 * (xz - wy)
        self.r21 = 2.0 * (yz + wx)
        self.r22 = 1.0 - 2.0 * (xx + yy)

    def rotation(self) -> Mat3:
        """Body-to-world rotation (``frames.rot_body_to_world`` of :meth:`euler`)."""
        return ((self.r00, self.r01, self.r02), (self.r10, self.r11, self.r12),
                (self.r20, self.r21, self.r22))

    def euler(self) -> Vec3:
        """(roll, pitch, yaw) Z-Y-X of the current attitude."""
        return quaternion_to_euler(self.qw, self.qx, self.qy, self.qz)

    # --- kinematics of body-fixed points ----------------------------------------------------

    def point_world(self, bx: float, by: float, bz: float) -> Vec3:
        """World position of the body-frame point (bx, by, bz)."""
        return (self.x + self.r00 * bx + self.r01 * by + self.r02 * bz,
                self.y + self.r10 * bx + self.r11 * by + self.r12 * bz,
                self.z + self.r20 * bx + self.r21 * by + self.r22 * bz)

    def angular_velocity_world(self) -> Vec3:
        p, q, r = self.p, self.q, self.r
        return (self.r00 * p + self.r01 * q + self.r02 * r,
                self.r10 * p + self.r11 * q + self.r12 * r,
                self.r20 * p + self.r21 * q + self.r22 * r)

    def point_velocity(self, bx: float, by: float, bz: float) -> Vec3:
        """World velocity of the body-frame point: v + ω × (R b)."""
        ox, oy, oz = self.angular_velocity_world()
        dx = self.r00 * bx + self.r01 * by + self.r02 * bz
        dy = self.r10 * bx + self.r11 * by + self.r12 * bz
        dz = self.r20 * bx + self.r21 * by + self.r22 * bz
        return (self.vx + oy * dz - oz * dy, self.vy + oz * dx - ox * dz,
                self.vz + ox * dy - oy * dx)

    def energy_j(self) -> float:
        """Kinetic (translation + rotation) plus gravitational potential energy (z = 0 datum)."""
        p, q, r = self.p, self.q, self.r
        return (0.5 * self.m * (self.vx * self.vx + self.vy * self.vy + self.vz * self.vz)
                + 0.5 * (self.jx * p * p + self.jy * q * q + self.jz * r * r)
                + self.m * self.g * self.z)

    # --- integration ---------------------------------------------------------------------------

    def step(self, h: float, fx: float, fy: float, fz: float, tx: float, ty: float,
             tz: float) -> None:
        """Advance by h under force (fx, fy, fz) [N, world, gravity excluded] and torque
        (tx, ty, tz) [N·m, body] about the centre of mass, both held over the step."""
        im = self.inv_m
        vx = self.vx + fx * im * h
        vy = self.vy + fy * im * h
        vz = self.vz + (fz * im - self.g) * h
        self.vx, self.vy, self.vz = vx, vy, vz
        self.x += vx * h
        self.y += vy * h
        self.z += vz * h

        jx, jy, jz = self.jx, self.jy, self.jz
        # torque impulse, then the gyroscopic term implicitly:
        # solve J (ω − ω_a) + h ω × J ω = 0 by one Newton step from ω_a
        p = self.p + tx / jx * h
        q = self.q + ty / jy * h
        r = self.r + tz / jz * h
        dzy, dxz, dyx = jz - jy, jx - jz, jy - jx
        f0 = h * dzy * q * r
        f1 = h * dxz * r * p
        f2 = h * dyx * p * q
        # Jacobian of J ω + h ω × J ω at ω_a
        a00, a01, a02 = jx, h * r * dzy, h * q * dzy
        a10, a11, a12 = h * r * dxz, jy, h * p * dxz
        a20, a21, a22 = h * q * dyx, h * p * dyx, jz
        c00 = a11 * a22 - a12 * a21
        c01 = a12 * a20 - a10 * a22
        c02 = a10 * a21 - a11 * a20
        det = a00 * c00 + a01 * c01 + a02 * c02
        if det != 0.0:
            inv = 1.0 / det
            d0 = (c00 * f0 + (a02 * a21 - a01 * a22) * f1 + (a01 * a12 - a02 * a11) * f2) * inv
            d1 = (c01 * f0 + (a00 * a22 - a02 * a20) * f1 + (a02 * a10 - a00 * a12) * f2) * inv
            d2 = (c02 * f0 + (a01 * a20 - a00 * a21) * f1 + (a00 * a11 - a01 * a10) * f2) * inv
            p -= d0
            q -= d1
            r -= d2
        self.p, self.q, self.r = p, q, r

        # q ← q ⊗ (cos(θ/2), sin(θ/2) ω/|ω|), θ = |ω| h (exact for constant body rates)
        wn = math.sqrt(p * p + q * q + r * r)
        half = 0.5 * wn * h
        if half > 1e-9:
            s = math.sin(half) / wn
            c = math.cos(half)
        else:   # series: sin(θ/2)/|ω| → h/2
            s = 0.5 * h
            c = 1.0 - 0.5 * half * half
        ex, ey, ez = p * s, q * s, r * s
        w0, x0, y0, z0 = self.qw, self.qx, self.qy, self.qz
        w1 = w0 * c - x0 * ex - y0 * ey - z0 * ez
        x1 = w0 * ex + x0 * c + y0 * ez - z0 * ey
        y1 = w0 * ey - x0 * ez + y0 * c + z0 * ex
        z1 = w0 * ez + x0 * ey - y0 * ex + z0 * c
        n = 1.0 / math.sqrt(w1 * w1 + x1 * x1 + y1 * y1 + z1 * z1)
        self.qw, self.qx, self.qy, self.qz = w1 * n, x1 * n, y1 * n, z1 * n
        self._update_rotation()
