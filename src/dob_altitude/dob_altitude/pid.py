"""PID altitude controller: the classic baseline the paper compares against (Table 1, [27]).

Same plant (6), interface, γ̄ (4), tilt compensation and saturation as the DOB controller:
a_cmd = −K_p e_z − K_d ė_z − K_i ∫e_z dt, u_z = m / (γ̄ cφ cθ) · [a_cmd + g + z̈_d + a_s], with
the measured rate ė_z and conditional-integration anti-windup (|K_i ∫e_z| bounded). Its
default gains are the DOB law (16)-(19) linearised at e_z = 0 — K_d = K + Λ + Γ,
K_p = KΛ + KΓ + ΛΓ, K_i = KΛΓ (:meth:`PidParams.from_dob`) — so a comparison isolates what
the DOB adds. ``sigma`` is (14) with ``lam``; ``d_hat_mps2`` = K_i ∫e_z. Package README,
decision 10.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
import math

from deckland_common.contract import GRAVITY_MPS2, PAPER_MASS_KG

from dob_altitude.dob import (
    PAPER_GAMMA_OBS,
    PAPER_K,
    PAPER_LAM,
    DobParams,
    check_limits,
)
from dob_altitude.ground_effect import ground_effect_gain
from dob_altitude.types import AltitudeInput, AltitudeOutput, GuardedAltitudeLaw, saturate


@dataclass(frozen=True, slots=True)
class PidParams:
    """Parameters of :class:`PidAltitudeController` (validated at construction).

    Default gains are matched to the paper's DOB gains (Table 4) — see :meth:`from_dob`.
    """

    mass_kg: float = PAPER_MASS_KG
    gravity_mps2: float = GRAVITY_MPS2
    kp: float = PAPER_K * PAPER_LAM + PAPER_K * PAPER_GAMMA_OBS + PAPER_LAM * PAPER_GAMMA_OBS
    ki: float = PAPER_K * PAPER_LAM * PAPER_GAMMA_OBS
    kd: float = PAPER_K + PAPER_LAM + PAPER_GAMMA_OBS
    lam: float = PAPER_LAM  # only for the reported σ of (14)
    rho_bar: float = 1.0
    prop_radius_m: float = 0.127
    ge_min_rotor_height_m: float = 0.05
    ge_max_gain: float = 1.5
    thrust_min_n: float = 2.66
    thrust_max_n: float = 53.17
    max_tilt_rad: float = math.radians(35.0)
    integral_limit_mps2: float = 19.62  # |K_i ∫e| bound (2 g)

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ValueError(f'PidParams.{f.name}: expected a number, got {value!r}')
            if not math.isfinite(value):
                raise ValueError(f'PidParams.{f.name}: must be finite, got {value!r}')
        for name in ('mass_kg', 'gravity_mps2', 'lam', 'prop_radius_m',
                     'ge_min_rotor_height_m', 'integral_limit_mps2'):
            if getattr(self, name) <= 0.0:
                raise ValueError(f'PidParams.{name}: must be > 0, got {getattr(self, name)!r}')
        for name in ('kp', 'ki', 'kd'):
            if getattr(self, name) < 0.0:
                raise ValueError(f'PidParams.{name}: must be >= 0, got {getattr(self, name)!r}')
        check_limits('PidParams', self.rho_bar, self.ge_max_gain, self.thrust_min_n,
                      self.thrust_max_n, self.max_tilt_rad, self.mass_kg * self.gravity_mps2)

    @classmethod
    def from_dob(cls, dob: DobParams) -> PidParams:
        """The PID equal to the linearised DOB law of ``dob`` (same poles −K, −Λ, −Γ)."""
        k, lam, gam = dob.k, dob.lam, dob.gamma_obs
        return cls(mass_kg=dob.mass_kg, gravity_mps2=dob.gravity_mps2,
                   kp=k * lam + k * gam + lam * gam, ki=k * lam * gam, kd=k + lam + gam,
                   lam=lam, rho_bar=dob.rho_bar, prop_radius_m=dob.prop_radius_m,
                   ge_min_rotor_height_m=dob.ge_min_rotor_height_m,
                   ge_max_gain=dob.ge_max_gain, thrust_min_n=dob.thrust_min_n,
                   thrust_max_n=dob.thrust_max_n, max_tilt_rad=dob.max_tilt_rad,
                   integral_limit_mps2=dob.d_hat_limit_mps2)

    @classmethod
    def profile(cls, name: str) -> PidParams:
        """Named gain sets.

        ``'paper'``: the small-signal equivalent of the DOB with Table 4 gains
        (``from_dob``). ``'default'``: the best point of the equal-effort sweep
        (``deckland tune --controller pid``, 27 points, same cost and seeds as the DOB's
        sweep), shipped because it also beat ``'paper'`` on the independent report seeds
        (README of the deckland package: "Tuning"). The DOB's own sweep winner did not, so
        the DOB default stays at Table 4.
        """
        if name not in ('default', 'paper'):
            raise ValueError(f'PidParams.profile: unknown profile {name!r}; '
                             "choose one of ['default', 'paper']")
        base = cls.from_dob(DobParams.profile('paper'))
        if name == 'paper':
            return base
        return replace(base, **TUNED_DEFAULT_GAINS)


#: ``deckland tune --controller pid`` best point (runs/tune_pid.json when regenerated).
TUNED_DEFAULT_GAINS = {'kp': 16.2069, 'ki': 8.5435, 'kd': 20.672}


class PidAltitudeController(GuardedAltitudeLaw):
    """Classic PID altitude controller with the same interface as the DOB controller.

    Attributes: ``integral`` (∫e_z dt, m·s), ``rejected`` (``'nan'``, ``'bad_dt'``) and
    ``clamped`` (``'integral'``: samples not integrated or limited, ``'tilt'``, ``'thrust'``).
    """

    def __init__(self, params: PidParams | None = None) -> None:
        self.params = PidParams() if params is None else params
        p = self.params
        self._m = p.mass_kg
        self._g = p.gravity_mps2
        self._cos_max_tilt = math.cos(p.max_tilt_rad)
        self._umin = p.thrust_min_n
        self._umax = p.thrust_max_n
        self._ilim = p.integral_limit_mps2 / p.ki if p.ki > 0.0 else 0.0
        self._ge = (p.rho_bar, p.prop_radius_m, p.ge_min_rotor_height_m, p.ge_max_gain)
        self.rejected: dict[str, int] = {'nan': 0, 'bad_dt': 0}
        self.clamped: dict[str, int] = {'integral': 0, 'tilt': 0, 'thrust': 0}
        self.reset()

    def reset(self) -> None:
        """Zero the integral and forget the previous sample (counters are kept)."""
        self.integral = 0.0
        self._started = False
        self._u_prev = 0.0
        self._pending_dt = 0.0
        self._last: AltitudeOutput | None = None

    def step(self, inp: AltitudeInput, dt_s: float,
             applied_thrust_n: float | None = None) -> AltitudeOutput:
        """One control sample; same contract as :meth:`DobAltitudeController.step`.

        ``applied_thrust_n`` (thrust produced over the last interval) only informs the
        anti-windup: if it fell short of (exceeded) the previous command, the actuator is
        treated as saturated high (low).
        """
        held = self._refused(inp, dt_s, applied_thrust_n)
        if held is not None:
            return held
        a_s = inp.surface_accel_mps2

        p = self.params
        e = inp.z_m - inp.z_d_m  # (7)
        e_dot = inp.z_dot_mps - inp.z_d_dot_mps  # (8), measured
        c = math.cos(inp.roll_rad) * math.cos(inp.pitch_rad)
        if c < self._cos_max_tilt:
            c = self._cos_max_tilt
            self.clamped['tilt'] += 1
        rho, r, hmin, gmax = self._ge
        gbar = ground_effect_gain(rho, r, inp.rotor_height_m, hmin, gmax)  # (4) with ρ̄
        scale = self._m / (gbar * c)
        base = -p.kp * e - p.kd * e_dot + self._g + inp.z_d_ddot_mps2 + a_s

        integral = self.integral
        if self._started:
            dt = dt_s + self._pending_dt
            candidate = integral + e * dt
            if candidate > self._ilim or candidate < -self._ilim:
                candidate = self._ilim if candidate > 0.0 else -self._ilim
                self.clamped['integral'] += 1
            u_try = scale * (base - p.ki * candidate)
            tol = 1e-3 * self._umax
            high = u_try > self._umax or (
                applied_thrust_n is not None and applied_thrust_n < self._u_prev - tol)
            low = u_try < self._umin or (
                applied_thrust_n is not None and applied_thrust_n > self._u_prev + tol)
            # conditional integration: only integrate if it does not push deeper into a limit
            if (high and candidate < integral) or (low and candidate > integral):
                self.clamped['integral'] += 1
            else:
                integral = candidate
        self._started = True
        self._pending_dt = 0.0
        self.integral = integral

        i_term = p.ki * integral
        u_unsat = scale * (base - i_term)
        u, saturated = saturate(u_unsat, self._umin, self._umax)
        if saturated:
            self.clamped['thrust'] += 1
        self._u_prev = u
        sigma = e_dot + p.lam * e / math.sqrt(e * e + 1.0)  # (14), for comparison
        out = AltitudeOutput(u, u_unsat, saturated, sigma, i_term, e, gbar)
        self._last = out
        return out
