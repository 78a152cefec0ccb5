"""Sensor models of the simulated vehicle: truth geometry plus seeded noise (pure).

Every sensor owns its random streams (``random.Random`` for uniform draws, a
:func:`normal_stream` of seeded numpy blocks for its Gaussian noise), so reading one sensor
more or less often never changes another's. Stochastic processes (GPS and baro bias, glints)
advance lazily at read time with their exact discretisation. The camera projection is the
simulator's truth, written independently of the estimator's (27)-(30): a full pinhole through
the tilted body.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
import hashlib
import math
import random
from typing import Protocol

from deckland_common.frames import Mat3, rot_body_to_world
from deckland_common.validate import is_finite_number, require
import numpy as np

Block = tuple[int, int, int, int, int]   # (signature, x, y, w, h), Pixy units
Normal = Callable[[], float]             # a standard-normal source: normal() ~ N(0, 1)

NORMAL_BLOCK = 256   # samples drawn per numpy call by normal_stream


class TrueCameraLike(Protocol):
    """What :meth:`Camera.frame` needs of :class:`deck_simulator.sensor_camera.TrueCamera`."""

    fx: float
    fy: float

    def optical(self, r_body_to_world: Mat3, d0: float, d1: float,
                d2: float) -> tuple[float, float, float]: ...

    def project_optical(self, xo: float, yo: float,
                        zo: float) -> tuple[float, float] | None: ...


def normal_stream(key: str, block: int = NORMAL_BLOCK) -> Normal:
    """An endless, deterministic N(0, 1) source named ``key`` (e.g. ``'7:imu:normal'``).

    numpy's PCG64 seeded with the first 128 bits of sha256(key): different keys give
    independent streams, the same key the same sequence (on every platform and Python
    version). Samples are drawn ``block`` at a time with ``Generator.standard_normal`` and
    handed out one by one as plain floats (``list.tolist`` + a generator), which costs about a
    tenth of ``random.Random.gauss`` per sample.
    """
    seed = int.from_bytes(hashlib.sha256(key.encode()).digest()[:16], 'little')
    gen = np.random.Generator(np.random.PCG64(seed))

    def samples() -> Iterator[float]:
        while True:
            yield from gen.standard_normal(block).tolist()

    return samples().__next__


def _gauss_of(rng: random.Random) -> Normal:
    """The default normal source of a sensor built from a ``random.Random`` only."""
    gauss = rng.gauss
    return lambda: gauss(0.0, 1.0)


@dataclass(frozen=True, slots=True)
class CameraParams:
    """IR Pixy (CMUcam5) as the estimator is told it is (the nominal camera): 320×200 px,
    full FOV 60°×47° (Table 2). Its frame clock and latency are
    ``sensors.true_camera.timing``; the simulated unit differs from this per seed
    (:mod:`deck_simulator.sensor_camera`)."""

    fov_x_deg: float = 60.0
    fov_y_deg: float = 47.0
    width_px: int = 320
    height_px: int = 200
    principal_point_px: tuple[float, float] = (160.0, 100.0)
    pixel_noise_px: float = 0.5
    dropout_prob: float = 0.02         # per frame, the beacon is missed
    max_range_m: float = 12.0
    beacon_size_m: float = 0.08        # apparent size of the IR beacon blob
    signature: int = 1
    false_blob_rate_hz: float = 0.0    # Poisson rate of glints
    false_blob_lifetime_s: float = 0.06
    mount_offset_m: tuple[float, float, float] = (0.0, 0.0, 0.0)   # body FLU
    mount_rpy_rad: tuple[float, float, float] = (0.0, 0.0, 0.0)    # misalignment, body FLU

    def __post_init__(self) -> None:
        for name in ('fov_x_deg', 'fov_y_deg'):
            v = getattr(self, name)
            require(is_finite_number(v) and 0 < v < 170, name, 'must be in (0, 170) degrees', v)
        for name in ('width_px', 'height_px', 'signature'):
            v = getattr(self, name)
            require(isinstance(v, int) and v > 0, name, 'must be a positive integer', v)
        for name in ('max_range_m', 'beacon_size_m', 'false_blob_lifetime_s'):
            v = getattr(self, name)
            require(is_finite_number(v) and v > 0, name, 'must be > 0', v)
        for name in ('pixel_noise_px', 'false_blob_rate_hz'):
            v = getattr(self, name)
            require(is_finite_number(v) and v >= 0, name, 'must be >= 0', v)
        require(is_finite_number(self.dropout_prob) and 0 <= self.dropout_prob <= 1,
                'dropout_prob', 'must be in [0, 1]', self.dropout_prob)
        for name, n in (('principal_point_px', 2), ('mount_offset_m', 3), ('mount_rpy_rad', 3)):
            v = getattr(self, name)
            require(len(v) == n and all(is_finite_number(x) for x in v), name,
                    f'must be {n} finite numbers', v)

    @property
    def fx_px(self) -> float:
        return 0.5 * self.width_px / math.tan(math.radians(self.fov_x_deg) / 2.0)

    @property
    def fy_px(self) -> float:
        return 0.5 * self.height_px / math.tan(math.radians(self.fov_y_deg) / 2.0)


@dataclass(frozen=True, slots=True)
class LidarParams:
    """LidarLite v3 pointing along body −z from the body origin."""

    rate_hz: float = 100.0
    noise_m: float = 0.02
    min_range_m: float = 0.05
    max_range_m: float = 40.0
    dropout_prob: float = 0.0

    def __post_init__(self) -> None:
        for name in ('rate_hz', 'max_range_m'):
            v = getattr(self, name)
            require(is_finite_number(v) and v > 0, name, 'must be > 0', v)
        for name in ('noise_m', 'min_range_m'):
            v = getattr(self, name)
            require(is_finite_number(v) and v >= 0, name, 'must be >= 0', v)
        require(self.min_range_m < self.max_range_m, 'min_range_m', 'must be < max_range_m',
                self.min_range_m)
        require(is_finite_number(self.dropout_prob) and 0 <= self.dropout_prob <= 1,
                'dropout_prob', 'must be in [0, 1]', self.dropout_prob)


@dataclass(frozen=True, slots=True)
class GpsParams:
    """Commercial GPS local position: Ornstein–Uhlenbeck bias + white noise; baro altitude."""

    rate_hz: float = 10.0
    bias_std_m: float = 0.7            # stationary σ of the horizontal bias, per axis
    bias_tau_s: float = 90.0
    noise_m: float = 0.03
    velocity_noise_mps: float = 0.05
    alt_bias_std_m: float = 0.10
    alt_bias_tau_s: float = 60.0
    alt_noise_m: float = 0.05

    def __post_init__(self) -> None:
        for name in ('rate_hz', 'bias_tau_s', 'alt_bias_tau_s'):
            v = getattr(self, name)
            require(is_finite_number(v) and v > 0, name, 'must be > 0', v)
        for name in ('bias_std_m', 'noise_m', 'velocity_noise_mps', 'alt_bias_std_m',
                     'alt_noise_m'):
            v = getattr(self, name)
            require(is_finite_number(v) and v >= 0, name, 'must be >= 0', v)


@dataclass(frozen=True, slots=True)
class ImuParams:
    """Attitude (EKF output) and world-frame acceleration (gravity removed) noise."""

    rate_hz: float = 100.0
    attitude_noise_rad: float = 0.005
    yaw_noise_rad: float = 0.01
    accel_noise_mps2: float = 0.1

    def __post_init__(self) -> None:
        require(is_finite_number(self.rate_hz) and self.rate_hz > 0, 'rate_hz', 'must be > 0',
                self.rate_hz)
        for name in ('attitude_noise_rad', 'yaw_noise_rad', 'accel_noise_mps2'):
            v = getattr(self, name)
            require(is_finite_number(v) and v >= 0, name, 'must be >= 0', v)


@dataclass(frozen=True, slots=True)
class SensorParams:
    camera: CameraParams = field(default_factory=CameraParams)
    lidar: LidarParams = field(default_factory=LidarParams)
    gps: GpsParams = field(default_factory=GpsParams)
    imu: ImuParams = field(default_factory=ImuParams)


# --- truth geometry ---------------------------------------------------------------------

def optical_from_body(mount_rpy_rad: tuple[float, float, float]) -> Mat3:
    """Constant matrix taking a body (FLU) vector to the camera optical frame.

    Nominal mount (frames.py): optical x = body −y, optical y = body −x, optical z = body −z
    (down-looking, image top toward the nose). ``mount_rpy_rad`` is a misalignment of the
    camera relative to that nominal mount, in body axes (camera-to-body rotation M): a body
    vector is first taken into the misaligned camera-body axes (Mᵀ) then permuted.
    """
    m = rot_body_to_world(*mount_rpy_rad)
    # the rows of Mᵀ are the columns of M: optical x = −(Mᵀ row 1), y = −(row 0), z = −(row 2)
    return ((-m[0][1], -m[1][1], -m[2][1]),
            (-m[0][0], -m[1][0], -m[2][0]),
            (-m[0][2], -m[1][2], -m[2][2]))


def to_optical(c: Mat3, r: Mat3, d0: float, d1: float, d2: float) -> tuple[
        float, float, float]:
    """Optical coordinates of the world vector d: C · Rᵀ · d."""
    b0 = r[0][0] * d0 + r[1][0] * d1 + r[2][0] * d2
    b1 = r[0][1] * d0 + r[1][1] * d1 + r[2][1] * d2
    b2 = r[0][2] * d0 + r[1][2] * d1 + r[2][2] * d2
    return (c[0][0] * b0 + c[0][1] * b1 + c[0][2] * b2,
            c[1][0] * b0 + c[1][1] * b1 + c[1][2] * b2,
            c[2][0] * b0 + c[2][1] * b1 + c[2][2] * b2)


def project_point(params: CameraParams, cam_position_m: tuple[float, float, float],
                  r_body_to_world: Mat3, point_m: tuple[float, float, float]) -> tuple[
                      float, float, float] | None:
    """Noise-free pinhole projection of a world point → (u_px, v_px, depth_m); None behind.

    u = c_x + f_x x_o / z_o, v = c_y + f_y y_o / z_o with f_x = (W/2) / tan(fov_x/2),
    f_y = (H/2) / tan(fov_y/2) (full FOV angles, Table 2).
    """
    xo, yo, zo = to_optical(optical_from_body(params.mount_rpy_rad), r_body_to_world,
                             point_m[0] - cam_position_m[0], point_m[1] - cam_position_m[1],
                             point_m[2] - cam_position_m[2])
    if zo <= 1e-6:
        return None
    cx, cy = params.principal_point_px
    return cx + params.fx_px * xo / zo, cy + params.fy_px * yo / zo, zo


def lidar_true_range(position_m: tuple[float, float, float], r_body_to_world: Mat3,
                     deck_center_m: tuple[float, float], deck_top_m: float,
                     half_size_m: tuple[float, float]) -> float | None:
    """Distance along body −z from the body origin to the pad top or the ground.

    The ray hits the pad top if it crosses the pad-top plane inside the pad rectangle
    (from above), otherwise the ground plane z = 0. None when the ray points upward.
    The sides of the deck are not modelled (the ray from a vehicle beside and below the
    pad top goes to the ground).
    """
    return lidar_range_along(position_m[0], position_m[1], position_m[2],
                             -r_body_to_world[0][2], -r_body_to_world[1][2],
                             -r_body_to_world[2][2], deck_center_m[0], deck_center_m[1],
                             deck_top_m, half_size_m[0], half_size_m[1])


def lidar_range_along(x: float, y: float, z: float, dx: float, dy: float, dz: float,
                      deck_cx: float, deck_cy: float, deck_top_m: float, half_x: float,
                      half_y: float) -> float | None:
    """:func:`lidar_true_range` in scalars: from (x, y, z) along the unit direction
    (dx, dy, dz) (body −z in world axes, i.e. −R e3) to the pad top or the ground."""
    if dz >= -1e-9:
        return None
    if z > deck_top_m:
        s = (z - deck_top_m) / -dz
        hx = x + s * dx - deck_cx
        hy = y + s * dy - deck_cy
        if -half_x <= hx <= half_x and -half_y <= hy <= half_y:
            return s
    if z <= 0.0:
        return 0.0
    return z / -dz


# --- sensors ------------------------------------------------------------------------------

class Camera:
    """Pixy frame generator: beacon blob with noise, quantisation, dropouts, and glints."""

    __slots__ = ('_c', '_cx', '_cy', '_fx', '_fy', 'glints', 'last_t', 'normal', 'params',
                 'period_s', 'rng')

    def __init__(self, params: CameraParams, rng: random.Random,
                 normal: Normal | None = None, period_s: float = 0.02) -> None:
        self.params = params
        self.period_s = period_s       # frame period (glints before the first frame)
        self.rng = rng                 # uniforms: dropouts, glints
        self.normal = normal if normal is not None else _gauss_of(rng)   # pixel noise
        self._fx, self._fy = params.fx_px, params.fy_px
        self._cx, self._cy = params.principal_point_px
        self._c = optical_from_body(params.mount_rpy_rad)
        self.glints: list[tuple[float, int, int, int, int]] = []
        self.last_t: float | None = None

    def frame(self, t_s: float, cam_position_m: tuple[float, float, float],
              r_body_to_world: Mat3, beacon_m: tuple[float, float, float],
              show_beacon: bool = True, true_camera: TrueCameraLike | None = None) -> list[Block]:
        """One frame exposed at t_s. ``show_beacon=False`` (occlusion fault) draws the same
        random numbers but leaves the beacon out, so the noise streams stay aligned.
        ``true_camera`` (:class:`deck_simulator.sensor_camera.TrueCamera`): project through
        it (distortion, the seed's intrinsics and mount) instead of the nominal pinhole."""
        p = self.params
        rng = self.rng
        blocks: list[Block] = []
        d0 = beacon_m[0] - cam_position_m[0]
        d1 = beacon_m[1] - cam_position_m[1]
        d2 = beacon_m[2] - cam_position_m[2]
        if true_camera is None:
            xo, yo, zo = to_optical(self._c, r_body_to_world, d0, d1, d2)
        else:
            xo, yo, zo = true_camera.optical(r_body_to_world, d0, d1, d2)
        dist = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        if zo > 1e-3 and dist <= p.max_range_m and rng.random() >= p.dropout_prob:
            normal = self.normal
            nu = p.pixel_noise_px * normal()
            nv = p.pixel_noise_px * normal()
            if true_camera is None:
                u0, v0 = self._cx + self._fx * xo / zo, self._cy + self._fy * yo / zo
                fx, fy = self._fx, self._fy
            else:
                uv = true_camera.project_optical(xo, yo, zo)
                assert uv is not None   # zo > 1e-3
                u0, v0 = uv
                fx, fy = true_camera.fx, true_camera.fy
            ui, vi = round(u0 + nu), round(v0 + nv)
            if show_beacon and 0 <= ui < p.width_px and 0 <= vi < p.height_px:
                w = max(1, round(fx * p.beacon_size_m / zo))
                h = max(1, round(fy * p.beacon_size_m / zo))
                blocks.append((p.signature, ui, vi, w, h))
        # glints: Poisson arrivals over the time since the last frame, short-lived
        if p.false_blob_rate_hz > 0.0:
            elapsed = self.period_s if self.last_t is None else max(0.0, t_s - self.last_t)
            lam = p.false_blob_rate_hz * elapsed
            n = 0
            if lam > 0.0:
                thresh = math.exp(-lam)
                prod = rng.random()
                while prod > thresh and n < 20:
                    n += 1
                    prod *= rng.random()
            for _ in range(n):
                self.glints.append((t_s + p.false_blob_lifetime_s, rng.randrange(p.width_px),
                                    rng.randrange(p.height_px), rng.randint(1, 4),
                                    rng.randint(1, 4)))
            if self.glints:
                self.glints = [g for g in self.glints if g[0] > t_s]
                blocks.extend((p.signature, g[1], g[2], g[3], g[4]) for g in self.glints)
                blocks.sort(key=lambda b: -b[3] * b[4])   # Pixy sends the largest first
        self.last_t = t_s
        return blocks

    def project_blob(self, cam_position_m: tuple[float, float, float], r_body_to_world: Mat3,
                     point_m: tuple[float, float, float], size_m: float,
                     rng: random.Random) -> Block | None:
        """A blob of world size ``size_m`` at a world point (false-blob faults), with the
        camera's pixel noise drawn from ``rng``; None outside the image, range or behind."""
        p = self.params
        d0 = point_m[0] - cam_position_m[0]
        d1 = point_m[1] - cam_position_m[1]
        d2 = point_m[2] - cam_position_m[2]
        xo, yo, zo = to_optical(self._c, r_body_to_world, d0, d1, d2)
        if zo <= 1e-3 or d0 * d0 + d1 * d1 + d2 * d2 > p.max_range_m ** 2:
            return None
        ui = round(self._cx + self._fx * xo / zo + rng.gauss(0.0, p.pixel_noise_px))
        vi = round(self._cy + self._fy * yo / zo + rng.gauss(0.0, p.pixel_noise_px))
        if not (0 <= ui < p.width_px and 0 <= vi < p.height_px):
            return None
        return (p.signature, ui, vi, max(1, round(self._fx * size_m / zo)),
                max(1, round(self._fy * size_m / zo)))


class Lidar:
    __slots__ = ('normal', 'params', 'rng')

    def __init__(self, params: LidarParams, rng: random.Random,
                 normal: Normal | None = None) -> None:
        self.params = params
        self.rng = rng                 # uniforms: dropouts
        self.normal = normal if normal is not None else _gauss_of(rng)

    def read(self, true_range_m: float | None) -> float | None:
        p = self.params
        if true_range_m is None or true_range_m > p.max_range_m:
            return None
        if p.dropout_prob > 0.0 and self.rng.random() < p.dropout_prob:
            return None
        r = true_range_m + p.noise_m * self.normal()
        if r < p.min_range_m:
            return None
        return r if r <= p.max_range_m else None


class Gps:
    """Local position (ENU) with OU bias (exact discretisation at read time) + white noise."""

    __slots__ = ('_ou_dt', '_ou_k', 'bx', 'by', 'bz', 'last_t', 'normal', 'params', 'rng')

    def __init__(self, params: GpsParams, rng: random.Random, initial_bias: bool = True,
                 normal: Normal | None = None) -> None:
        self.params = params
        self.rng = rng
        self.normal = g = normal if normal is not None else _gauss_of(rng)
        s = params.bias_std_m if initial_bias else 0.0
        self.bx = s * g() if s > 0 else 0.0
        self.by = s * g() if s > 0 else 0.0
        sz = params.alt_bias_std_m if initial_bias else 0.0
        self.bz = sz * g() if sz > 0 else 0.0
        self.last_t: float | None = None
        self._ou_dt = -1.0                        # cache: the read interval of _ou_k
        self._ou_k = (1.0, 0.0, 1.0, 0.0)         # (a, q) horizontal, (a, q) altitude

    def read(self, t_s: float, position_m, velocity_mps):
        p = self.params
        g = self.normal
        last = self.last_t
        if last is not None and t_s > last:
            dt = t_s - last
            if dt != self._ou_dt:   # exact OU discretisation, cached for the usual fixed rate
                a = math.exp(-dt / p.bias_tau_s)
                az = math.exp(-dt / p.alt_bias_tau_s)
                self._ou_k = (a, p.bias_std_m * math.sqrt(1.0 - a * a),
                              az, p.alt_bias_std_m * math.sqrt(1.0 - az * az))
                self._ou_dt = dt
            a, q, az, qz = self._ou_k
            self.bx = a * self.bx + q * g()
            self.by = a * self.by + q * g()
            self.bz = az * self.bz + qz * g()
        if last is None or t_s > last:
            self.last_t = t_s
        sn, sa, sv = p.noise_m, p.alt_noise_m, p.velocity_noise_mps
        pos = (position_m[0] + self.bx + sn * g(),
               position_m[1] + self.by + sn * g(),
               position_m[2] + self.bz + sa * g())
        vel = (velocity_mps[0] + sv * g(), velocity_mps[1] + sv * g(),
               velocity_mps[2] + sv * g())
        return pos, vel


class Imu:
    __slots__ = ('normal', 'params', 'rng')

    def __init__(self, params: ImuParams, rng: random.Random,
                 normal: Normal | None = None) -> None:
        self.params = params
        self.rng = rng
        self.normal = normal if normal is not None else _gauss_of(rng)

    def attitude(self, roll: float, pitch: float, yaw: float) -> tuple[float, float, float]:
        g = self.normal
        p = self.params
        s = p.attitude_noise_rad
        y = yaw + p.yaw_noise_rad * g()
        return roll + s * g(), pitch + s * g(), (y + math.pi) % (2.0 * math.pi) - math.pi

    def accel(self, ax: float, ay: float, az: float) -> tuple[float, float, float]:
        g = self.normal
        s = self.params.accel_noise_mps2
        return ax + s * g(), ay + s * g(), az + s * g()
