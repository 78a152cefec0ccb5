"""Truth model of the quadcopter: mixer (1), rigid-body dynamics (2), ground effect (3)-(4).

Pure and deterministic (no randomness; wind is an input), plain floats, one flat
:meth:`Vehicle.step` (it runs at >= 400 Hz in campaigns). Plus configuration, motor 1 on the
nose, 2 left, 3 tail, 4 right; rotational dynamics (2) on the Euler angles (semi-implicit);
translational ``p̈ = γ u_z R e3 / m − g e3 + δ`` in ENU with δ the drag of the air-relative
velocity; γ of (4) with the true ρ scales the whole thrust; first-order motors; a 400 Hz angle
P → rate PI attitude loop like PX4's with attitude priority on saturation. The decisions and
their tests are in the package README.
"""

from __future__ import annotations

from dataclasses import dataclass
import math

# (4) is one formula, shared with the controller side (the simulator's own ρ, r and clamps
# are passed in; only the expression is common)
from deckland_common.validate import is_finite_number, non_negative, positive, require
from dob_altitude.ground_effect import ground_effect_gain


@dataclass(frozen=True, slots=True)
class VehicleParams:
    """Truth parameters of the simulated quadcopter (Table 2 plus actuator/drag/controller)."""

    mass_kg: float = 2.71
    inertia_kgm2: tuple[float, float, float] = (0.0172, 0.0143, 0.0221)
    arm_length_m: float = 0.225
    yaw_moment_coeff_m: float = 0.016      # c_d in (1), torque per newton of thrust
    gravity_mps2: float = 9.81
    motor_tau_s: float = 0.04
    thrust_to_weight: float = 2.0          # total max thrust / (m g)
    rho_true: float = 1.4                  # true ρ of (4); the controller's nominal is 1.0
    prop_radius_m: float = 0.127
    rotor_height_m: float = 0.05           # rotor plane above the body origin
    gear_height_m: float = 0.15            # body origin above the bottom of the gear
    gear_half_width_m: float = 0.2         # half-width of the square gear footprint
    ge_min_rotor_height_m: float = 0.05
    ge_max_gain: float = 1.5
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

    def __post_init__(self) -> None:
        for name in ('mass_kg', 'arm_length_m', 'yaw_moment_coeff_m', 'gravity_mps2',
                     'motor_tau_s', 'prop_radius_m', 'ge_min_rotor_height_m',
                     'gear_height_m', 'gear_half_width_m', 'att_p', 'yaw_p', 'rate_p',
                     'yaw_rate_p', 'max_rate_radps', 'max_yaw_rate_radps'):
            positive(name, getattr(self, name))
        for name in ('rho_true', 'rotor_height_m', 'drag_linear_n_per_mps',
                     'drag_quad_h_kg_per_m', 'drag_quad_v_kg_per_m', 'rate_i', 'yaw_rate_i',
                     'rate_i_limit_radps2'):
            non_negative(name, getattr(self, name))
        require(len(self.inertia_kgm2) == 3, 'inertia_kgm2', 'must have 3 entries',
                self.inertia_kgm2)
        for v in self.inertia_kgm2:
            positive('inertia_kgm2', v)
        require(is_finite_number(self.thrust_to_weight) and self.thrust_to_weight > 1.0,
                'thrust_to_weight', 'must be > 1', self.thrust_to_weight)
        require(is_finite_number(self.ge_max_gain) and self.ge_max_gain >= 1.0, 'ge_max_gain',
                'must be >= 1', self.ge_max_gain)

    @property
    def motor_max_n(self) -> float:
        return self.thrust_to_weight * self.mass_kg * self.gravity_mps2 / 4.0

    def gamma(self, rotor_height_m: float) -> float:
        """True ground-effect gain (4) at a rotor-plane height above the surface."""
        return ground_effect_gain(self.rho_true, self.prop_radius_m, rotor_height_m,
                                  self.ge_min_rotor_height_m, self.ge_max_gain)


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
    """Quadcopter truth state and its 400 Hz attitude loop; stepped by :meth:`step`.

    Positions are of the body origin in world ENU; attitude is Z-Y-X Euler (FLU in ENU).
    The command (roll, pitch, yaw, collective thrust) is what the autopilot receives.
    """

    __slots__ = (
        '_a_mot', '_dt_cache', '_k', 'ax', 'ay', 'az', 'cmd_pitch', 'cmd_roll', 'cmd_thrust',
        'cmd_yaw', 'f1', 'f2', 'f3', 'f4', 'gamma', 'i_p', 'i_q', 'i_r', 'motor_cmd', 'params',
        'pitch', 'pitch_rate', 'roll', 'roll_rate', 'vx', 'vy', 'vz', 'x', 'y', 'yaw',
        'yaw_rate', 'z',
    )

    def __init__(self, params: VehicleParams, position_m: tuple[float, float, float],
                 yaw_rad: float = 0.0, thrust_n: float | None = None) -> None:
        self.params = params
        self.x, self.y, self.z = (float(v) for v in position_m)
        self.vx = self.vy = self.vz = 0.0
        self.ax = self.ay = self.az = 0.0
        self.roll = self.pitch = 0.0
        self.yaw = float(yaw_rad)
        self.roll_rate = self.pitch_rate = self.yaw_rate = 0.0
        self.i_p = self.i_q = self.i_r = 0.0
        hover = params.mass_kg * params.gravity_mps2 if thrust_n is None else float(thrust_n)
        self.f1 = self.f2 = self.f3 = self.f4 = min(hover / 4.0, params.motor_max_n)
        self.cmd_roll = self.cmd_pitch = 0.0
        self.cmd_yaw = self.yaw
        self.cmd_thrust = hover
        self.gamma = 1.0
        #: direct motor input (N, motors 1-4) from an external autopilot's mixer; None = the
        #: built-in attitude loop and mixer fly the (roll, pitch, yaw, thrust) command
        self.motor_cmd: tuple[float, float, float, float] | None = None
        self._dt_cache = -1.0
        self._a_mot = 0.0
        # parameters hoisted once (step() runs at 400 Hz): plain floats, same expressions
        jx, jy, jz = params.inertia_kgm2
        self._k = (
            jx, jy, jz, (jy - jz) / jx, (jz - jx) / jy, (jx - jy) / jz,
            params.max_rate_radps, params.max_yaw_rate_radps, params.att_p, params.yaw_p,
            params.rate_p, params.rate_i, params.yaw_rate_p, params.yaw_rate_i,
            params.rate_i_limit_radps2, params.arm_length_m, params.yaw_moment_coeff_m,
            params.motor_max_n, params.rotor_height_m, params.ge_min_rotor_height_m,
            params.rho_true * params.prop_radius_m * params.prop_radius_m,
            params.ge_max_gain, 1.0 - 1.0 / params.ge_max_gain, params.mass_kg,
            params.drag_linear_n_per_mps, params.drag_quad_h_kg_per_m,
            params.drag_quad_v_kg_per_m, params.gravity_mps2,
        )

    @property
    def thrust_n(self) -> float:
        """Collective rotor thrust u_z the motors really produce now (before γ)."""
        return self.f1 + self.f2 + self.f3 + self.f4

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

    def step(self, dt_s: float, surface_height_m: float, wind_x: float, wind_y: float,
             wind_z: float) -> None:
        """Advance by dt_s (one attitude-loop tick; the caller keeps dt_s <= 1/400 s).

        ``surface_height_m`` is the world height of the surface under the vehicle (for z_p of
        (4)); ``wind_*`` the air velocity in ENU. The parameters come from the tuple hoisted in
        ``__init__`` (the params are frozen); the arithmetic is that of the model above.
        """
        (jx, jy, jz, kx, ky, kz, lim, ylim, att_p, yaw_p, rate_p, rate_i, yaw_rate_p,
         yaw_rate_i, ilim, L, cd, fmax, rotor_h, zmin, rho_r2, gmax, q_max, m, drag_lin,
         drag_qh, drag_qv, grav) = self._k
        if dt_s != self._dt_cache:
            self._dt_cache = dt_s
            self._a_mot = 1.0 - math.exp(-dt_s / self.params.motor_tau_s)
        roll, pitch, yaw = self.roll, self.pitch, self.yaw
        rr, pr, yr = self.roll_rate, self.pitch_rate, self.yaw_rate

        # --- attitude controller (angle P -> rate PI), α_cmd in rad/s² -------------------
        sp = att_p * (self.cmd_roll - roll)
        sp = lim if sp > lim else (-lim if sp < -lim else sp)
        e = sp - rr
        i = self.i_p + rate_i * e * dt_s
        i = ilim if i > ilim else (-ilim if i < -ilim else i)
        self.i_p = i
        u_phi = jx * (rate_p * e + i)
        sp = att_p * (self.cmd_pitch - pitch)
        sp = lim if sp > lim else (-lim if sp < -lim else sp)
        e = sp - pr
        i = self.i_q + rate_i * e * dt_s
        i = ilim if i > ilim else (-ilim if i < -ilim else i)
        self.i_q = i
        u_theta = jy * (rate_p * e + i)
        ey = (self.cmd_yaw - yaw + math.pi) % (2.0 * math.pi) - math.pi
        sp = yaw_p * ey
        sp = ylim if sp > ylim else (-ylim if sp < -ylim else sp)
        e = sp - yr
        i = self.i_r + yaw_rate_i * e * dt_s
        i = ilim if i > ilim else (-ilim if i < -ilim else i)
        self.i_r = i
        u_psi = jz * (yaw_rate_p * e + i)

        # --- mixer: inverse of (1), attitude priority, per-motor limits --------------------
        b = 0.25 * self.cmd_thrust
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
        if b + dmax > fmax:
            b = fmax - dmax
        c1, c2, c3, c4 = b + d1, b + d2, b + d3, b + d4
        c1 = 0.0 if c1 < 0.0 else (fmax if c1 > fmax else c1)
        c2 = 0.0 if c2 < 0.0 else (fmax if c2 > fmax else c2)
        c3 = 0.0 if c3 < 0.0 else (fmax if c3 > fmax else c3)
        c4 = 0.0 if c4 < 0.0 else (fmax if c4 > fmax else c4)
        mc = self.motor_cmd
        if mc is not None:      # direct motor input (set_motor_thrusts): the external mixer's
            c1, c2, c3, c4 = mc
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

        # --- rotational dynamics (2), torques from (1) --------------------------------------
        t_phi = L * (f2 - f4)
        t_theta = L * (f3 - f1)
        t_psi = cd * (-f1 + f2 - f3 + f4)
        rr_n = rr + (kx * pr * yr + t_phi / jx) * dt_s
        pr_n = pr + (ky * rr * yr + t_theta / jy) * dt_s
        yr_n = yr + (kz * rr * pr + t_psi / jz) * dt_s
        self.roll_rate, self.pitch_rate, self.yaw_rate = rr_n, pr_n, yr_n
        self.roll = roll + rr_n * dt_s
        self.pitch = pitch + pr_n * dt_s
        yaw = yaw + yr_n * dt_s
        if yaw >= math.pi or yaw < -math.pi:
            yaw = (yaw + math.pi) % (2.0 * math.pi) - math.pi
        self.yaw = yaw

        # --- translational dynamics (2)-(3) with ground effect (4) and drag δ --------------
        zp = self.z + rotor_h - surface_height_m
        if zp < zmin:
            zp = zmin
        q = rho_r2 / (16.0 * zp * zp)
        gamma = gmax if q >= q_max else 1.0 / (1.0 - q)
        self.gamma = gamma
        cr, sr = math.cos(roll), math.sin(roll)
        sp_ = math.sin(pitch)
        cy, sy = math.cos(yaw), math.sin(yaw)
        k = gamma * (f1 + f2 + f3 + f4) / m
        vx, vy, vz = self.vx, self.vy, self.vz
        wx = vx - wind_x
        wy = vy - wind_y
        wz = vz - wind_z
        kh = (drag_lin + drag_qh * math.sqrt(wx * wx + wy * wy)) / m
        ax = k * (cr * sp_ * cy + sr * sy) - kh * wx
        ay = k * (cr * sp_ * sy - sr * cy) - kh * wy
        az = k * cr * math.cos(pitch) - grav - drag_qv * abs(wz) * wz / m
        self.ax, self.ay, self.az = ax, ay, az
        vx += ax * dt_s
        vy += ay * dt_s
        vz += az * dt_s
        self.vx, self.vy, self.vz = vx, vy, vz
        self.x += vx * dt_s
        self.y += vy * dt_s
        self.z += vz * dt_s
