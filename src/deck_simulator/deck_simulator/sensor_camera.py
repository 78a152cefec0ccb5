"""The Pixy as it really is: lens distortion, a calibration the estimator does not know, and
the exposure timing of its frames (pure).

:class:`TrueCamera` is one seed's camera: focal length, principal point and mount drawn around
the nominal camera the estimator is configured with (:class:`deck_simulator.sensors.CameraParams`),
with Brown–Conrady distortion (radial k1, k2, tangential p1, p2) on normalised optical
coordinates. :class:`CameraModel` adds each frame's exposure time: per-frame jitter and the
rolling-shutter delay of the beacon's row. Sources: docs/world/sensors.md.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import random

from deckland_common.frames import Mat3, Vec3, rot_body_to_world
from deckland_common.lens import PIXY_K1, PIXY_K2, distort, undistort

from deck_simulator.sensor_imu import euler_from_matrix
from deck_simulator.sensor_models import ModelStreams, TimingParams, mat_mul
from deck_simulator.sensors import CameraParams, optical_from_body, to_optical
from deckland_common import validate as chk


def _timing() -> TimingParams:
    return TimingParams(rate_hz=50.0, latency_s=0.036, latency_jitter_s=0.005,
                        stamp_mode='arrival', assumed_latency_s=0.036,
                        stamp_offset_std_s=0.003, clock_ppm_std=20.0)


@dataclass(frozen=True, slots=True)
class CameraModelParams:
    """Lens class, per-unit spread, calibration mismatch and exposure timing of the Pixy."""

    k1: float = PIXY_K1                 # fitted to ArduPilot AP_IRLock's lens characterisation
    k2: float = PIXY_K2
    p1: float = 0.0
    p2: float = 0.0
    k_rel_std: float = 0.05             # per unit, relative σ of k1 and k2
    p_std: float = 5e-4                 # per unit, σ of p1 and p2
    focal_rel_std: float = 0.015        # calibration mismatch: f_true = f (1 + ε)
    principal_point_std_px: float = 2.0
    mount_std_rad: tuple[float, float, float] = (0.009, 0.009, 0.017)   # roll, pitch, yaw
    exposure_jitter_s: float = 0.001    # per frame, σ of the exposure midpoint
    rolling_readout_s: float = 0.016    # top row → bottom row exposure delay
    timing: TimingParams = field(default_factory=_timing)

    def __post_init__(self) -> None:
        for name in ('k1', 'k2', 'p1', 'p2'):
            chk.in_range(name, getattr(self, name), -5.0, 5.0)
        for name in ('k_rel_std', 'p_std', 'focal_rel_std', 'principal_point_std_px',
                     'exposure_jitter_s', 'rolling_readout_s'):
            chk.non_negative(name, getattr(self, name))
        chk.require(self.focal_rel_std < 0.3, 'focal_rel_std', 'must be < 0.3',
                    self.focal_rel_std)
        chk.finite_tuple('mount_std_rad', self.mount_std_rad, 3)
        chk.require(all(0.0 <= v < 0.5 for v in self.mount_std_rad), 'mount_std_rad',
                    'must be in [0, 0.5) rad', self.mount_std_rad)
        chk.require(self.rolling_readout_s < 1.0 / self.timing.rate_hz, 'rolling_readout_s',
                    'must be shorter than the frame period', self.rolling_readout_s)


class TrueCamera:
    """Intrinsics, distortion and mount of the simulated camera (one seed).

    Brown–Conrady on normalised optical coordinates (x, y) = (x_o / z_o, y_o / z_o):
    x_d = x (1 + k1 r² + k2 r⁴) + 2 p1 x y + p2 (r² + 2 x²),
    y_d = y (1 + k1 r² + k2 r⁴) + p1 (r² + 2 y²) + 2 p2 x y, r² = x² + y²;
    pixels u = c_x + f_x x_d, v = c_y + f_y y_d. The mount is the nominal one followed by
    the misalignment (camera-to-body rotations, :func:`deck_simulator.sensors.optical_from_body`).
    """

    __slots__ = ('_c', 'cx', 'cy', 'fx', 'fy', 'height_px', 'iterations', 'k1', 'k2',
                 'mount_rpy_rad', 'p1', 'p2', 'width_px')

    def __init__(self, fx: float, fy: float, cx: float, cy: float, k1: float, k2: float,
                 p1: float, p2: float, mount_rpy_rad: Vec3, width_px: int, height_px: int,
                 iterations: int = 20) -> None:
        self.fx, self.fy, self.cx, self.cy = fx, fy, cx, cy
        self.k1, self.k2, self.p1, self.p2 = k1, k2, p1, p2
        self.mount_rpy_rad = mount_rpy_rad
        self.width_px, self.height_px = width_px, height_px
        self.iterations = iterations
        self._c = optical_from_body(mount_rpy_rad)

    @classmethod
    def draw(cls, nominal: CameraParams, params: CameraModelParams,
             rng: random.Random) -> TrueCamera:
        """The seed's camera around ``nominal`` (draw order: f_x, f_y, c_x, c_y, k1, k2,
        p1, p2, mount roll, pitch, yaw). f_x and f_y share one focal error (one lens) plus
        nothing else: the pixel aspect is the sensor's."""
        p = params

        def g(s: float) -> float:
            return rng.gauss(0.0, s) if s > 0.0 else 0.0

        ef = g(p.focal_rel_std)
        cx0, cy0 = nominal.principal_point_px
        cx, cy = cx0 + g(p.principal_point_std_px), cy0 + g(p.principal_point_std_px)
        k1 = p.k1 * (1.0 + g(p.k_rel_std))
        k2 = p.k2 * (1.0 + g(p.k_rel_std))
        p1, p2 = p.p1 + g(p.p_std), p.p2 + g(p.p_std)
        dr, dp, dy = g(p.mount_std_rad[0]), g(p.mount_std_rad[1]), g(p.mount_std_rad[2])
        # true mount = nominal mount followed by the misalignment, both camera-to-body
        m = mat_mul(rot_body_to_world(*nominal.mount_rpy_rad), rot_body_to_world(dr, dp, dy))
        return cls(nominal.fx_px * (1.0 + ef), nominal.fy_px * (1.0 + ef), cx, cy, k1, k2,
                   p1, p2, euler_from_matrix(m), nominal.width_px, nominal.height_px)

    def distort(self, x: float, y: float) -> tuple[float, float]:
        """Normalised undistorted (x, y) → distorted (Brown–Conrady)."""
        return distort(x, y, self.k1, self.k2, self.p1, self.p2)

    def undistort(self, xd: float, yd: float) -> tuple[float, float]:
        """Inverse of :meth:`distort` by fixed-point iteration (the OpenCV scheme)."""
        return undistort(xd, yd, self.k1, self.k2, self.p1, self.p2, self.iterations)

    def optical(self, r_body_to_world: Mat3, d0: float, d1: float, d2: float) -> Vec3:
        """Optical-frame coordinates of the world vector d (camera → point)."""
        return to_optical(self._c, r_body_to_world, d0, d1, d2)

    def project_optical(self, xo: float, yo: float, zo: float) -> tuple[float, float] | None:
        """Pixel (u, v) of an optical-frame point; None behind the lens."""
        if zo <= 1e-6:
            return None
        xd, yd = self.distort(xo / zo, yo / zo)
        return self.cx + self.fx * xd, self.cy + self.fy * yd

    def pixel_ray(self, u: float, v: float) -> tuple[float, float]:
        """Normalised undistorted ray (x, y) of pixel (u, v) (the true inverse projection)."""
        return self.undistort((u - self.cx) / self.fx, (v - self.cy) / self.fy)


class CameraModel:
    """A :class:`TrueCamera` plus the exposure timing of its frames.

    ``start_frame()`` once per frame draws that frame's exposure jitter; ``exposure_offset_s(v)``
    is then when, relative to the frame's nominal time, the row ``v`` was exposed.
    """

    __slots__ = ('_frame_jitter', 'camera', 'normal', 'params')

    def __init__(self, params: CameraModelParams, nominal: CameraParams,
                 streams: ModelStreams) -> None:
        self.params = params
        self.camera = TrueCamera.draw(nominal, params, streams.draw)
        self.normal = streams.normal
        self._frame_jitter = 0.0

    def start_frame(self) -> None:
        s = self.params.exposure_jitter_s
        n = self.normal()
        self._frame_jitter = s * n

    def exposure_offset_s(self, v_px: float) -> float:
        """Exposure time of row ``v_px`` minus the frame's nominal time (the image centre row
        at zero jitter): rolling readout (v/H − ½) T_readout plus the frame's jitter."""
        cam = self.camera
        return (self.params.rolling_readout_s * (v_px / cam.height_px - 0.5)
                + self._frame_jitter)
