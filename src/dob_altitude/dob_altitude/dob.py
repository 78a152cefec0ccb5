"""Disturbance-observer-based (DOB) altitude controller, paper §3.1, eqs. (6)-(19).

Model (6) of the relative height z = z_vehicle − z_surface, z̈ = −g + (γ̄/m) cφ cθ u_z + d,
with the lumped disturbance d (external δ, ground-effect mismatch, minus the surface's own
acceleration); e_z = z − z_d (7). Sliding variable σ (14), ζ (17), observer d̂ = μ + Γσ (18)
with μ̇ (19), control law u_z (16): σ̇ = −Kσ + d̃ (20), d̃̇ = ḋ − Γd̃ (22). Paper typos (15 into
13; γ̃ is the nominal γ̄), the surface-acceleration feed-forward a_s, the exact discretisation
of the observer, the observer on the applied thrust, the bumpless start (d̂ = 0) and the
tilt/d̂/thrust guards: package README, decisions.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
import math

from deckland_common.contract import GRAVITY_MPS2, PAPER_MASS_KG

from dob_altitude.ground_effect import ground_effect_gain
from dob_altitude.types import AltitudeInput, AltitudeOutput, GuardedAltitudeLaw, saturate

#: Table 4 of the paper: controller gains K, Λ and observer gain Γ.
PAPER_K = 0.85
PAPER_LAM = 10.47
PAPER_GAMMA_OBS = 1.6


@dataclass(frozen=True, slots=True)
class DobParams:
    """Parameters of :class:`DobAltitudeController` (validated at construction).

    Gains are easy to override: ``dataclasses.replace(DobParams(), k=2.0)``.
    """

    mass_kg: float = PAPER_MASS_KG  # m, Table 2 (the shared vehicle description)
    gravity_mps2: float = GRAVITY_MPS2  # g, Table 2
    k: float = PAPER_K  # K of (15)-(16)
    lam: float = PAPER_LAM  # Λ of (14)-(17)
    gamma_obs: float = PAPER_GAMMA_OBS  # Γ of (18)-(19)
    rho_bar: float = 1.0  # nominal ρ̄ of (4); Cheeseman–Bennett classic value
    prop_radius_m: float = 0.127  # r of (4), 10-inch props
    ge_min_rotor_height_m: float = 0.05  # lower clamp of z_p in (4)
    ge_max_gain: float = 1.5  # upper clamp of γ̄
    thrust_min_n: float = 2.66  # ≈ 0.1 m g: keep the motors spinning
    thrust_max_n: float = 53.17  # ≈ 2 m g
    max_tilt_rad: float = math.radians(35.0)  # tilt limit used in 1/(cφ cθ)
    d_hat_limit_mps2: float = 19.62  # |d̂| bound (2 g), a safety net

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ValueError(f'DobParams.{f.name}: expected a number, got {value!r}')
            if not math.isfinite(value):
                raise ValueError(f'DobParams.{f.name}: must be finite, got {value!r}')
        for name in ('mass_kg', 'gravity_mps2', 'k', 'lam', 'gamma_obs', 'prop_radius_m',
                     'ge_min_rotor_height_m', 'd_hat_limit_mps2'):
            if getattr(self, name) <= 0.0:
                raise ValueError(f'DobParams.{name}: must be > 0, got {getattr(self, name)!r}')
        check_limits('DobParams', self.rho_bar, self.ge_max_gain, self.thrust_min_n,
                      self.thrust_max_n, self.max_tilt_rad, self.mass_kg * self.gravity_mps2)

    @classmethod
    def profile(cls, name: str) -> DobParams:
        """Named parameter sets: ``'paper'`` (Table 4 gains) and ``'default'`` (shipped)."""
        try:
            return _DOB_PROFILES[name]
        except KeyError:
            raise ValueError(f'DobParams.profile: unknown profile {name!r}; '
                             f'choose one of {sorted(_DOB_PROFILES)}') from None


def check_limits(owner: str, rho_bar: float, ge_max_gain: float, thrust_min_n: float,
                  thrust_max_n: float, max_tilt_rad: float, weight_n: float) -> None:
    """Validation shared by DobParams and PidParams (ValueError naming the field)."""
    if rho_bar < 0.0:
        raise ValueError(f'{owner}.rho_bar: must be >= 0, got {rho_bar!r}')
    if ge_max_gain < 1.0:
        raise ValueError(f'{owner}.ge_max_gain: must be >= 1, got {ge_max_gain!r}')
    if not 0.0 <= max_tilt_rad < math.radians(80.0):
        raise ValueError(f'{owner}.max_tilt_rad: must be in [0, 80°), got {max_tilt_rad!r}')
    if thrust_min_n < 0.0:
        raise ValueError(f'{owner}.thrust_min_n: must be >= 0, got {thrust_min_n!r}')
    if thrust_max_n <= weight_n:
        raise ValueError(f'{owner}.thrust_max_n: must exceed the weight m g = {weight_n:.3f} N '
                         f'(else the vehicle cannot hover), got {thrust_max_n!r}')
    if thrust_min_n >= weight_n / ge_max_gain:
        raise ValueError(f'{owner}.thrust_min_n: must be below m g / ge_max_gain = '
                         f'{weight_n / ge_max_gain:.3f} N (else it cannot descend in ground '
                         f'effect), got {thrust_min_n!r}')


_DOB_PROFILES: dict[str, DobParams] = {
    'paper': DobParams(k=PAPER_K, lam=PAPER_LAM, gamma_obs=PAPER_GAMMA_OBS),
    # The shipped default; a campaign will replace these gains (identical to 'paper' for now).
    'default': DobParams(),
}


class DobAltitudeController(GuardedAltitudeLaw):
    """The DOB altitude controller (16)-(19) as a pure, stepped core.

    Call :meth:`step` once per control period (100 Hz in the paper) with the time elapsed since
    the previous call. Attributes: ``mu`` (observer state μ of (18)-(19)), ``rejected``
    (counts of refused inputs: ``'nan'`` non-finite values, ``'bad_dt'`` non-finite or
    non-positive ``dt_s``) and ``clamped`` (counts of guard activations: ``'d_hat'``,
    ``'tilt'``, ``'thrust'``).
    """

    def __init__(self, params: DobParams | None = None) -> None:
        self.params = DobParams() if params is None else params
        p = self.params
        self._m = p.mass_kg
        self._g = p.gravity_mps2
        self._k = p.k
        self._lam = p.lam
        self._gam = p.gamma_obs
        self._cos_max_tilt = math.cos(p.max_tilt_rad)
        self._umin = p.thrust_min_n
        self._umax = p.thrust_max_n
        self._dlim = p.d_hat_limit_mps2
        self._ge = (p.rho_bar, p.prop_radius_m, p.ge_min_rotor_height_m, p.ge_max_gain)
        self._a_dt = -1.0  # cache of (Δt, e^(−ΓΔt))
        self._a = 1.0
        self.rejected: dict[str, int] = {'nan': 0, 'bad_dt': 0}
        self.clamped: dict[str, int] = {'d_hat': 0, 'tilt': 0, 'thrust': 0}
        self.reset()

    def reset(self) -> None:
        """Forget the observer state μ and the previous sample (counters are kept)."""
        self.mu = 0.0
        self._started = False
        self._w_free = 0.0  # ζ − g − z̈_d − a_s of the previous sample
        self._sigma_prev = 0.0
        self._b_prev = 0.0  # (γ̄/m) cφ cθ of the previous sample
        self._u_prev = 0.0  # last thrust command (after saturation)
        self._pending_dt = 0.0  # time of rejected samples since the last good one
        self._last: AltitudeOutput | None = None

    def step(self, inp: AltitudeInput, dt_s: float,
             applied_thrust_n: float | None = None) -> AltitudeOutput:
        """One control sample: propagate the observer over ``dt_s``, return the command (16).

        Args:
            inp: measured relative height/rate, reference, attitude, rotor height, a_s.
            dt_s: time since the previous call (s, > 0). Ignored on the first call after
                :meth:`reset` (nothing to propagate yet).
            applied_thrust_n: the thrust the actuator really produced during that interval (in
                response to the previous command). ``None`` → the previous saturated command.

        Bad input never raises: the state is not updated, the reason is counted in
        ``rejected`` and the last good output is returned again (free-air hover thrust
        m g / cφcθ, tilt-guarded, if there is none yet).
        """
        held = self._refused(inp, dt_s, applied_thrust_n)
        if held is not None:
            return held
        a_s = inp.surface_accel_mps2

        gam = self._gam
        lam = self._lam
        e = inp.z_m - inp.z_d_m  # (7)
        e_dot = inp.z_dot_mps - inp.z_d_dot_mps  # (8)
        s2 = e * e + 1.0
        r1 = 1.0 / math.sqrt(s2)  # (e² + 1)^(−1/2)
        sigma = e_dot + lam * e * r1  # (14)
        zeta = lam * e_dot * r1 / s2  # (17): Λ ė (e² + 1)^(−3/2)
        ff = self._g + inp.z_d_ddot_mps2 + a_s  # g + z̈_d (+ a_s, the known part of −d)

        if self._started:
            dt = dt_s + self._pending_dt
            u_app = self._u_prev if applied_thrust_n is None else applied_thrust_n
            # f̄: the bracket of (19) without Γσ over the last interval — thrust held, the
            # exogenous part ζ − g − z̈_d − a_s averaged (trapezoid) over the interval.
            f_bar = 0.5 * (self._w_free + zeta - ff) + self._b_prev * u_app
            if dt != self._a_dt:
                self._a_dt = dt
                self._a = math.exp(-gam * dt)
            a = self._a
            # (18)-(19) ⇔ d̂̇ = Γ (σ̇ − f − d̂): a first-order low-pass of the measured
            # disturbance σ̇ − f, discretised exactly for a zero-order-hold input.
            d_meas = (sigma - self._sigma_prev) / dt - f_bar
            d_hat = a * (self.mu + gam * self._sigma_prev) + (1.0 - a) * d_meas
        else:
            d_hat = 0.0  # start-up: no disturbance known (μ = −Γσ)
            self._started = True
        self._pending_dt = 0.0
        if d_hat > self._dlim or d_hat < -self._dlim:
            d_hat = self._dlim if d_hat > 0.0 else -self._dlim
            self.clamped['d_hat'] += 1
        self.mu = d_hat - gam * sigma  # (18): d̂ = μ + Γσ

        c = math.cos(inp.roll_rad) * math.cos(inp.pitch_rad)
        c_ctrl = c
        if c < self._cos_max_tilt:
            c_ctrl = self._cos_max_tilt
            self.clamped['tilt'] += 1
        rho, r, hmin, gmax = self._ge
        gbar = ground_effect_gain(rho, r, inp.rotor_height_m, hmin, gmax)  # (4) with ρ̄
        m = self._m
        # (16): −K ė − K Λ e (e²+1)^(−1/2) = −K σ
        u_unsat = m / (gbar * c_ctrl) * (-self._k * sigma - zeta + ff - d_hat)
        u, saturated = saturate(u_unsat, self._umin, self._umax)
        if saturated:
            self.clamped['thrust'] += 1

        self._w_free = zeta - ff  # ζ − g − z̈_d − a_s
        self._sigma_prev = sigma
        self._b_prev = gbar * c / m  # the true cφcθ: what the plant multiplies u by
        self._u_prev = u
        out = AltitudeOutput(u, u_unsat, saturated, sigma, d_hat, e, gbar)
        self._last = out
        return out
