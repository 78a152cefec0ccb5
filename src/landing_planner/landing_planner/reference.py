"""Smooth 1-D reference generator (z_d, ż_d, z̈_d) with speed, acceleration and jerk limits.

More in the package README, "Module notes" (`landing_planner.reference`).
"""

from __future__ import annotations

from dataclasses import dataclass
import math

_SNAP_POS_M = 1e-6
_SNAP_VEL_MPS = 1e-4
_TOL_M = 1e-9


@dataclass(frozen=True, slots=True)
class ReferenceLimits:
    """Acceleration and jerk limits of a :class:`ReferenceGenerator` (speed is per step)."""

    max_accel_mps2: float = 0.5
    max_jerk_mps3: float = 2.0

    def __post_init__(self) -> None:
        for name in ('max_accel_mps2', 'max_jerk_mps3'):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0.0):
                raise ValueError(f'ReferenceLimits.{name} must be a finite number > 0, '
                                 f'got {value!r}')


def _advance(v: float, a: float, j: float, t: float) -> tuple[float, float, float]:
    """Constant-jerk kinematics: displacement, speed and acceleration after ``t`` seconds."""
    return (v * t + 0.5 * a * t * t + j * t * t * t / 6.0,
            v + a * t + 0.5 * j * t * t,
            a + j * t)


def stopping_displacement(v: float, a: float, accel: float, jerk: float) -> float:
    """Signed distance travelled until rest under the fastest jerk-limited braking.

    Braking profile for v ≥ 0: acceleration ramps from ``a`` down to −a_p at −J, holds −a_p,
    then ramps back to 0 at +J, with a_p = min(A, √(J v + a²/2)) (triangular when the peak
    stays below A). If the vehicle already decelerates so hard that merely releasing the
    acceleration (+J until a = 0) reverses it (a ≤ 0 and a²/2J ≥ v), the release is followed
    by the braking of the reversed motion. For v < 0 the result is mirrored.
    """
    if v < 0.0 or (v == 0.0 and a < 0.0):
        return -stopping_displacement(-v, -a, accel, jerk)
    J = jerk
    if a <= 0.0 and a * a >= 2.0 * J * v:
        x_rel, v_rel, _ = _advance(v, a, J, -a / J)     # v_rel = v − a²/2J ≤ 0, a → 0
        if v_rel >= 0.0:
            return x_rel
        return x_rel - stopping_displacement(-v_rel, 0.0, accel, jerk)
    if a > accel:
        a = accel
    a_p = math.sqrt(J * v + 0.5 * a * a)
    if a_p > accel:
        a_p = accel
    # the three phases, _advance written out (this runs several times per planner step)
    t1 = (a + a_p) / J                                   # ramp a → −a_p at −J
    x1 = v * t1 + 0.5 * a * t1 * t1 + -J * t1 * t1 * t1 / 6.0
    v1 = v + a * t1 + 0.5 * -J * t1 * t1
    t2 = max((v1 - a_p * a_p / (2.0 * J)) / a_p, 0.0) if a_p > 0.0 else 0.0
    x2 = v1 * t2 - 0.5 * a_p * t2 * t2                   # hold −a_p
    v2 = v1 - a_p * t2
    t3 = a_p / J                                         # ramp −a_p → 0 at +J
    x3 = v2 * t3 + 0.5 * -a_p * t3 * t3 + J * t3 * t3 * t3 / 6.0
    return x1 + x2 + x3


class ReferenceGenerator:
    """1-D reference (z, ż, z̈) moving toward a target with limited speed, accel and jerk."""

    __slots__ = ('_a', '_v', '_z', 'limits')

    def __init__(self, limits: ReferenceLimits | None = None, z0_m: float = 0.0) -> None:
        self.limits = limits or ReferenceLimits()
        self._z = float(z0_m)
        self._v = 0.0
        self._a = 0.0

    # --- state ---------------------------------------------------------------------------
    @property
    def z_m(self) -> float:
        return self._z

    @property
    def z_dot_mps(self) -> float:
        return self._v

    @property
    def z_ddot_mps2(self) -> float:
        return self._a

    def state(self) -> tuple[float, float, float]:
        """(z_d, ż_d, z̈_d)."""
        return self._z, self._v, self._a

    def reset(self, z_m: float, z_dot_mps: float = 0.0, z_ddot_mps2: float = 0.0) -> None:
        """Re-initialise the reference (ignored when any value is not finite)."""
        if math.isfinite(z_m) and math.isfinite(z_dot_mps) and math.isfinite(z_ddot_mps2):
            a_max = self.limits.max_accel_mps2
            self._z, self._v = float(z_m), float(z_dot_mps)
            self._a = max(-a_max, min(a_max, float(z_ddot_mps2)))

    def shift(self, offset_m: float) -> None:
        """Move the whole reference by a constant; ż_d and z̈_d are untouched."""
        if math.isfinite(offset_m):
            self._z += offset_m

    def stopping_point(self) -> float:
        """Where the reference would come to rest if it braked now (jerk-limited)."""
        lim = self.limits
        return self._z + stopping_displacement(self._v, self._a, lim.max_accel_mps2,
                                               lim.max_jerk_mps3)

    # --- step ----------------------------------------------------------------------------
    def step(self, target_m: float, max_speed_mps: float,
             dt_s: float) -> tuple[float, float, float]:
        """Advance by ``dt_s`` toward ``target_m`` at no more than ``max_speed_mps``.

        Non-finite or non-positive arguments leave the state unchanged. Returns (z, ż, z̈).
        """
        if not (math.isfinite(target_m) and math.isfinite(max_speed_mps)
                and math.isfinite(dt_s) and dt_s > 0.0 and max_speed_mps >= 0.0):
            return self._z, self._v, self._a
        A = self.limits.max_accel_mps2
        J = self.limits.max_jerk_mps3
        e = target_m - self._z
        s = 1.0 if e >= 0.0 else -1.0
        d = s * e                        # distance to go, ≥ 0
        v = s * self._v                  # speed toward the target
        a = s * self._a
        if d <= _SNAP_POS_M and abs(v) <= _SNAP_VEL_MPS and abs(a) <= J * dt_s:
            self._z, self._v, self._a = target_m, 0.0, 0.0
            return self._z, self._v, self._a
        # preferred jerk j_v: the acceleration a1 after this step is chosen so that releasing
        # it at maximum jerk lands the speed exactly on v_max:
        #   v1 + a1|a1| / 2J = v_max,  v1 = v + (a + a1) dt / 2
        c = v + 0.5 * a * dt_s - max_speed_mps
        h = 0.5 * dt_s
        if c <= 0.0:    # speed up (a1 ≥ 0)
            a1 = J * (-h + math.sqrt(h * h - 2.0 * c / J))
        else:           # slow down (a1 < 0)
            a1 = J * (h - math.sqrt(h * h + 2.0 * c / J))
        a1 = max(-A, min(A, a1))
        j_v = max(-J, min(J, (a1 - a) / dt_s))
        best = None
        cands = ((j_v, 0.5 * j_v, 0.2 * j_v, 0.05 * j_v, 0.0, -J) if j_v > 0.0
                 else (j_v, -J))
        limit = d + _TOL_M
        for j in cands:
            a1 = a + j * dt_s
            a1 = A if a1 > A else (-A if a1 < -A else a1)
            x1, v1, _ = _advance(v, a, (a1 - a) / dt_s, dt_s)
            if x1 + stopping_displacement(v1, a1, A, J) <= limit:
                best = (x1, v1, a1)
                break
        if best is None:
            a1 = max(-A, a - J * dt_s)
            x1, v1, _ = _advance(v, a, (a1 - a) / dt_s, dt_s)
            best = (x1, v1, a1)
        x1, v1, a1 = best
        self._z += s * x1
        self._v = s * v1
        self._a = s * a1
        return self._z, self._v, self._a
