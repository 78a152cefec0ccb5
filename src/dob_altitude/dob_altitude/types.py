"""Inputs and outputs of the altitude controllers (contract: docs/interfaces.md, dob_altitude).

Both :class:`~dob_altitude.dob.DobAltitudeController` and
:class:`~dob_altitude.pid.PidAltitudeController` take an :class:`AltitudeInput` and return an
:class:`AltitudeOutput`. Heights are of the body origin above the surface below (deck or
ground), so ``z_m`` is the *relative* height z = z_vehicle − z_surface of the paper's (6)-(7).
"""

from __future__ import annotations

from dataclasses import dataclass
import math


@dataclass(frozen=True, slots=True)
class AltitudeInput:
    """One controller sample: measured state, reference and attitude (SI units, ENU/FLU)."""

    z_m: float  # height above the surface below (deck or ground), body origin
    z_dot_mps: float  # its rate (closing speed; negative when descending toward it)
    z_d_m: float  # reference height above the surface
    z_d_dot_mps: float
    z_d_ddot_mps2: float
    roll_rad: float
    pitch_rad: float
    rotor_height_m: float  # rotor plane above the surface, for γ̄ of (4)
    surface_accel_mps2: float = 0.0  # known vertical acceleration of the surface (0 = paper)


@dataclass(frozen=True, slots=True)
class AltitudeOutput:
    """One controller command plus the internal signals worth logging."""

    thrust_n: float  # u_z actually commanded (after saturation)
    thrust_unsat_n: float  # before saturation
    saturated: bool
    sigma: float  # (14); PID: the same expression for comparison
    d_hat_mps2: float  # (18); PID: integral term expressed as an acceleration
    e_z_m: float  # (7)
    gamma_bar: float  # nominal ground-effect gain used (4)


def input_rejection(inp: AltitudeInput, dt_s: float,
                    applied_thrust_n: float | None) -> str | None:
    """Why one controller sample must be refused, or None: ``'bad_dt'`` (dt not in (0, inf))
    or ``'nan'`` (any input not finite). The one gate in front of both altitude laws (the DOB
    (16)-(19) and the PID baseline); one ``isfinite`` on a sum is false if any term is NaN or
    ±inf."""
    if not (dt_s > 0.0 and dt_s < math.inf):
        return 'bad_dt'
    check = (inp.z_m + inp.z_dot_mps + inp.z_d_m + inp.z_d_dot_mps + inp.z_d_ddot_mps2
             + inp.roll_rad + inp.pitch_rad + inp.rotor_height_m + inp.surface_accel_mps2)
    if applied_thrust_n is not None:
        check += applied_thrust_n
    return None if math.isfinite(check) else 'nan'


def saturate(u: float, lo: float, hi: float) -> tuple[float, bool]:
    """``u`` clamped to [lo, hi] and whether it was (NaN passes through unclamped)."""
    if u > hi:
        return hi, True
    if u < lo:
        return lo, True
    return u, False


def hover_output(inp: AltitudeInput, weight_n: float, cos_max_tilt: float, thrust_min_n: float,
                 thrust_max_n: float) -> AltitudeOutput:
    """Hover thrust m g / cφcθ with no ground-effect credit (γ̄ = 1), used before any good sample.

    Assuming free air when nothing is known errs toward climbing away from a surface rather
    than toward sinking into it.
    """
    c = math.cos(inp.roll_rad) * math.cos(inp.pitch_rad)
    if not c >= cos_max_tilt:  # also NaN
        c = cos_max_tilt if math.isfinite(c) else 1.0
    u = min(thrust_max_n, max(thrust_min_n, weight_n / c))
    return AltitudeOutput(u, u, False, 0.0, 0.0, 0.0, 1.0)


class GuardedAltitudeLaw:
    """What both altitude laws (the DOB of (16)-(19) and the PID baseline) do with a refused
    sample: count it, carry its dt into the next good one when it was a non-finite sample,
    and return the last good output (free-air hover thrust before any)."""

    rejected: dict[str, int]
    _pending_dt: float
    _last: AltitudeOutput | None
    _m: float
    _g: float
    _cos_max_tilt: float
    _umin: float
    _umax: float

    def _refused(self, inp: AltitudeInput, dt_s: float,
                 applied_thrust_n: float | None) -> AltitudeOutput | None:
        """The output to return for a refused sample, or None (the sample is good)."""
        reason = input_rejection(inp, dt_s, applied_thrust_n)
        if reason is None:
            return None
        self.rejected[reason] += 1
        if reason == 'nan':
            self._pending_dt += dt_s
        return self._hold(inp)

    def _hold(self, inp: AltitudeInput) -> AltitudeOutput:
        """Safe output for a rejected sample: the last good one, else free-air hover thrust."""
        if self._last is not None:
            return self._last
        return hover_output(inp, self._m * self._g, self._cos_max_tilt, self._umin, self._umax)
