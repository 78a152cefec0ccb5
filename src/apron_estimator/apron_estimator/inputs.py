"""Pure conversions from the vehicle/camera topics to the estimator's inputs (no rclpy).

:func:`world_accel_from_specific_force` (IMU specific force FLU → ENU acceleration, gravity
removed), :func:`lidar_range` (``sensor_msgs/Range``, REP-117, → ``range_m | None``),
:func:`blocks_from_cloud` (the ``pixy/blocks`` PointCloud layout of docs/interfaces.md →
blocks) and :class:`LocalPositionPairer` (``vehicle/odom`` + ``vehicle/velocity`` of one
stamp → one local-position sample). Orientation → Euler: :mod:`deckland_common.frames`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
import math

from deckland_common.contract import PixyBlock

_isfinite = math.isfinite

Vec3 = tuple[float, float, float]


def rotate_body_to_world(q: tuple[float, float, float, float], v: Sequence[float]) -> Vec3:
    """R(q) · v for a unit quaternion q = (w, x, y, z): v + 2w (u × v) + 2 u × (u × v)."""
    w, ux, uy, uz = q
    vx, vy, vz = v
    # t = 2 (u × v)
    tx = 2.0 * (uy * vz - uz * vy)
    ty = 2.0 * (uz * vx - ux * vz)
    tz = 2.0 * (ux * vy - uy * vx)
    return (vx + w * tx + (uy * tz - uz * ty),
            vy + w * ty + (uz * tx - ux * tz),
            vz + w * tz + (ux * ty - uy * tx))


def world_accel_from_specific_force(q: tuple[float, float, float, float],
                                    specific_force_flu: Sequence[float],
                                    gravity_mps2: float) -> Vec3 | None:
    """Vehicle acceleration in ENU, gravity removed: ``a = R(q) f − (0, 0, g)``.

    ``q`` is the orientation (ENU←FLU, unit, (w, x, y, z)) and ``f`` the accelerometer's
    specific force in FLU (REP-145: ``(0, 0, +g)`` when level and at rest). Returns None if
    any number is not finite.
    """
    try:
        fx, fy, fz = (float(c) for c in specific_force_flu)
    except (TypeError, ValueError):
        return None
    if not (_isfinite(fx) and _isfinite(fy) and _isfinite(fz) and _isfinite(gravity_mps2)
            and all(_isfinite(c) for c in q)):
        return None
    ax, ay, az = rotate_body_to_world(q, (fx, fy, fz))
    return ax, ay, az - gravity_mps2


def lidar_range(range_m: float, min_range_m: float, max_range_m: float) -> float | None:
    """``sensor_msgs/Range`` → the estimator's ``range_m | None`` (REP-117).

    ``±inf`` (no return / too close) and readings outside ``[min_range, max_range]`` are
    ``None`` (the estimator counts them as dropouts). The limits are ignored when they are
    not finite or do not form an interval (``max <= min``, e.g. an unset message). NaN is
    passed through unchanged so that the estimator rejects and counts it.
    """
    if math.isnan(range_m):
        return range_m
    if math.isinf(range_m):
        return None
    if (_isfinite(min_range_m) and _isfinite(max_range_m) and max_range_m > min_range_m
            and not min_range_m <= range_m <= max_range_m):
        return None
    return range_m


def blocks_from_cloud(xs: Sequence[float], ys: Sequence[float],
                      channels: Mapping[str, Sequence[float]]) -> list[PixyBlock] | None:
    """The ``pixy/blocks`` PointCloud → blocks, or None when the layout is inconsistent.

    One point per block (``x`` = x_px, ``y`` = y_px) and the channels ``signature``,
    ``width``, ``height`` with one value per point (docs/interfaces.md). A missing channel or
    a channel of another length makes the whole frame malformed (None); an empty frame is
    ``[]``. Non-finite numbers are kept (the estimator rejects and counts them per block); a
    non-finite or non-integral signature is kept as -1, which no beacon signature matches.
    """
    n = len(xs)
    if len(ys) != n:
        return None
    try:
        sig, wid, hei = channels['signature'], channels['width'], channels['height']
    except KeyError:
        return None
    if len(sig) != n or len(wid) != n or len(hei) != n:
        return None
    out = []
    for i in range(n):
        s = sig[i]
        s_int = int(s) if _isfinite(s) and s == int(s) and s >= 0 else -1
        out.append(PixyBlock(s_int, float(xs[i]), float(ys[i]), float(wid[i]), float(hei[i])))
    return out


@dataclass(frozen=True, slots=True)
class LocalPosition:
    """One paired local-position sample for ``ApronEstimator.on_local_position``."""

    t_s: float
    position_m: Vec3
    velocity_mps: Vec3


class LocalPositionPairer:
    """Join position and velocity samples of the same stamp (``vehicle/odom`` + ``velocity``).

    The bridge publishes both from one LOCAL_POSITION_NED with the same header stamp, but the
    two messages arrive in any order. Each call stores its sample; when the other sample's
    stamp is within ``tolerance_s`` a :class:`LocalPosition` stamped with the later of the two
    is returned, once (a pair is never emitted twice, and never at a stamp not after the last
    emitted one). Non-finite stamps never pair; non-finite values are passed on so that the
    estimator rejects and counts them.
    """

    __slots__ = ('_pos', '_vel', 'last_t_s', 'tolerance_s')

    def __init__(self, tolerance_s: float = 0.005) -> None:
        if not (_isfinite(tolerance_s) and tolerance_s >= 0.0):
            raise ValueError(f'LocalPositionPairer.tolerance_s must be >= 0, got {tolerance_s!r}')
        self.tolerance_s = float(tolerance_s)
        self._pos: tuple[float, Vec3] | None = None
        self._vel: tuple[float, Vec3] | None = None
        self.last_t_s = -math.inf

    def on_position(self, t_s: float, position_m: Vec3) -> LocalPosition | None:
        self._pos = (t_s, position_m)
        return self._pair()

    def on_velocity(self, t_s: float, velocity_mps: Vec3) -> LocalPosition | None:
        self._vel = (t_s, velocity_mps)
        return self._pair()

    def _pair(self) -> LocalPosition | None:
        if self._pos is None or self._vel is None:
            return None
        tp, pos = self._pos
        tv, vel = self._vel
        if not (_isfinite(tp) and _isfinite(tv)) or abs(tp - tv) > self.tolerance_s:
            return None
        t = max(tp, tv)
        if t <= self.last_t_s:
            return None
        self.last_t_s = t
        return LocalPosition(t, pos, vel)
