"""Vertical state relative to the (heaving) surface below: a 5-state Kalman filter (pure).

Beyond the paper (which feeds the raw lidar range to the altitude loop, Figure 7c): state
``[z_v, v_v, z_s, v_s, a_s]`` (vehicle altitude and speed, surface height, speed and a Singer
acceleration, τ), the vehicle's acceleration as a held input integrated exactly; scalar
updates from the lidar (h = range cosφ cosθ = z_v − z_s), the altitude and optionally v_z.
Surface jumps (a deck edge under the lidar) are re-based, never filtered: ``jump_confirm``
consistent innovations beyond the threshold move z_s and count ``surface_epoch``; shorter
runs are spikes. Equations, Q and the re-base: package README, decisions 10-11 and 10b.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
import math

from deckland_common.contract import VerticalState

from apron_estimator.horizontal import AccelIntegrator, NoiseScale
from deckland_common import validate as chk

_UPPER = tuple((i, j) for i in range(5) for j in range(i, 5))
_SYM = tuple(tuple(_UPPER.index((min(i, j), max(i, j))) for j in range(5)) for i in range(5))


@dataclass(frozen=True)
class VerticalParams:
    """Vertical filter parameters (σ are standard deviations)."""

    sigma_lidar_m: float = 0.03
    sigma_altitude_m: float = 0.3          # local position z (GPS / EKF)
    sigma_vz_mps: float = 0.2              # local velocity z; used if use_vz
    use_vz: bool = True
    vehicle_accel_psd_m2ps3: float = 0.5   # q_v: error of the acceleration input
    surface_accel_sigma_mps2: float = 1.0  # σ_a: stationary σ of the deck acceleration
    surface_tau_s: float = 1.5             # τ of the Singer (Gauss-Markov) deck acceleration
    surface_model: str = 'accel'           # 'accel' (3 surface states) | 'velocity' (2)
    jump_threshold_m: float = 0.2
    jump_sigma: float = 6.0
    jump_confirm: int = 3                  # consecutive consistent samples to re-base
    jump_consistency_m: float = 0.15
    jump_window_s: float = 0.3             # a pending run older than this starts over
    rebase_vs_sigma_mps: float = 0.5       # σ of v_s after a re-base
    altitude_gate: float = 25.0            # NIS gate of the altitude / vz updates
    lidar_timeout_s: float = 0.5
    range_min_m: float = 0.05
    range_max_m: float = 40.0
    max_tilt_rad: float = 0.7              # no lidar fusion beyond this roll/pitch
    late_tolerance_s: float = 0.05         # older stamps (vs the filter) are applied 'now'
    # adaptive lidar noise (horizontal.NoiseScale): R = λ σ_lidar² with λ from the innovations
    adapt_noise: bool = True
    adapt_weight: float = 0.01             # per accepted range (≈ 1 s at 100 Hz)
    adapt_max_scale: float = 25.0          # λ ≤ this (σ up to 5× sigma_lidar_m)

    def __post_init__(self) -> None:
        o = 'VerticalParams'
        for name in ('sigma_lidar_m', 'sigma_altitude_m', 'sigma_vz_mps',
                     'surface_accel_sigma_mps2', 'surface_tau_s', 'jump_threshold_m',
                     'jump_sigma', 'jump_consistency_m', 'jump_window_s',
                     'rebase_vs_sigma_mps', 'altitude_gate', 'lidar_timeout_s',
                     'range_max_m', 'max_tilt_rad'):
            chk.positive(f'{o}.{name}', getattr(self, name))
        chk.non_negative(f'{o}.vehicle_accel_psd_m2ps3', self.vehicle_accel_psd_m2ps3)
        chk.non_negative(f'{o}.range_min_m', self.range_min_m)
        chk.non_negative(f'{o}.late_tolerance_s', self.late_tolerance_s)
        chk.integer_at_least(f'{o}.jump_confirm', self.jump_confirm, 1)
        if self.range_min_m >= self.range_max_m:
            raise ValueError(f'{o}.range_min_m must be < range_max_m')
        if self.surface_model not in ('accel', 'velocity'):
            raise ValueError(f"{o}.surface_model must be 'accel' or 'velocity', "
                             f'got {self.surface_model!r}')
        if not isinstance(self.adapt_noise, bool):
            raise ValueError(f'{o}.adapt_noise must be a bool, got {self.adapt_noise!r}')
        chk.in_range(f'{o}.adapt_weight', self.adapt_weight, 0.0, 1.0)
        if self.adapt_max_scale < 1.0:
            raise ValueError(f'{o}.adapt_max_scale must be >= 1')
        if not isinstance(self.use_vz, bool):
            raise ValueError(f'{o}.use_vz must be a bool, got {self.use_vz!r}')
        if self.max_tilt_rad >= math.pi / 2:
            raise ValueError(f'{o}.max_tilt_rad must be < pi/2')


class VerticalFilter:
    """The 5-state vertical Kalman filter with surface re-basing (see module docstring)."""

    def __init__(self, params: VerticalParams | None = None) -> None:
        self.params = params if params is not None else VerticalParams()
        self._accel_state = self.params.surface_model == 'accel'
        self.accel = AccelIntegrator(history_s=2.0)
        #: the lidar's noise scale (a property of the sensor: kept across resets)
        self.lidar_noise = NoiseScale(self.params.adapt_weight, self.params.adapt_max_scale)
        self.rejected: dict[str, int] = {'nan': 0, 'out_of_order': 0, 'range': 0, 'tilt': 0,
                                         'outlier': 0, 'altitude_gated': 0, 'dropout': 0}
        self.reset()

    def reset(self) -> None:
        self.x = [0.0] * 5
        self._p = [0.0] * 15
        self.t = -math.inf                   # filter time (-inf until initialised)
        self.initialised = False
        self.surface_epoch = 0
        self.last_rebase_m = 0.0
        self.surface_level_m = 0.0           # sum of the re-base steps (see _rebase)
        self.t_lidar_ok: float | None = None
        self.last_h_m: float | None = None   # last tilt-corrected lidar height (raw)
        self.last_range_m: float | None = None
        self.t_last_range: float | None = None  # stamp of last_range_m
        self._t_src = {'lidar': -math.inf, 'alt': -math.inf, 'accel': -math.inf}
        self._alt: tuple[float, float | None] | None = None  # last (z, vz) before init
        self._pending: list[tuple[float, float]] = []         # (t, innovation) of a jump run

    # -- covariance storage ----------------------------------------------------------------
    # P is kept as its upper triangle, flat: [00, 01, 02, 03, 04, 11, 12, 13, 14, 22, 23, 24,
    # 33, 34, 44] (the unrolled predict below is ~3x faster than 5×5 list arithmetic).
    @property
    def P(self) -> list[list[float]]:
        """The full 5×5 covariance (a copy)."""
        u = self._p
        return [[u[_SYM[i][j]] for j in range(5)] for i in range(5)]

    @P.setter
    def P(self, full: list[list[float]]) -> None:
        self._p = [0.5 * (full[i][j] + full[j][i]) for i, j in _UPPER]

    # -- prediction ------------------------------------------------------------------------
    def _predict(self, t_s: float) -> None:
        """(Singer) model over [self.t, t_s]: x ← F x (+ input), P ← F P Fᵀ + Q (unrolled)."""
        dt = t_s - self.t
        if dt <= 0.0:
            return
        p = self.params
        x = self.x
        dp, dv, _, _ = self.accel.displacement(self.t, t_s)
        x[0] += x[1] * dt + dp
        x[1] += dv
        dt2 = dt * dt
        dt3 = dt2 * dt
        h2 = 0.5 * dt2
        sa2 = p.surface_accel_sigma_mps2 * p.surface_accel_sigma_mps2
        tau = p.surface_tau_s
        x[2] += x[3] * dt + h2 * x[4]
        x[3] += x[4] * dt
        (p00, p01, p02, p03, p04, p11, p12, p13, p14, p22, p23, p24, p33, p34,
         p44) = self._p
        if self._accel_state:
            phi = math.exp(-dt / tau)
            qs = 2.0 * sa2 / tau
            q22, q23, q24 = qs * dt3 * dt2 / 20.0, qs * dt3 * dt / 8.0, qs * dt3 / 6.0
            q33, q34, q44 = qs * dt3 / 3.0, qs * h2, sa2 * (1.0 - phi * phi)
        else:
            phi = 0.0
            qs = 2.0 * sa2 * tau
            q22, q23, q24, q33, q34, q44 = qs * dt3 / 3.0, qs * h2, 0.0, qs * dt, 0.0, 0.0
        x[4] *= phi
        qv = p.vehicle_accel_psd_m2ps3
        # M = F P, rows 0, 2, 3 (row 1 is P's, row 4 is φ P's)
        m00, m01, m02 = p00 + dt * p01, p01 + dt * p11, p02 + dt * p12
        m03, m04 = p03 + dt * p13, p04 + dt * p14
        m22 = p22 + dt * p23 + h2 * p24
        m23 = p23 + dt * p33 + h2 * p34
        m24 = p24 + dt * p34 + h2 * p44
        m33, m34 = p33 + dt * p34, p34 + dt * p44
        # P = M Fᵀ + Q (upper triangle)
        self._p = [
            m00 + dt * m01 + qv * dt3 / 3.0, m01 + qv * h2, m02 + dt * m03 + h2 * m04,
            m03 + dt * m04, phi * m04,
            p11 + qv * dt, p12 + dt * p13 + h2 * p14, p13 + dt * p14, phi * p14,
            m22 + dt * m23 + h2 * m24 + q22, m23 + dt * m24 + q23, phi * m24 + q24,
            m33 + dt * m34 + q33, phi * m34 + q34,
            phi * phi * p44 + q44,
        ]
        self.t = t_s

    def _column(self, k: int) -> list[float]:
        u = self._p
        return [u[_SYM[i][k]] for i in range(5)]

    def _scalar_update(self, c: Sequence[float], s: float, nu: float) -> None:
        """x ← x + c ν/S, P ← P − c cᵀ/S with c = P Hᵀ (symmetric by construction).

        Unrolled over the 15 stored entries (the order of _UPPER); each entry is
        ``p_ij − c_i c_j / S`` computed as ``p_ij − (c_i c_j)·(1/S)``, as filterpy's scalar
        case (``test_predict_update_equal_filterpy``).
        """
        c0, c1, c2, c3, c4 = c
        f = nu / s
        x = self.x
        x[0] += c0 * f
        x[1] += c1 * f
        x[2] += c2 * f
        x[3] += c3 * f
        x[4] += c4 * f
        inv = 1.0 / s
        (p00, p01, p02, p03, p04, p11, p12, p13, p14, p22, p23, p24, p33, p34,
         p44) = self._p
        self._p = [
            p00 - c0 * c0 * inv, p01 - c0 * c1 * inv, p02 - c0 * c2 * inv,
            p03 - c0 * c3 * inv, p04 - c0 * c4 * inv,
            p11 - c1 * c1 * inv, p12 - c1 * c2 * inv, p13 - c1 * c3 * inv, p14 - c1 * c4 * inv,
            p22 - c2 * c2 * inv, p23 - c2 * c3 * inv, p24 - c2 * c4 * inv,
            p33 - c3 * c3 * inv, p34 - c3 * c4 * inv,
            p44 - c4 * c4 * inv,
        ]

    def _advance(self, src: str, t_s: float) -> bool:
        """Common stamp handling: per-source order, late tolerance, prediction."""
        if t_s <= self._t_src[src]:
            self.rejected['out_of_order'] += 1
            return False
        if t_s < self.t - self.params.late_tolerance_s:
            self.rejected['out_of_order'] += 1
            return False
        self._t_src[src] = t_s
        if self.initialised:
            self._predict(t_s)
        return True

    # -- inputs ----------------------------------------------------------------------------
    def on_accel(self, t_s: float, az_mps2: float) -> None:
        """Vehicle vertical acceleration (world, gravity removed), held until the next one."""
        if not (math.isfinite(t_s) and math.isfinite(az_mps2)):
            self.rejected['nan'] += 1
            return
        if t_s <= self._t_src['accel']:
            self.rejected['out_of_order'] += 1
            return
        self._t_src['accel'] = t_s
        self.accel.add(t_s, az_mps2, 0.0)

    def on_altitude(self, t_s: float, z_m: float, vz_mps: float | None = None) -> None:
        """Vehicle altitude (local position z, ENU) and optionally its vertical speed."""
        # one isfinite on the sum: a NaN/inf anywhere makes it non-finite (two finite values
        # near 1e308 could overflow and be rejected too: no time or altitude is that large)
        if not math.isfinite(t_s + z_m + (0.0 if vz_mps is None else vz_mps)):
            self.rejected['nan'] += 1
            return
        if not self._advance('alt', t_s):
            return
        if not self.initialised:
            self._alt = (z_m, vz_mps)
            return
        p = self.params
        u = self._p
        s = u[0] + p.sigma_altitude_m ** 2
        nu = z_m - self.x[0]
        if nu * nu / s > p.altitude_gate:
            self.rejected['altitude_gated'] += 1
        else:
            self._scalar_update(u[0:5], s, nu)          # column 0 of P (H = e0)
        if vz_mps is not None and p.use_vz:
            u = self._p
            s = u[5] + p.sigma_vz_mps ** 2
            nu = vz_mps - self.x[1]
            if nu * nu / s > p.altitude_gate:
                self.rejected['altitude_gated'] += 1
            else:
                self._scalar_update((u[1], u[5], u[6], u[7], u[8]), s, nu)   # column 1

    def on_lidar(self, t_s: float, range_m: float | None, roll_rad: float = 0.0,
                 pitch_rad: float = 0.0) -> None:
        """Downward lidar range (None = no return); h = range·cosφ·cosθ."""
        if range_m is None:
            self.rejected['dropout'] += 1
            return
        if not math.isfinite(t_s + range_m + roll_rad + pitch_rad):   # overflow: see on_altitude
            self.rejected['nan' if not math.isinf(range_m) else 'dropout'] += 1
            return
        p = self.params
        if not p.range_min_m < range_m < p.range_max_m:   # at a limit: saturated, no surface
            self.rejected['range'] += 1
            return
        if abs(roll_rad) > p.max_tilt_rad or abs(pitch_rad) > p.max_tilt_rad:
            self.rejected['tilt'] += 1
            return
        if not self._advance('lidar', t_s):
            return
        h = range_m * math.cos(roll_rad) * math.cos(pitch_rad)
        self.last_range_m = range_m
        self.t_last_range = t_s
        self.last_h_m = h
        if not self.initialised:
            self._initialise(t_s, h)
            return
        r0 = p.sigma_lidar_m ** 2
        r = self._lidar_var()
        u = self._p
        c = (u[0] - u[2], u[1] - u[6], u[2] - u[9], u[3] - u[10], u[4] - u[11])
        s = c[0] - c[2] + r
        nu = h - (self.x[0] - self.x[2])
        thr = max(p.jump_threshold_m, p.jump_sigma * math.sqrt(max(s, 0.0)))
        if abs(nu) <= thr:
            if self._pending:
                self.rejected['outlier'] += len(self._pending)
                self._pending = []
            if p.adapt_noise:
                self.lidar_noise.update(nu * nu, c[0] - c[2], r0)
            self._scalar_update(c, s, nu)
            self.t_lidar_ok = t_s
            return
        pend = self._pending
        if pend and ((nu > 0.0) != (pend[0][1] > 0.0)
                     or abs(nu - pend[0][1]) > p.jump_consistency_m
                     or t_s - pend[0][0] > p.jump_window_s):
            self.rejected['outlier'] += len(pend)
            pend.clear()
        pend.append((t_s, nu))
        if len(pend) >= p.jump_confirm:
            jump = -sum(n for _, n in pend) / len(pend)
            pend.clear()
            self._rebase(jump, h)
            self.t_lidar_ok = t_s

    def _lidar_var(self) -> float:
        """The lidar variance used: σ_lidar², times the learnt scale when adapting."""
        p = self.params
        r = p.sigma_lidar_m ** 2
        return r * self.lidar_noise.scale if p.adapt_noise else r

    # -- initialisation and re-basing ------------------------------------------------------
    def _initialise(self, t_s: float, h: float) -> None:
        p = self.params
        if self._alt is not None:
            zv, vz = self._alt
            var_zv = p.sigma_altitude_m ** 2
        else:
            zv, vz, var_zv = h, None, 1.0
        vv, var_vv = (vz, p.sigma_vz_mps ** 2) if vz is not None else (0.0, 1.0)
        self.x = [zv, vv, zv - h, 0.0, 0.0]
        P = [[0.0] * 5 for _ in range(5)]
        P[0][0] = var_zv
        P[1][1] = var_vv
        self.P = P
        self.t = t_s
        self.initialised = True
        self._rebase_covariance(h)
        self.t_lidar_ok = t_s

    def _rebase_covariance(self, h: float) -> None:
        """Surface states re-derived from z_s = z_v − h: copy z_v's correlations."""
        p = self.params
        P = self.P
        r = self._lidar_var()
        for j in range(5):
            P[2][j] = P[j][2] = 0.0
            P[3][j] = P[j][3] = 0.0
            P[4][j] = P[j][4] = 0.0
        P[2][0] = P[0][2] = P[0][0]
        P[2][1] = P[1][2] = P[0][1]
        P[2][2] = P[0][0] + r
        P[3][3] = p.rebase_vs_sigma_mps ** 2
        P[4][4] = p.surface_accel_sigma_mps2 ** 2 if self._accel_state else 0.0
        self.P = P

    def _rebase(self, jump_m: float, h: float) -> None:
        """z_s += jump (the mean of the run's −innovations, i.e. z_v − h averaged over the
        confirming samples); v_s = a_s = 0 with their prior covariance."""
        x = self.x
        self.last_rebase_m = jump_m
        # the level of the surface below without its continuous motion (heave, which the
        # filter tracks) nor the altitude's drift: only the steps, e.g. a deck edge
        self.surface_level_m += jump_m
        self.surface_epoch += 1
        x[2], x[3], x[4] = x[2] + jump_m, 0.0, 0.0
        self._rebase_covariance(h)

    # -- output ----------------------------------------------------------------------------
    def valid_at(self, t_s: float) -> bool:
        return (self.initialised and self.t_lidar_ok is not None
                and t_s - self.t_lidar_ok <= self.params.lidar_timeout_s)

    def height_at(self, t_s: float) -> float:
        """``state(t_s).height_m`` alone (same arithmetic, nothing else built); NaN if the
        filter is not initialised."""
        if not self.initialised or not math.isfinite(t_s):
            return math.nan
        x = self.x
        dt = t_s - self.t
        dp = self.accel.displacement(self.t, t_s)[0] if dt > 0.0 else 0.0
        return (x[0] + x[1] * dt + dp) - (x[2] + x[3] * dt + 0.5 * dt * dt * x[4])

    def state(self, t_s: float) -> VerticalState:
        """Predicted (mean only) to t_s; does not change the filter. t_s may be slightly in
        the past (camera exposure stamps): the same kinematics are extrapolated backwards."""
        if not self.initialised or not math.isfinite(t_s):
            return VerticalState.invalid()
        x = self.x
        dt = t_s - self.t
        if dt > 0.0:
            dp, dv, _, _ = self.accel.displacement(self.t, t_s)
        else:
            dp = dv = 0.0
        zv = x[0] + x[1] * dt + dp
        vv = x[1] + dv
        phi = math.exp(-dt / self.params.surface_tau_s) if self._accel_state else 0.0
        zs = x[2] + x[3] * dt + 0.5 * dt * dt * x[4]
        vs = x[3] + x[4] * dt
        return VerticalState(
            valid=self.valid_at(t_s), height_m=zv - zs, closing_speed_mps=vv - vs,
            vehicle_altitude_m=zv, vehicle_vz_mps=vv, surface_height_m=zs,
            surface_vz_mps=vs, surface_accel_mps2=x[4] * phi if dt > 0.0 else x[4],
            surface_epoch=self.surface_epoch, last_rebase_m=self.last_rebase_m)
