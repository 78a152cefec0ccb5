"""IMU and the autopilot's attitude estimate as the companion receives them (pure).

:class:`ImuModel`: specific force and angular rate in body FLU with, per axis, white noise
(sensor noise density plus in-flight vibration), a turn-on bias and a bias random walk whose
Allan curve bottoms out at the data sheet's bias instability. :class:`AttitudeModel`: the
estimate's error as a small world-frame rotation — roll/pitch (about east/north) a bias plus a
Gauss–Markov wander bounded by the accelerometer aiding, yaw (about up) a larger bias and a
slower, larger wander. :func:`accel_world_through` rotates the measured specific force through
the *estimated* attitude, so attitude error leaks gravity into horizontal acceleration.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import math

from deckland_common.frames import Mat3, Vec3, mat_vec, rot_body_to_world

from deck_simulator.sensor_models import (
    ModelStreams,
    TimingParams,
    mat_mul,
    ou_coefficients,
    random_walk_from_instability,
    white_sigma,
)
from deckland_common import validate as chk

G0_MPS2 = 9.80665                    # standard gravity (data sheets quote g in it)
DPS = math.pi / 180.0                # 1 °/s in rad/s


def _imu_timing() -> TimingParams:
    return TimingParams(rate_hz=100.0, latency_s=0.0055, latency_jitter_s=0.0015,
                        stamp_mode='arrival', clock_ppm_std=20.0)


def _attitude_timing() -> TimingParams:
    return TimingParams(rate_hz=100.0, latency_s=0.008, latency_jitter_s=0.003,
                        stamp_mode='arrival', clock_ppm_std=20.0)


@dataclass(frozen=True, slots=True)
class ImuModelParams:
    """Per-axis error budget of the IMU (defaults: ICM-42688-P, see docs/world/sensors.md)."""

    accel_noise_density: float = 70e-6 * G0_MPS2          # m/s²/√Hz (70 µg/√Hz)
    accel_vibration_density: float = 0.035                 # m/s²/√Hz (0.35 m/s² at 100 Hz)
    accel_bias_instability: float = 40e-6 * G0_MPS2       # m/s² (Allan minimum)
    accel_turn_on_bias_std: float = 1.5e-3 * G0_MPS2      # m/s², residual after calibration
    gyro_noise_density: float = 0.0028 * DPS               # rad/s/√Hz
    gyro_vibration_density: float = 1.5e-3                 # rad/s/√Hz (0.015 rad/s at 100 Hz)
    gyro_bias_instability: float = 2.0 / 3600.0 * DPS      # rad/s (2 °/h)
    gyro_turn_on_bias_std: float = 0.05 * DPS              # rad/s, residual after calibration
    bias_update_s: float = 0.1        # the bias random walks advance this often (exact steps)
    timing: TimingParams = field(default_factory=_imu_timing)    # HIGHRES_IMU stream

    def __post_init__(self) -> None:
        for name in ('accel_noise_density', 'accel_vibration_density', 'accel_bias_instability',
                     'accel_turn_on_bias_std', 'gyro_noise_density', 'gyro_vibration_density',
                     'gyro_bias_instability', 'gyro_turn_on_bias_std'):
            chk.non_negative(name, getattr(self, name))
        chk.positive('bias_update_s', self.bias_update_s)
        chk.require(isinstance(self.timing, TimingParams), 'timing', 'must be TimingParams',
                    self.timing)

    @property
    def accel_random_walk(self) -> float:
        """Bias random walk K (m/s²/√s) from the instability and the sensor's noise density."""
        return random_walk_from_instability(self.accel_bias_instability,
                                            self.accel_noise_density)

    @property
    def gyro_random_walk(self) -> float:
        """Bias random walk K (rad/s/√s) from the instability and the sensor's noise density."""
        return random_walk_from_instability(self.gyro_bias_instability, self.gyro_noise_density)


class ImuModel:
    """Measured specific force f = Rᵀ (a + g e_z) + b_a + n_a and rate ω + b_g + n_g, FLU.

    Sampled every ``period_s`` (the sample averages white noise over that period): the
    per-sample σ is the total density / √period. The biases walk by K √(m period) every
    m = round(bias_update_s / period) samples (exact random-walk increments, held between:
    below 0.1 s the walk is far under the white noise).
    """

    __slots__ = ('_countdown', '_every', '_ka', '_kg', '_sa', '_sg', 'accel_bias',
                 'gravity_mps2', 'gyro_bias', 'normal', 'params', 'period_s')

    def __init__(self, params: ImuModelParams, streams: ModelStreams, period_s: float,
                 gravity_mps2: float = 9.81) -> None:
        chk.positive('period_s', period_s)
        self.params = params
        self.period_s = period_s
        self.gravity_mps2 = gravity_mps2
        self.normal = streams.normal
        d = streams.draw
        p = params
        sa0, sg0 = p.accel_turn_on_bias_std, p.gyro_turn_on_bias_std
        self.accel_bias = [d.gauss(0.0, sa0) if sa0 > 0.0 else 0.0 for _ in range(3)]
        self.gyro_bias = [d.gauss(0.0, sg0) if sg0 > 0.0 else 0.0 for _ in range(3)]
        self._sa = white_sigma(math.hypot(p.accel_noise_density, p.accel_vibration_density),
                               period_s)
        self._sg = white_sigma(math.hypot(p.gyro_noise_density, p.gyro_vibration_density),
                               period_s)
        self._every = max(1, round(p.bias_update_s / period_s))
        self._countdown = 0
        self._ka = p.accel_random_walk * math.sqrt(self._every * period_s)
        self._kg = p.gyro_random_walk * math.sqrt(self._every * period_s)

    def sample(self, accel_world: Vec3, r_body_to_world: Mat3,
               rate_body: Vec3) -> tuple[Vec3, Vec3]:
        """One sample: (specific force FLU m/s², angular rate FLU rad/s) for the true vehicle
        acceleration ``accel_world`` (ENU, m/s²), attitude R and body rate ``rate_body``."""
        n = self.normal
        ba, bg = self.accel_bias, self.gyro_bias
        if self._countdown == 0:
            self._countdown = self._every
            ka, kg = self._ka, self._kg
            for i in range(3):
                ba[i] += ka * n()
                bg[i] += kg * n()
        self._countdown -= 1
        r = r_body_to_world
        ax, ay, az = accel_world[0], accel_world[1], accel_world[2] + self.gravity_mps2
        sa, sg = self._sa, self._sg
        f = (r[0][0] * ax + r[1][0] * ay + r[2][0] * az + ba[0] + sa * n(),
             r[0][1] * ax + r[1][1] * ay + r[2][1] * az + ba[1] + sa * n(),
             r[0][2] * ax + r[1][2] * ay + r[2][2] * az + ba[2] + sa * n())
        w = (rate_body[0] + bg[0] + sg * n(), rate_body[1] + bg[1] + sg * n(),
             rate_body[2] + bg[2] + sg * n())
        return f, w


@dataclass(frozen=True, slots=True)
class AttitudeModelParams:
    """Error of the autopilot's attitude estimate (EKF2-like, magnetometer heading)."""

    tilt_bias_std_rad: float = 0.0035        # per seed, about east and north (0.2°)
    tilt_drift_std_rad: float = 0.0035       # Gauss–Markov wander, stationary σ (0.2°)
    tilt_drift_tau_s: float = 30.0           # its correlation time (accelerometer aiding)
    tilt_noise_rad: float = 0.0003           # white, per sample
    yaw_bias_std_rad: float = 0.03           # per seed (1.7°, magnetometer heading error)
    yaw_drift_std_rad: float = 0.017         # Gauss–Markov wander (1°)
    yaw_drift_tau_s: float = 300.0           # slow: weak magnetometer aiding
    yaw_noise_rad: float = 0.001             # white, per sample
    timing: TimingParams = field(default_factory=_attitude_timing)   # ATTITUDE stream

    def __post_init__(self) -> None:
        for name in ('tilt_bias_std_rad', 'tilt_drift_std_rad', 'tilt_noise_rad',
                     'yaw_bias_std_rad', 'yaw_drift_std_rad', 'yaw_noise_rad'):
            chk.in_range(name, getattr(self, name), 0.0, 0.5)
        chk.positive('tilt_drift_tau_s', self.tilt_drift_tau_s)
        chk.positive('yaw_drift_tau_s', self.yaw_drift_tau_s)
        chk.require(isinstance(self.timing, TimingParams), 'timing', 'must be TimingParams',
                    self.timing)


def small_rotation(ex: float, ey: float, ez: float) -> Mat3:
    """Rotation matrix exp([e]×) of the rotation vector e (Rodrigues, exact)."""
    th = math.sqrt(ex * ex + ey * ey + ez * ez)
    if th < 1e-12:
        return ((1.0, -ez, ey), (ez, 1.0, -ex), (-ey, ex, 1.0))
    s = math.sin(th) / th
    c = (1.0 - math.cos(th)) / (th * th)
    return ((1.0 - c * (ey * ey + ez * ez), -s * ez + c * ex * ey, s * ey + c * ex * ez),
            (s * ez + c * ex * ey, 1.0 - c * (ex * ex + ez * ez), -s * ex + c * ey * ez),
            (-s * ey + c * ex * ez, s * ex + c * ey * ez, 1.0 - c * (ex * ex + ey * ey)))


def euler_from_matrix(m: Mat3) -> Vec3:
    """Z-Y-X (roll, pitch, yaw) of a body-to-world rotation (inverse of rot_body_to_world)."""
    s = -m[2][0]
    pitch = math.asin(1.0 if s > 1.0 else (-1.0 if s < -1.0 else s))
    return math.atan2(m[2][1], m[2][2]), pitch, math.atan2(m[1][0], m[0][0])


class AttitudeModel:
    """Estimated attitude R̂ = exp([e]×) R, e = (e_east, e_north, e_up) in the world frame.

    e_east, e_north: per-seed bias + Gauss–Markov (σ ``tilt_drift_std_rad``, τ
    ``tilt_drift_tau_s``) + white; e_up (heading): the same with the yaw parameters. Exact
    discretisation over ``period_s``; the output is Z-Y-X Euler angles as MAVLink ATTITUDE
    gives them.
    """

    __slots__ = ('_ta', '_tq', '_ya', '_yq', 'bias', 'drift', 'normal', 'params', 'period_s')

    def __init__(self, params: AttitudeModelParams, streams: ModelStreams,
                 period_s: float) -> None:
        chk.positive('period_s', period_s)
        self.params = params
        self.period_s = period_s
        self.normal = streams.normal
        d = streams.draw
        p = params
        st, sy = p.tilt_bias_std_rad, p.yaw_bias_std_rad
        self.bias = (d.gauss(0.0, st) if st > 0.0 else 0.0,
                     d.gauss(0.0, st) if st > 0.0 else 0.0,
                     d.gauss(0.0, sy) if sy > 0.0 else 0.0)
        # the wander starts from its stationary distribution
        sdt, sdy = p.tilt_drift_std_rad, p.yaw_drift_std_rad
        self.drift = [d.gauss(0.0, sdt) if sdt > 0.0 else 0.0,
                      d.gauss(0.0, sdt) if sdt > 0.0 else 0.0,
                      d.gauss(0.0, sdy) if sdy > 0.0 else 0.0]
        self._ta, self._tq = ou_coefficients(period_s, p.tilt_drift_tau_s, sdt)
        self._ya, self._yq = ou_coefficients(period_s, p.yaw_drift_tau_s, sdy)

    def error(self) -> Vec3:
        """Advance one sample; the world-frame error rotation vector (rad) of this sample."""
        n = self.normal
        p = self.params
        g = self.drift
        g[0] = self._ta * g[0] + self._tq * n()
        g[1] = self._ta * g[1] + self._tq * n()
        g[2] = self._ya * g[2] + self._yq * n()
        b = self.bias
        st, sy = p.tilt_noise_rad, p.yaw_noise_rad
        return (b[0] + g[0] + st * n(), b[1] + g[1] + st * n(), b[2] + g[2] + sy * n())

    @property
    def heading_error_rad(self) -> float:
        """The estimate's heading error now, white noise aside (bias + wander, about up):
        an autopilot holds a heading setpoint on its estimate, so its true heading is the
        setpoint minus this (``World.set_command``)."""
        return self.bias[2] + self.drift[2]

    def sample(self, roll_rad: float, pitch_rad: float, yaw_rad: float) -> Vec3:
        """One estimate (roll, pitch, yaw) of the true attitude (Z-Y-X, FLU in ENU)."""
        e = self.error()
        r = rot_body_to_world(roll_rad, pitch_rad, yaw_rad)
        m = mat_mul(small_rotation(e[0], e[1], e[2]), r)
        return euler_from_matrix(m)


def body_rates_from_euler(roll_rad: float, pitch_rad: float, roll_rate: float,
                          pitch_rate: float, yaw_rate: float) -> Vec3:
    """Body (FLU) angular rate of Z-Y-X Euler angle rates — what a gyro measures of the
    vehicle model's (φ̇, θ̇, ψ̇): p = φ̇ − ψ̇ sθ, q = θ̇ cφ + ψ̇ sφ cθ, r = ψ̇ cφ cθ − θ̇ sφ."""
    sr, cr = math.sin(roll_rad), math.cos(roll_rad)
    sp, cp = math.sin(pitch_rad), math.cos(pitch_rad)
    return (roll_rate - yaw_rate * sp, pitch_rate * cr + yaw_rate * sr * cp,
            yaw_rate * cr * cp - pitch_rate * sr)


def accel_world_through(specific_force_body: Vec3, roll_rad: float, pitch_rad: float,
                        yaw_rad: float, gravity_mps2: float) -> Vec3:
    """Vehicle acceleration in ENU, gravity removed, through a (possibly wrong) attitude:
    a = R(φ̂, θ̂, ψ̂) f − (0, 0, g). A tilt error δ leaks ≈ g δ into the horizontal."""
    ax, ay, az = mat_vec(rot_body_to_world(roll_rad, pitch_rad, yaw_rad), specific_force_body)
    return ax, ay, az - gravity_mps2
