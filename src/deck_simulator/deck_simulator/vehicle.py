"""Truth model of the quadcopter: mixer (1), a free rigid body, gear contact, ground effect.

Pure and deterministic (no randomness; wind is an input), plain floats. Plus configuration,
motor 1 on the nose, 2 left, 3 tail, 4 right; a 400 Hz angle P → body-rate PI attitude loop
like PX4's with attitude priority on saturation; first-order motors; thrust γ_i F_i of each
rotor along body z with its own partial ground effect; drag of the air-relative velocity;
the body a :class:`~deck_simulator.rigid_body.RigidBody` touching the surfaces through its
gear and prop tips (:mod:`deck_simulator.contact`), sub-stepped only near them. Decisions and
tests: the package README and docs/world/contact.md.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
import math

from deckland_common.frames import Vec3, euler_to_quaternion, quaternion_to_euler
from deckland_common.validate import is_finite_number, non_negative, positive, require

from deck_simulator.contact import (
    ContactModel,
    ContactParams,
    GearGeometry,
    Surface,
    ground_surface,
    prop_tip_points,
)
from deck_simulator.rigid_body import RigidBody, RigidBodyParams
from deck_simulator.rotor_ground_effect import (
    RotorGroundEffect,
    RotorGroundEffectParams,
    multirotor_gain_level,
)
from deck_simulator.touchdown import TouchdownMonitor


@dataclass(frozen=True, slots=True)
class VehicleParams:
    """Truth parameters of the simulated quadcopter (Table 2 plus actuators, drag, attitude
    loop, landing gear, contact and ground effect; sources in docs/world/contact.md)."""

    mass_kg: float = 2.71
    inertia_kgm2: tuple[float, float, float] = (0.0172, 0.0143, 0.0221)
    arm_length_m: float = 0.225
    yaw_moment_coeff_m: float = 0.016      # c_d in (1), torque per newton of thrust
    gravity_mps2: float = 9.81
    motor_tau_s: float = 0.04
    thrust_to_weight: float = 2.0          # total max thrust / (m g)
    prop_radius_m: float = 0.127
    rotor_height_m: float = 0.05           # rotor plane above the body origin
    drag_linear_n_per_mps: float = 0.25    # rotor (induced) drag, horizontal
    drag_quad_h_kg_per_m: float = 0.06     # ½ ρ_air C_D A, side area
    drag_quad_v_kg_per_m: float = 0.15     # ½ ρ_air C_D A, top area
    att_p: float = 6.0                     # roll/pitch angle gain, 1/s
    yaw_p: float = 2.8                     # yaw angle gain, 1/s
    rate_p: float = 20.0                   # roll/pitch rate gain, 1/s (α_cmd per rate error)
    rate_i: float = 5.0                    # roll/pitch rate integral gain, 1/s²
    yaw_rate_p: float = 8.0
    yaw_rate_i: float = 2.0
    rate_i_limit_radps2: float = 5.0       # |integral term| limit, as an angular acceleration
    max_rate_radps: float = 3.8            # roll/pitch rate limit (≈ 220°/s, PX4 default)
    max_yaw_rate_radps: float = 3.5
    gear: GearGeometry = field(default_factory=GearGeometry)
    contact: ContactParams = field(default_factory=ContactParams)
    #: its ``prop_radius_m`` is the vehicle's (leave it at its default, or give the same)
    ground_effect: RotorGroundEffectParams = field(default_factory=RotorGroundEffectParams)

    def __post_init__(self) -> None:
        for name in ('mass_kg', 'arm_length_m', 'yaw_moment_coeff_m', 'gravity_mps2',
                     'motor_tau_s', 'prop_radius_m', 'att_p', 'yaw_p', 'rate_p',
                     'yaw_rate_p', 'max_rate_radps', 'max_yaw_rate_radps'):
            positive(name, getattr(self, name))
        for name in ('rotor_height_m', 'drag_linear_n_per_mps', 'drag_quad_h_kg_per_m',
                     'drag_quad_v_kg_per_m', 'rate_i', 'yaw_rate_i', 'rate_i_limit_radps2'):
            non_negative(name, getattr(self, name))
        require(len(self.inertia_kgm2) == 3, 'inertia_kgm2', 'must have 3 entries',
                self.inertia_kgm2)
        for v in self.inertia_kgm2:
            positive('inertia_kgm2', v)
        require(is_finite_number(self.thrust_to_weight) and self.thrust_to_weight > 1.0,
                'thrust_to_weight', 'must be > 1', self.thrust_to_weight)
        RigidBodyParams(self.mass_kg, self.inertia_kgm2, self.gravity_mps2)   # triangle rule
        ge = self.ground_effect
        if ge.prop_radius_m != self.prop_radius_m:
            default = RotorGroundEffectParams().prop_radius_m
            require(ge.prop_radius_m == default, 'ground_effect.prop_radius_m',
                    f'must equal prop_radius_m ({self.prop_radius_m})', ge.prop_radius_m)
            object.__setattr__(self, 'ground_effect',
                               replace(ge, prop_radius_m=self.prop_radius_m))

    @property
    def motor_max_n(self) -> float:
        return self.thrust_to_weight * self.mass_kg * self.gravity_mps2 / 4.0

    @property
    def gear_height_m(self) -> float:
        """Body origin above the bottom of the gear."""
        return self.gear.height_m

    def rotors_body_m(self) -> tuple[Vec3, Vec3, Vec3, Vec3]:
        """Rotor hubs 1-4 in the body frame (plus frame, in the rotor plane)."""
        a, h = self.arm_length_m, self.rotor_height_m
        return (a, 0.0, h), (0.0, a, h), (-a, 0.0, h), (0.0, -a, h)

    def gamma(self, rotor_height_m: float) -> float:
        """True ground-effect gain of the level vehicle with its rotor plane at this height
        above one surface: the per-rotor model's value (Sanchez-Cuevas et al. 2017, level),
        clamped as the model is."""
        ge = self.ground_effect
        z = rotor_height_m if rotor_height_m > ge.min_height_m else ge.min_height_m
        g = multirotor_gain_level(z, self.prop_radius_m, math.sqrt(2.0) * self.arm_length_m,
                                  self.arm_length_m, ge.body_coeff)
        return g if 1.0 <= g < ge.max_gain else ge.max_gain


def mix(u_z: float, u_phi: float, u_theta: float, u_psi: float, arm_length_m: float,
        yaw_moment_coeff_m: float) -> tuple[float, float, float, float]:
    """Inverse of (1): motor forces (F1, F2, F3, F4) producing (u_z, u_φ, u_θ, u_ψ)."""
    b = 0.25 * u_z
    r = 0.5 * u_phi / arm_length_m
    p = 0.5 * u_theta / arm_length_m
    y = 0.25 * u_psi / yaw_moment_coeff_m
    return b - p - y, b + r + y, b + p - y, b - r + y


def unmix(f1: float, f2: float, f3: float, f4: float, arm_length_m: float,
          yaw_moment_coeff_m: float) -> tuple[float, float, float, float]:
    """(1): (u_z, u_φ, u_θ, u_ψ) from the motor forces."""
    return (f1 + f2 + f3 + f4, arm_length_m * (f2 - f4), arm_length_m * (f3 - f1),
            yaw_moment_coeff_m * (-f1 + f2 - f3 + f4))


class Vehicle:
    """Quadcopter truth: attitude loop, mixer, motors, and the free rigid body in contact.

    Position and velocity are the body origin's (the centre of mass) in world ENU
    (read/write, on ``body``); ``roll``, ``pitch``, ``yaw`` (Z-Y-X, FLU in ENU) and their
    Euler rates are exported once per tick (change the attitude with :meth:`set_attitude`);
    ``ax, ay, az`` are Δv/dt over the tick (contact included); ``gamma`` the mean rotor gain.
    The command (roll, pitch, yaw, collective thrust) is what the autopilot receives. One tick
    is :meth:`begin` (controls, motors, ground effect, near test → contact sub-steps),
    :meth:`substep` each, :meth:`finish`; :meth:`step` runs them against fixed surfaces.
    """

    __slots__ = (
        '_a_mot', '_dt_cache', '_fx', '_fy', '_fz', '_k', '_pitch', '_pitch_rate', '_roll',
        '_roll_rate', '_tx', '_ty', '_tz', '_use_contact', '_vx0', '_vy0', '_vz0', '_yaw',
        '_yaw_rate', 'armed', 'ax', 'ay', 'az', 'body', 'cmd_pitch', 'cmd_roll', 'cmd_thrust',
        'cmd_yaw', 'contact', 'f1', 'f2', 'f3', 'f4', 'gamma', 'ground_effect', 'i_p', 'i_q',
        'i_r', 'monitor', 'motor_cmd', 'params', 'surfaces',
    )

    def __init__(self, params: VehicleParams, position_m: tuple[float, float, float],
                 yaw_rad: float = 0.0, thrust_n: float | None = None,
                 surfaces: list[Surface] | None = None) -> None:
        self.params = params
        p = params
        self.body = RigidBody(RigidBodyParams(p.mass_kg, p.inertia_kgm2, p.gravity_mps2),
                              (float(position_m[0]), float(position_m[1]),
                               float(position_m[2])), (0.0, 0.0, float(yaw_rad)))
        #: the surfaces the gear, the prop tips and the rotor wakes meet (the world moves
        #: them); default: the ground
        self.surfaces: list[Surface] = (surfaces if surfaces is not None
                                        else [ground_surface(p.contact.friction_ground)])
        self.contact = ContactModel(p.contact, p.mass_kg, p.inertia_kgm2, p.gear.points(),
                                    prop_tip_points(p.arm_length_m, p.prop_radius_m,
                                                    p.rotor_height_m), self.surfaces)
        self.ground_effect = RotorGroundEffect(p.ground_effect, p.rotors_body_m(),
                                               (0.0, 0.0, p.rotor_height_m))
        #: the touchdown monitor updated every contact sub-step (the world's), or None
        self.monitor: TouchdownMonitor | None = None
        self.armed = True
        self._roll = self._pitch = 0.0
        self._yaw = float(yaw_rad)
        self._roll_rate = self._pitch_rate = self._yaw_rate = 0.0
        self.ax = self.ay = self.az = 0.0
        self.i_p = self.i_q = self.i_r = 0.0
        hover = p.mass_kg * p.gravity_mps2 if thrust_n is None else float(thrust_n)
        self.f1 = self.f2 = self.f3 = self.f4 = min(hover / 4.0, p.motor_max_n)
        self.cmd_roll = self.cmd_pitch = 0.0
        self.cmd_yaw = self._yaw
        self.cmd_thrust = hover
        self.gamma = 1.0
        #: direct motor input (N, motors 1-4) from an external autopilot's mixer; None = the
        #: built-in attitude loop and mixer fly the (roll, pitch, yaw, thrust) command
        self.motor_cmd: tuple[float, float, float, float] | None = None
        self._dt_cache = -1.0
        self._a_mot = 0.0
        self._fx = self._fy = self._fz = self._tx = self._ty = self._tz = 0.0
        self._vx0 = self._vy0 = self._vz0 = 0.0
        self._use_contact = False
        # parameters hoisted once (400 Hz): plain floats
        jx, jy, jz = p.inertia_kgm2
        self._k = (
            jx, jy, jz, p.max_rate_radps, p.max_yaw_rate_radps, p.att_p, p.yaw_p, p.rate_p,
            p.rate_i, p.yaw_rate_p, p.yaw_rate_i, p.rate_i_limit_radps2, p.arm_length_m,
            p.yaw_moment_coeff_m, p.motor_max_n, p.drag_linear_n_per_mps,
            p.drag_quad_h_kg_per_m, p.drag_quad_v_kg_per_m,
        )

    # --- state ---------------------------------------------------------------------------

    @property
    def x(self) -> float:
        return self.body.x

    @x.setter
    def x(self, value: float) -> None:
        self.body.x = value

    @property
    def y(self) -> float:
        return self.body.y

    @y.setter
    def y(self, value: float) -> None:
        self.body.y = value

    @property
    def z(self) -> float:
        return self.body.z

    @z.setter
    def z(self, value: float) -> None:
        self.body.z = value

    @property
    def vx(self) -> float:
        return self.body.vx

    @vx.setter
    def vx(self, value: float) -> None:
        self.body.vx = value

    @property
    def vy(self) -> float:
        return self.body.vy

    @vy.setter
    def vy(self, value: float) -> None:
        self.body.vy = value

    @property
    def vz(self) -> float:
        return self.body.vz

    @vz.setter
    def vz(self, value: float) -> None:
        self.body.vz = value

    @property
    def roll(self) -> float:
        return self._roll

    @property
    def pitch(self) -> float:
        return self._pitch

    @property
    def yaw(self) -> float:
        return self._yaw

    @property
    def roll_rate(self) -> float:
        """Euler rate φ̇ (the body rates are ``body.p, q, r``)."""
        return self._roll_rate

    @property
    def pitch_rate(self) -> float:
        return self._pitch_rate

    @property
    def yaw_rate(self) -> float:
        return self._yaw_rate

    @property
    def thrust_n(self) -> float:
        """Collective rotor thrust u_z the motors really produce now (before γ)."""
        return self.f1 + self.f2 + self.f3 + self.f4

    def set_attitude(self, roll_rad: float, pitch_rad: float, yaw_rad: float,
                     rates_radps: Vec3 = (0.0, 0.0, 0.0)) -> None:
        """Put the body at this attitude (Z-Y-X) with these body rates (p, q, r)."""
        w, x, y, z = euler_to_quaternion(roll_rad, pitch_rad, yaw_rad)
        b = self.body
        b.set_quaternion(w, x, y, z)
        b.p, b.q, b.r = float(rates_radps[0]), float(rates_radps[1]), float(rates_radps[2])
        self._export_attitude()

    def reset_attitude_loop(self) -> None:
        self.i_p = self.i_q = self.i_r = 0.0

    def set_motor_thrusts(self, f1: float, f2: float, f3: float, f4: float) -> None:
        """Direct motor input: commanded thrust of motors 1-4 (N, the numbering of (1)),
        clamped to [0, motor_max_n] (NaN → 0); each motor still follows its first-order lag.
        From then on :meth:`step` bypasses the built-in attitude loop (an external autopilot
        such as PX4 in the loop mixes); :meth:`release_motors` gives it back."""
        fmax = self.params.motor_max_n

        def clamp(f: float) -> float:
            return f if 0.0 <= f <= fmax else (fmax if f > fmax else 0.0)

        self.motor_cmd = (clamp(f1), clamp(f2), clamp(f3), clamp(f4))

    def release_motors(self) -> None:
        """Back to the built-in attitude loop and mixer."""
        self.motor_cmd = None

    # --- one tick ----------------------------------------------------------------------------

    def step(self, dt_s: float, wind_x: float, wind_y: float, wind_z: float,
             t_s: float = 0.0) -> None:
        """One tick of dt_s (the caller keeps dt_s <= 1/400 s) against the surfaces as they
        are; ``wind_*`` the air velocity in ENU, ``t_s`` the time for the monitor."""
        n = self.begin(dt_s, wind_x, wind_y, wind_z)
        h = dt_s / n
        for k in range(n):
            self.substep(h, t_s + k * h)
        self.finish(dt_s)

    def begin(self, dt_s: float, wind_x: float, wind_y: float, wind_z: float) -> int:
        """Attitude loop, mixer and motors (all zero while disarmed), rotor gains, and the
        wrench of the tick (held over it); returns the number of contact sub-steps."""
        (jx, jy, jz, lim, ylim, att_p, yaw_p, rate_p, rate_i, yaw_rate_p, yaw_rate_i, ilim,
         L, cd, fmax, drag_lin, drag_qh, drag_qv) = self._k
        if dt_s != self._dt_cache:
            self._dt_cache = dt_s
            self._a_mot = 1.0 - math.exp(-dt_s / self.params.motor_tau_s)
        b = self.body
        pr, qr, rr = b.p, b.q, b.r

        mc = self.motor_cmd
        if not self.armed:
            c1 = c2 = c3 = c4 = 0.0
            self.i_p = self.i_q = self.i_r = 0.0
        elif mc is not None:    # direct motor input (set_motor_thrusts): the external mixer's
            c1, c2, c3, c4 = mc
        else:
            # --- attitude controller (angle P -> body-rate PI), α_cmd in rad/s² ------------
            sp = att_p * (self.cmd_roll - self._roll)
            sp = lim if sp > lim else (-lim if sp < -lim else sp)
            e = sp - pr
            i = self.i_p + rate_i * e * dt_s
            i = ilim if i > ilim else (-ilim if i < -ilim else i)
            self.i_p = i
            u_phi = jx * (rate_p * e + i)
            sp = att_p * (self.cmd_pitch - self._pitch)
            sp = lim if sp > lim else (-lim if sp < -lim else sp)
            e = sp - qr
            i = self.i_q + rate_i * e * dt_s
            i = ilim if i > ilim else (-ilim if i < -ilim else i)
            self.i_q = i
            u_theta = jy * (rate_p * e + i)
            ey = (self.cmd_yaw - self._yaw + math.pi) % (2.0 * math.pi) - math.pi
            sp = yaw_p * ey
            sp = ylim if sp > ylim else (-ylim if sp < -ylim else sp)
            e = sp - rr
            i = self.i_r + yaw_rate_i * e * dt_s
            i = ilim if i > ilim else (-ilim if i < -ilim else i)
            self.i_r = i
            u_psi = jz * (yaw_rate_p * e + i)

            # --- mixer: inverse of (1), attitude priority, per-motor limits ----------------
            bc = 0.25 * self.cmd_thrust
            dr = 0.5 * u_phi / L
            dp = 0.5 * u_theta / L
            dy = 0.25 * u_psi / cd
            d1, d2, d3, d4 = -dp - dy, dr + dy, dp - dy, -dr + dy
            dmax = d1
            if d2 > dmax:
                dmax = d2
            if d3 > dmax:
                dmax = d3
            if d4 > dmax:
                dmax = d4
            if bc + dmax > fmax:
                bc = fmax - dmax
            c1, c2, c3, c4 = bc + d1, bc + d2, bc + d3, bc + d4
            c1 = 0.0 if c1 < 0.0 else (fmax if c1 > fmax else c1)
            c2 = 0.0 if c2 < 0.0 else (fmax if c2 > fmax else c2)
            c3 = 0.0 if c3 < 0.0 else (fmax if c3 > fmax else c3)
            c4 = 0.0 if c4 < 0.0 else (fmax if c4 > fmax else c4)
        a = self._a_mot
        f1 = self.f1
        f1 += a * (c1 - f1)
        f2 = self.f2
        f2 += a * (c2 - f2)
        f3 = self.f3
        f3 += a * (c3 - f3)
        f4 = self.f4
        f4 += a * (c4 - f4)
        self.f1, self.f2, self.f3, self.f4 = f1, f2, f3, f4

        # --- rotor thrusts with their own ground effect; torques from (1) --------------------
        ge = self.ground_effect
        ge.update(b, self.surfaces)
        g = ge.gain
        g1, g2, g3, g4 = g[0], g[1], g[2], g[3]
        self.gamma = 0.25 * (g1 + g2 + g3 + g4)
        t1, t2, t3, t4 = g1 * f1, g2 * f2, g3 * f3, g4 * f4
        thrust = t1 + t2 + t3 + t4
        self._tx = L * (t2 - t4)
        self._ty = L * (t3 - t1)
        self._tz = cd * (-f1 + f2 - f3 + f4)
        # --- force in the world: thrust along body z, drag of the air-relative velocity δ --
        vx, vy, vz = b.vx, b.vy, b.vz
        wx = vx - wind_x
        wy = vy - wind_y
        wz = vz - wind_z
        kh = drag_lin + drag_qh * math.sqrt(wx * wx + wy * wy)
        self._fx = thrust * b.r02 - kh * wx
        self._fy = thrust * b.r12 - kh * wy
        self._fz = thrust * b.r22 - drag_qv * abs(wz) * wz
        self._vx0, self._vy0, self._vz0 = vx, vy, vz

        c = self.contact
        # a surface within reach, or points touching at the last call (released cleanly)
        self._use_contact = use = c.n_active > 0 or c.near(b, dt_s)
        return c.substeps(dt_s) if use else 1

    def substep(self, h: float, t_s: float) -> None:
        """One integration step of h: contact (when near), the monitor, the rigid body."""
        b = self.body
        if self._use_contact:
            cfx, cfy, cfz, ctx, cty, ctz = self.contact.wrench(b)
            mon = self.monitor
            if mon is not None:
                mon.update(t_s, b, self.armed)
            b.step(h, self._fx + cfx, self._fy + cfy, self._fz + cfz, self._tx + ctx,
                   self._ty + cty, self._tz + ctz)
        else:
            mon = self.monitor
            if mon is not None:
                mon.update(t_s, b, self.armed)
            b.step(h, self._fx, self._fy, self._fz, self._tx, self._ty, self._tz)

    def finish(self, dt_s: float) -> None:
        """Export the tick: acceleration Δv/dt, attitude and Euler rates."""
        b = self.body
        inv = 1.0 / dt_s
        self.ax = (b.vx - self._vx0) * inv
        self.ay = (b.vy - self._vy0) * inv
        self.az = (b.vz - self._vz0) * inv
        self._export_attitude()

    def _export_attitude(self) -> None:
        b = self.body
        roll, pitch, yaw = quaternion_to_euler(b.qw, b.qx, b.qy, b.qz)
        self._roll, self._pitch, self._yaw = roll, pitch, yaw
        # Euler rates from the body rates: φ̇ = p + (q sφ + r cφ) tθ, θ̇ = q cφ − r sφ,
        # ψ̇ = (q sφ + r cφ) / cθ
        sr, cr = math.sin(roll), math.cos(roll)
        cp = math.cos(pitch)
        s = b.q * sr + b.r * cr
        self._roll_rate = b.p + s * math.sin(pitch) / cp if cp != 0.0 else b.p
        self._pitch_rate = b.q * cr - b.r * sr
        self._yaw_rate = s / cp if cp != 0.0 else 0.0
