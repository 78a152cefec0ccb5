"""Horizontal position controller: PID with velocity feed-forward → roll/pitch (FLU).

More in the package README, "Module notes" (`landing_planner.horizontal`).
"""

from __future__ import annotations

from dataclasses import dataclass, fields
import math

from deckland_common.frames import world_to_body_xy


@dataclass(frozen=True, slots=True)
class HorizontalParams:
    """Gains and limits of :class:`HorizontalController` (SI units)."""

    kp: float = 3.0             # 1/s²  position error → acceleration
    kd: float = 3.0             # 1/s   velocity error → acceleration
    ki: float = 0.8             # 1/s³  integral of the position error → acceleration
    # 'precise' gains, used over the deck (DESCEND/FINAL): stiffer against gusts at touchdown.
    # The softer gains above fly APPROACH/ALIGN/SEARCH, where aggressive tilts swing the
    # camera off the beacon (campaign evidence in the README).
    precise_kp: float = 8.0
    precise_kd: float = 5.5
    precise_ki: float = 2.0
    max_accel_mps2: float = 3.0
    max_tilt_rad: float = math.radians(20.0)
    max_integral_accel_mps2: float = 1.0   # clamp of |k_i ∫e| (each axis)
    integral_zone_m: float = 0.5           # integrate only while |e_p| is below this
    gravity_mps2: float = 9.81

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if not (isinstance(value, (int, float)) and math.isfinite(value)):
                raise ValueError(f'HorizontalParams.{f.name} must be finite, got {value!r}')
        for name in ('kp', 'max_accel_mps2', 'gravity_mps2', 'integral_zone_m'):
            if getattr(self, name) <= 0.0:
                raise ValueError(f'HorizontalParams.{name} must be > 0')
        for name in ('kd', 'ki', 'max_integral_accel_mps2'):
            if getattr(self, name) < 0.0:
                raise ValueError(f'HorizontalParams.{name} must be >= 0')
        if not 0.0 < self.max_tilt_rad < math.radians(60.0):
            raise ValueError('HorizontalParams.max_tilt_rad must be in (0, 60°)')


def accel_to_tilt(ax_mps2: float, ay_mps2: float, yaw_rad: float,
                  gravity_mps2: float = 9.81) -> tuple[float, float]:
    """World horizontal acceleration → (roll, pitch) FLU at hover thrust, inverse of (2)."""
    a_f, a_l = world_to_body_xy(ax_mps2, ay_mps2, yaw_rad)
    pitch = math.atan(a_f / gravity_mps2)
    roll = math.atan(-a_l * math.cos(pitch) / gravity_mps2)
    return roll, pitch


class HorizontalController:
    """PID position controller with velocity feed-forward and tilt/acceleration limits."""

    __slots__ = ('_a_lim', '_ix', '_iy', '_last', 'params', 'rejected')

    def __init__(self, params: HorizontalParams | None = None) -> None:
        self.params = params or HorizontalParams()
        p = self.params
        self._a_lim = min(p.max_accel_mps2, p.gravity_mps2 * math.tan(p.max_tilt_rad))
        self._ix = 0.0
        self._iy = 0.0
        self._last = (0.0, 0.0)
        self.rejected: dict[str, int] = {'nan': 0, 'bad_dt': 0}

    def reset(self) -> None:
        """Zero the integrator and the last command."""
        self._ix = self._iy = 0.0
        self._last = (0.0, 0.0)

    @property
    def integral_accel_mps2(self) -> tuple[float, float]:
        """The integral term k_i ∫e_p currently applied (world ENU)."""
        return self._ix, self._iy

    def step(self, setpoint_m: tuple[float, float], velocity_ff_mps: tuple[float, float],
             position_m: tuple[float, ...], velocity_mps: tuple[float, ...], yaw_rad: float,
             dt_s: float, precise: bool = False,
             accel_ff_mps2: tuple[float, float] = (0.0, 0.0)) -> tuple[float, float]:
        """One control step; returns (roll_rad, pitch_rad) in the FLU convention.

        ``precise`` selects the stiffer gain set (over the deck); ``accel_ff_mps2`` (the
        deck's acceleration, world ENU) is added to the command before the limit. The
        integral is stored as the acceleration k_i ∫e it contributes, so switching gains is
        bumpless.
        Non-finite inputs are rejected (counted, the last command is returned).
        """
        try:
            sx, sy = float(setpoint_m[0]), float(setpoint_m[1])
            fx, fy = float(velocity_ff_mps[0]), float(velocity_ff_mps[1])
            px, py = float(position_m[0]), float(position_m[1])
            vx, vy = float(velocity_mps[0]), float(velocity_mps[1])
            yaw = float(yaw_rad)
            afx, afy = float(accel_ff_mps2[0]), float(accel_ff_mps2[1])
        except (TypeError, ValueError, IndexError):
            self.rejected['nan'] += 1
            return self._last
        # a NaN/inf anywhere makes the sum non-finite (finite inputs would have to be near
        # 1e308 to overflow it; positions, speeds and angles never are)
        if not math.isfinite(sx + sy + fx + fy + px + py + vx + vy + yaw + afx + afy):
            self.rejected['nan'] += 1
            return self._last
        if not (math.isfinite(dt_s) and dt_s > 0.0):
            self.rejected['bad_dt'] += 1
            return self._last
        p = self.params
        if precise:
            kp, kd, ki = p.precise_kp, p.precise_kd, p.precise_ki
        else:
            kp, kd, ki = p.kp, p.kd, p.ki
        ex, ey = sx - px, sy - py
        # a_cmd = a_ff + k_p e_p + k_d (v_ff − v) + k_i ∫e_p
        ux = afx + kp * ex + kd * (fx - vx)
        uy = afy + kp * ey + kd * (fy - vy)
        ax = ux + self._ix
        ay = uy + self._iy
        norm = math.hypot(ax, ay)
        saturated = norm > self._a_lim
        if saturated:
            k = self._a_lim / norm
            ax *= k
            ay *= k
        # conditional integration: only near the setpoint (the integrator is for steady
        # disturbances, not for the transit) and not while saturated outward
        if (ki > 0.0 and ex * ex + ey * ey < p.integral_zone_m * p.integral_zone_m
                and not (saturated and ex * ax + ey * ay > 0.0)):
            i_max = p.max_integral_accel_mps2
            self._ix = max(-i_max, min(i_max, self._ix + ki * ex * dt_s))
            self._iy = max(-i_max, min(i_max, self._iy + ki * ey * dt_s))
        self._last = accel_to_tilt(ax, ay, yaw, p.gravity_mps2)
        return self._last
