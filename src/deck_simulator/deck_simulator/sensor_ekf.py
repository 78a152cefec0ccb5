"""Local position and velocity as a PX4 EKF2 (GNSS + baro) gives them (pure).

Per axis the error is a bias (per seed, then a random walk) plus a coloured part whose
position and velocity belong together: the velocity error is a Gauss–Markov process and the
position error integrates it while the GNSS/baro fusion pulls it back,
dv = −v/τ_v dt + σ_v √(2/τ_v) dW, dp = (v − p/τ_p) dt, advanced with the exact discretisation
of that linear system. So the reported velocity is the derivative of the coloured position
error (plus the pull-back), not an independent white noise. Sources: docs/world/sensors.md.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import math

from deckland_common.frames import Vec3

from deck_simulator.sensor_models import ModelStreams, TimingParams
from deckland_common import validate as chk


@dataclass(frozen=True, slots=True)
class AxisErrorParams:
    """Error of one EKF output axis (position m, velocity m/s)."""

    bias_std_m: float                 # per seed, at the start of the run
    bias_random_walk_m_rts: float     # K: the bias changes by K √t
    velocity_std_mps: float           # stationary σ of the coloured velocity error
    velocity_tau_s: float             # its correlation time
    position_tau_s: float             # pull-back of the position error by the GNSS/baro fusion

    def __post_init__(self) -> None:
        for name in ('bias_std_m', 'bias_random_walk_m_rts', 'velocity_std_mps'):
            chk.in_range(name, getattr(self, name), 0.0, 100.0)
        chk.positive('velocity_tau_s', self.velocity_tau_s)
        chk.positive('position_tau_s', self.position_tau_s)

    def stationary(self) -> tuple[float, float, float]:
        """Stationary (var v, cov(v, p), var p) of the coloured part: with a = 1/τ_v,
        b = 1/τ_p, P_vv = σ_v², P_vp = σ_v²/(a + b), P_pp = P_vp/b."""
        a, b = 1.0 / self.velocity_tau_s, 1.0 / self.position_tau_s
        pvv = self.velocity_std_mps ** 2
        pvp = pvv / (a + b)
        return pvv, pvp, pvp / b


def _horizontal() -> AxisErrorParams:
    return AxisErrorParams(bias_std_m=0.5, bias_random_walk_m_rts=0.03, velocity_std_mps=0.05,
                           velocity_tau_s=2.0, position_tau_s=4.0)


def _timing() -> TimingParams:
    return TimingParams(rate_hz=50.0, latency_s=0.008, latency_jitter_s=0.003,
                        stamp_mode='arrival', clock_ppm_std=20.0)


def _vertical() -> AxisErrorParams:
    return AxisErrorParams(bias_std_m=0.2, bias_random_walk_m_rts=0.01, velocity_std_mps=0.05,
                           velocity_tau_s=1.0, position_tau_s=2.0)


@dataclass(frozen=True, slots=True)
class LocalPositionParams:
    """EKF2 local position error (defaults: u-blox M9N-class GNSS + baro; docs/world)."""

    horizontal: AxisErrorParams = field(default_factory=_horizontal)
    vertical: AxisErrorParams = field(default_factory=_vertical)
    timing: TimingParams = field(default_factory=_timing)    # LOCAL_POSITION_NED stream

    def __post_init__(self) -> None:
        for name in ('horizontal', 'vertical'):
            chk.require(isinstance(getattr(self, name), AxisErrorParams), name,
                        'must be AxisErrorParams', getattr(self, name))
        chk.require(isinstance(self.timing, TimingParams), 'timing', 'must be TimingParams',
                    self.timing)


# 5-point Gauss–Legendre nodes and weights on [0, 1]
_GL = ((0.04691007703066800, 0.11846344252809454), (0.23076534494715845, 0.23931433524968324),
       (0.5, 0.28444444444444444), (0.76923465505284155, 0.23931433524968324),
       (0.95308992296933200, 0.11846344252809454))


def _phi21(a: float, b: float, s: float) -> float:
    """(e^{as} − e^{bs}) / (a − b), also for a → b (then s e^{as})."""
    d = a - b
    if d == 0.0:
        return s * math.exp(a * s)
    return math.exp(b * s) * math.expm1(d * s) / d


class _Axis:
    """Exact discretisation of (v, p) over a fixed step h, plus the bias random walk."""

    __slots__ = ('bias', 'c11', 'c21', 'c22', 'f11', 'f21', 'f22', 'kb', 'p', 'v')

    def __init__(self, ap: AxisErrorParams, h: float, draw_gauss: list[float]) -> None:
        a, b = -1.0 / ap.velocity_tau_s, -1.0 / ap.position_tau_s
        # Φ(h) = [[e^{ah}, 0], [φ21(h), e^{bh}]] for A = [[a, 0], [1, b]]
        self.f11, self.f21, self.f22 = math.exp(a * h), _phi21(a, b, h), math.exp(b * h)
        # Q = ∫₀ʰ Φ(s) diag(q, 0) Φ(s)ᵀ ds, q = 2 σ_v² / τ_v (composite Gauss–Legendre: the
        # integrands are smooth exponentials; no cancellation when τ_v ≈ τ_p)
        q = 2.0 * ap.velocity_std_mps ** 2 / ap.velocity_tau_s
        m = max(1, math.ceil(2.0 * h * max(-a, -b)))
        w = h / m
        q11 = q21 = q22 = 0.0
        for j in range(m):
            for x, wt in _GL:
                s = (j + x) * w
                e, f = math.exp(a * s), _phi21(a, b, s)
                q11 += wt * e * e
                q21 += wt * e * f
                q22 += wt * f * f
        q11, q21, q22 = q * w * q11, q * w * q21, q * w * q22
        # Cholesky of [[q11, q21], [q21, q22]]
        self.c11 = math.sqrt(q11) if q11 > 0.0 else 0.0
        self.c21 = q21 / self.c11 if self.c11 > 0.0 else 0.0
        r22 = q22 - self.c21 * self.c21
        self.c22 = math.sqrt(r22) if r22 > 0.0 else 0.0
        self.kb = ap.bias_random_walk_m_rts * math.sqrt(h)
        pvv, pvp, ppp = ap.stationary()
        # start from the stationary distribution: v = √Pvv n1, p = Pvp/√Pvv n1 + √(.) n2
        n0, n1, n2 = draw_gauss[0], draw_gauss[1], draw_gauss[2]
        sv = math.sqrt(pvv)
        self.v = sv * n1
        self.p = (pvp / sv * n1 + math.sqrt(max(0.0, ppp - pvp * pvp / pvv)) * n2
                  if sv > 0.0 else 0.0)
        self.bias = ap.bias_std_m * n0

    def step(self, n1: float, n2: float, n3: float) -> None:
        v, p = self.v, self.p
        self.v = self.f11 * v + self.c11 * n1
        self.p = self.f21 * v + self.f22 * p + self.c21 * n1 + self.c22 * n2
        self.bias += self.kb * n3


class LocalPositionModel:
    """ENU position and velocity errors of the EKF output, sampled every ``period_s``.

    ``sample(position, velocity)`` → (position + bias + p, velocity + v) per axis.
    """

    __slots__ = ('axes', 'normal', 'params', 'period_s')

    def __init__(self, params: LocalPositionParams, streams: ModelStreams,
                 period_s: float) -> None:
        chk.positive('period_s', period_s)
        self.params = params
        self.period_s = period_s
        self.normal = streams.normal
        d = streams.draw
        self.axes = [_Axis(ap, period_s, [d.gauss(0.0, 1.0) for _ in range(3)])
                     for ap in (params.horizontal, params.horizontal, params.vertical)]

    def sample(self, position_m: Vec3, velocity_mps: Vec3) -> tuple[Vec3, Vec3]:
        n = self.normal
        ax, ay, az = self.axes[0], self.axes[1], self.axes[2]
        ax.step(n(), n(), n())
        ay.step(n(), n(), n())
        az.step(n(), n(), n())
        return ((position_m[0] + ax.bias + ax.p, position_m[1] + ay.bias + ay.p,
                 position_m[2] + az.bias + az.p),
                (velocity_mps[0] + ax.v, velocity_mps[1] + ay.v, velocity_mps[2] + az.v))
