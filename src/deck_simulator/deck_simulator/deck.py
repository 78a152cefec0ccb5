"""Heaving deck (the apron of the paper's section 4.1.2, or a ship's landing pad).

More in the package README, "Module notes" (`deck_simulator.deck`).
"""

from __future__ import annotations

import math
import random

import numpy as np

TWO_PI = 2.0 * math.pi


class NoHeave:
    __slots__ = ()

    def state(self, t_s: float) -> tuple[float, float, float]:
        return 0.0, 0.0, 0.0


class TriangleHeave:
    """Constant speed up and down between ±stroke/2; period 2·stroke/speed."""

    __slots__ = ('half', 'period_s', 'phase', 'speed')

    def __init__(self, stroke_m: float, speed_mps: float, phase: float = 0.0) -> None:
        if not (stroke_m > 0 and speed_mps > 0):
            raise ValueError('triangle heave needs stroke_m > 0 and speed_mps > 0')
        self.half = 0.5 * stroke_m
        self.speed = speed_mps
        self.period_s = 2.0 * stroke_m / speed_mps
        self.phase = phase % 1.0   # fraction of a period; 0 = bottom, moving up

    def state(self, t_s: float) -> tuple[float, float, float]:
        s = (t_s / self.period_s + self.phase) % 1.0
        if s < 0.5:
            return -self.half + self.speed * s * self.period_s, self.speed, 0.0
        return self.half - self.speed * (s - 0.5) * self.period_s, -self.speed, 0.0


class SineHeave:
    __slots__ = ('amp', 'omega', 'phase')

    def __init__(self, amplitude_m: float, period_s: float, phase_rad: float = 0.0) -> None:
        if not (amplitude_m >= 0 and period_s > 0):
            raise ValueError('sine heave needs amplitude_m >= 0 and period_s > 0')
        self.amp = amplitude_m
        self.omega = TWO_PI / period_s
        self.phase = phase_rad

    def state(self, t_s: float) -> tuple[float, float, float]:
        w = self.omega
        a = w * t_s + self.phase
        s, c = math.sin(a), math.cos(a)
        return self.amp * s, self.amp * w * c, -self.amp * w * w * s


def pierson_moskowitz(omega: np.ndarray, hs_m: float, tp_s: float) -> np.ndarray:
    """ITTC / Bretschneider two-parameter spectrum S(ω) [m² s/rad] for Hs and Tp."""
    wp = TWO_PI / tp_s
    w = np.asarray(omega, dtype=float)
    return 5.0 / 16.0 * hs_m ** 2 * wp ** 4 / w ** 5 * np.exp(-1.25 * (wp / w) ** 4)


def jonswap(omega: np.ndarray, hs_m: float, tp_s: float, gamma: float = 3.3) -> np.ndarray:
    """JONSWAP: PM times the peak enhancement γ^r, normalised by (1 − 0.287 ln γ)."""
    wp = TWO_PI / tp_s
    w = np.asarray(omega, dtype=float)
    sigma = np.where(w <= wp, 0.07, 0.09)
    r = np.exp(-((w - wp) ** 2) / (2.0 * sigma ** 2 * wp ** 2))
    return (1.0 - 0.287 * math.log(gamma)) * pierson_moskowitz(w, hs_m, tp_s) * gamma ** r


class SeaStateHeave:
    """Irregular heave from a wave spectrum (Hs = 4 √m0, peak period Tp), seeded."""

    __slots__ = ('amps', 'dt_grid', 'n_grid', 'omegas', 'phases', 'table_a', 'table_v',
                 'table_z')

    def __init__(self, significant_height_m: float, peak_period_s: float, spectrum: str,
                 rng: random.Random, duration_s: float, components: int = 80,
                 jonswap_gamma: float = 3.3, dt_grid_s: float = 0.01) -> None:
        if not (significant_height_m >= 0 and peak_period_s > 0 and components >= 2):
            raise ValueError('sea_state heave needs significant_height_m >= 0, '
                             'peak_period_s > 0 and components >= 2')
        wp = TWO_PI / peak_period_s
        edges = np.linspace(0.4 * wp, 4.0 * wp, components + 1)
        u = np.array([rng.random() for _ in range(components)])
        omegas = edges[:-1] + u * np.diff(edges)
        dw = np.diff(edges)
        if spectrum == 'pierson_moskowitz':
            s = pierson_moskowitz(omegas, significant_height_m, peak_period_s)
        elif spectrum == 'jonswap':
            s = jonswap(omegas, significant_height_m, peak_period_s, jonswap_gamma)
        else:
            raise ValueError(f'unknown spectrum {spectrum!r}')
        amps = np.sqrt(2.0 * s * dw)
        m0 = (significant_height_m / 4.0) ** 2
        total = float(np.sum(amps ** 2) / 2.0)
        if total > 0:
            amps *= math.sqrt(m0 / total)
        phases = np.array([rng.uniform(0.0, TWO_PI) for _ in range(components)])
        self.omegas = [float(w) for w in omegas]
        self.amps = [float(a) for a in amps]
        self.phases = [float(p) for p in phases]
        self.dt_grid = dt_grid_s
        n = math.ceil(max(duration_s, 0.0) / dt_grid_s) + 2
        self.n_grid = n
        z, v, a = self.exact_states(np.arange(n) * dt_grid_s)
        self.table_z = z.tolist()
        self.table_v = v.tolist()
        self.table_a = a.tolist()

    def exact_states(self, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The exact sum and its analytic derivatives at an array of times (numpy)."""
        t = np.asarray(t_s, dtype=float)
        z = np.zeros_like(t)
        v = np.zeros_like(t)
        acc = np.zeros_like(t)
        for w, amp, ph in zip(self.omegas, self.amps, self.phases, strict=True):
            arg = w * t + ph
            s, c = np.sin(arg), np.cos(arg)
            z += amp * s
            v += amp * w * c
            acc -= amp * w * w * s
        return z, v, acc

    def state(self, t_s: float) -> tuple[float, float, float]:
        f = t_s / self.dt_grid
        i = int(f)
        if 0 <= i < self.n_grid - 1 and t_s >= 0.0:
            r = f - i
            tz, tv, ta = self.table_z, self.table_v, self.table_a
            return (tz[i] + r * (tz[i + 1] - tz[i]), tv[i] + r * (tv[i + 1] - tv[i]),
                    ta[i] + r * (ta[i + 1] - ta[i]))
        z = v = a = 0.0
        for w, amp, ph in zip(self.omegas, self.amps, self.phases, strict=True):
            arg = w * t_s + ph
            s, c = math.sin(arg), math.cos(arg)
            z += amp * s
            v += amp * w * c
            a -= amp * w * w * s
        return z, v, a


class Deck:
    """Pad (rectangle, world-axis aligned) whose top heaves about a mean height and drifts.

    ``state(t)`` → ``(cx, cy, z_top, vz, az)``: the beacon / pad-centre position (world ENU),
    the pad-top height above the ground and its vertical velocity and acceleration.
    """

    __slots__ = ('_heave_state', 'cx0', 'cy0', 'drift_x', 'drift_y', 'half_x', 'half_y',
                 'heave', 'mean_z')

    def __init__(self, position_m: tuple[float, float], size_m: tuple[float, float],
                 mean_height_m: float, heave, drift_velocity_mps: tuple[float, float] = (
                     0.0, 0.0)) -> None:
        self.cx0, self.cy0 = float(position_m[0]), float(position_m[1])
        self.half_x, self.half_y = 0.5 * float(size_m[0]), 0.5 * float(size_m[1])
        self.mean_z = float(mean_height_m)
        self.heave = heave
        self._heave_state = heave.state   # bound once: state() runs every physics sub-step
        self.drift_x, self.drift_y = float(drift_velocity_mps[0]), float(drift_velocity_mps[1])

    def state(self, t_s: float) -> tuple[float, float, float, float, float]:
        z, vz, az = self._heave_state(t_s)
        return (self.cx0 + self.drift_x * t_s, self.cy0 + self.drift_y * t_s,
                self.mean_z + z, vz, az)


def make_heave(spec, rng: random.Random, duration_s: float, random_phase: bool = True):
    """Build the heave model of a :class:`deck_simulator.scenario.HeaveSpec`."""
    if spec.model == 'none':
        return NoHeave()
    if spec.model == 'triangle':
        return TriangleHeave(spec.stroke_m, spec.speed_mps,
                             rng.random() if random_phase else 0.0)
    if spec.model == 'sine':
        return SineHeave(spec.amplitude_m, spec.period_s,
                         rng.uniform(0.0, TWO_PI) if random_phase else 0.0)
    if spec.model == 'sea_state':
        return SeaStateHeave(spec.significant_height_m, spec.peak_period_s, spec.spectrum,
                             rng, duration_s, spec.components, spec.jonswap_gamma)
    raise ValueError(f'unknown heave model {spec.model!r}')
