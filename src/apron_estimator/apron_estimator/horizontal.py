"""Horizontal Kalman filter of the beacon's relative position and velocity (pure).

Paper (31)-(34): A, H (and our Q, R) are block diagonal, so the 4-state filter is exactly two
scalar closed-form 2-state filters, one per ENU axis (equal to filterpy's ``KalmanFilter`` to
1e-9). Beyond the paper: beacon-minus-vehicle in ENU axes, a variable step with
``Q = diag(0, q dt)``, the control input u = −(vehicle acceleration) integrated exactly for a
held input (:class:`AccelIntegrator`), σ = σ0 + k h, a 2-D χ² NIS gate, acquisition and loss,
and rival hypotheses for false IR blobs, told apart by the lidar's surface level under each
(:class:`HorizontalTracker`). Decisions 6-9 and 12-13c of the package README.
"""

from __future__ import annotations

from bisect import bisect_right
from dataclasses import dataclass
import math

from deckland_common import validate as chk

_UNKNOWN_VAR_M2 = 1.0e4  # reported variance before the first detection


class AxisPairKF:
    """Two independent [position, velocity] Kalman filters (x and y) in scalar closed form.

    Per axis, with P = [[a, b], [b, c]]:
    predict (32): p ← p + v·dt + Δp, v ← v + Δv;
    P ← F P Fᵀ + Q: a ← a + 2 dt b + dt² c, b ← b + dt c, c ← c + q dt.
    update (33)-(34): S = a + r, K = [a, b]/S, p ← p + K₀ ν, v ← v + K₁ ν,
    P ← P − K S Kᵀ: a ← a − a²/S, b ← b − a b/S, c ← c − b²/S.
    """

    __slots__ = ('ax', 'ay', 'bx', 'by', 'cx', 'cy', 'px', 'py', 'vx', 'vy')

    def __init__(self) -> None:
        self.reset(0.0, 0.0, 1.0, 1.0)

    def reset(self, x: float, y: float, pos_var: float, vel_var: float,
              vx: float = 0.0, vy: float = 0.0) -> None:
        self.px, self.vx, self.py, self.vy = x, vx, y, vy
        self.ax = self.ay = pos_var
        self.bx = self.by = 0.0
        self.cx = self.cy = vel_var

    def predict(self, dt: float, q: float, dpx: float = 0.0, dvx: float = 0.0,
                dpy: float = 0.0, dvy: float = 0.0) -> None:
        """(31)-(32) over ``dt`` with control displacements (Δp, Δv) per axis."""
        qdt = q * dt
        self.px += self.vx * dt + dpx
        self.vx += dvx
        self.ax += dt * (2.0 * self.bx + dt * self.cx)
        self.bx += dt * self.cx
        self.cx += qdt
        self.py += self.vy * dt + dpy
        self.vy += dvy
        self.ay += dt * (2.0 * self.by + dt * self.cy)
        self.by += dt * self.cy
        self.cy += qdt

    def scale(self, k: float) -> None:
        """Multiply the state by k (and P by k²): a change of the measurement's scale."""
        k2 = k * k
        self.px *= k
        self.vx *= k
        self.py *= k
        self.vy *= k
        self.ax *= k2
        self.bx *= k2
        self.cx *= k2
        self.ay *= k2
        self.by *= k2
        self.cy *= k2

    def nis(self, zx: float, zy: float, r: float) -> float:
        """Normalised innovation squared νᵀ S⁻¹ ν (S is diagonal: the axes are independent)."""
        nx = zx - self.px
        ny = zy - self.py
        return nx * nx / (self.ax + r) + ny * ny / (self.ay + r)

    def update(self, zx: float, zy: float, r: float) -> None:
        """(33)-(34) with R = diag(r, r)."""
        s = self.ax + r
        nu = zx - self.px
        k0, k1 = self.ax / s, self.bx / s
        self.px += k0 * nu
        self.vx += k1 * nu
        a, b = self.ax, self.bx
        self.ax = a - a * k0
        self.bx = b - b * k0
        self.cx -= b * k1
        s = self.ay + r
        nu = zy - self.py
        k0, k1 = self.ay / s, self.by / s
        self.py += k0 * nu
        self.vy += k1 * nu
        a, b = self.ay, self.by
        self.ay = a - a * k0
        self.by = b - b * k0
        self.cy -= b * k1

    def predicted(self, dt: float, q: float, dpx: float, dvx: float, dpy: float,
                  dvy: float) -> tuple[float, float, float, float, float, float]:
        """(x, y, vx, vy, var_x, var_y) after a predict, without changing the filter."""
        return (self.px + self.vx * dt + dpx, self.py + self.vy * dt + dpy,
                self.vx + dvx, self.vy + dvy,
                self.ax + dt * (2.0 * self.bx + dt * self.cx),
                self.ay + dt * (2.0 * self.by + dt * self.cy))


class DeckAccelKF:
    """The deck's acceleration from the same detections: per ENU axis a [relative position,
    relative velocity, deck acceleration] Kalman filter (white-jerk deck, Singer-type),
    driven by the same control input as :class:`AxisPairKF` (u = −vehicle acceleration).

    Per axis, relative acceleration = a_d − a_vehicle; the vehicle's part enters as the
    control displacements (Δp, Δv), so a_d holds only what the detections say the deck does:
    a vehicle manoeuvre changes the predicted relative state exactly as it changes the
    measured one and moves a_d not at all (no loop through the vehicle; README decision 13e).
    predict: p ← p + v dt + a_d dt²/2 + Δp, v ← v + a_d dt + Δv, a_d ← a_d;
    P ← F P Fᵀ + Q, Q = q [dt⁵/20, dt⁴/8, dt³/6; ·, dt³/3, dt²/2; ·, ·, dt] (white jerk, PSD q).
    update on p with variance r (the paper filter's R).
    """

    __slots__ = ('_p', '_s')

    def __init__(self) -> None:
        self._s = [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0]]          # per axis: p, v, a_d
        self._p = [[1.0, 0.0, 0.0, 1.0, 0.0, 1.0], [1.0, 0.0, 0.0, 1.0, 0.0, 1.0]]
        #            P00  P01  P02  P11  P12  P22

    def reset(self, x: float, y: float, pos_var: float, vel_var: float,
              acc_var: float, vx: float = 0.0, vy: float = 0.0) -> None:
        self._s = [[x, vx, 0.0], [y, vy, 0.0]]
        self._p = [[pos_var, 0.0, 0.0, vel_var, 0.0, acc_var],
                   [pos_var, 0.0, 0.0, vel_var, 0.0, acc_var]]

    def predict(self, dt: float, q: float, dpx: float, dvx: float, dpy: float,
                dvy: float) -> None:
        h = 0.5 * dt * dt
        d3 = dt * dt * dt
        q00, q01, q02 = q * d3 * dt * dt / 20.0, q * d3 * dt / 8.0, q * d3 / 6.0
        q11, q12, q22 = q * d3 / 3.0, q * h, q * dt
        for s, pp, dp, dv in ((self._s[0], self._p[0], dpx, dvx),
                              (self._s[1], self._p[1], dpy, dvy)):
            p, v, a = s
            s[0] = p + v * dt + a * h + dp
            s[1] = v + a * dt + dv
            p00, p01, p02, p11, p12, p22 = pp
            r00 = p00 + dt * p01 + h * p02
            r01 = p01 + dt * p11 + h * p12
            r02 = p02 + dt * p12 + h * p22
            r11 = p11 + dt * p12
            r12 = p12 + dt * p22
            pp[0] = r00 + dt * r01 + h * r02 + q00
            pp[1] = r01 + dt * r02 + q01
            pp[2] = r02 + q02
            pp[3] = r11 + dt * r12 + q11
            pp[4] = r12 + q12
            pp[5] = p22 + q22

    def update(self, zx: float, zy: float, r: float) -> None:
        for s, pp, z in ((self._s[0], self._p[0], zx), (self._s[1], self._p[1], zy)):
            p00, p01, p02, p11, p12, p22 = pp
            sv = p00 + r
            nu = z - s[0]
            k0, k1, k2 = p00 / sv, p01 / sv, p02 / sv
            s[0] += k0 * nu
            s[1] += k1 * nu
            s[2] += k2 * nu
            pp[0] = p00 - k0 * p00
            pp[1] = p01 - k0 * p01
            pp[2] = p02 - k0 * p02
            pp[3] = p11 - k1 * p01
            pp[4] = p12 - k1 * p02
            pp[5] = p22 - k2 * p02

    def shift(self, dx: float, dy: float) -> None:
        """Move the relative position (the track switched to another blob)."""
        self._s[0][0] += dx
        self._s[1][0] += dy

    def scale(self, k: float) -> None:
        """Multiply the state by k (and P by k²): a change of the measurement's scale."""
        k2 = k * k
        for s, pp in zip(self._s, self._p, strict=True):
            for i in range(3):
                s[i] *= k
            for i in range(6):
                pp[i] *= k2

    @property
    def accel_mps2(self) -> tuple[float, float]:
        """The deck acceleration (ENU); constant under prediction."""
        return self._s[0][2], self._s[1][2]

    @property
    def accel_sigma_mps2(self) -> float:
        """Its larger per-axis σ."""
        return math.sqrt(max(self._p[0][5], self._p[1][5], 0.0))


class NoiseScale:
    """A measurement-noise scale λ ≥ 1 learnt from the filter's innovations (covariance
    matching, Mehra 1972): E[ν²] = H P⁻ Hᵀ + R, so each accepted update gives the sample
    (ν² − H P⁻ Hᵀ) / R_nominal, averaged exponentially (``weight`` per sample); the filter
    uses R = λ R_nominal with λ the average clamped to [1, ``max_scale``]. A sensor noisier
    than configured then widens its own gate and weighs less, instead of being gated away.
    Samples are clipped at ``4 · max_scale`` (one outlier moves λ by at most that · weight).
    """

    def __init__(self, weight: float = 0.02, max_scale: float = 25.0) -> None:
        chk.in_range('NoiseScale.weight', weight, 0.0, 1.0)
        chk.require(max_scale >= 1.0, 'NoiseScale.max_scale', 'must be >= 1', max_scale)
        self.weight = float(weight)
        self.max_scale = float(max_scale)
        self.ratio = 1.0
        self.samples = 0

    @property
    def scale(self) -> float:
        """λ: the factor on the nominal measurement variance."""
        return min(self.max_scale, max(1.0, self.ratio))

    def update(self, innovation_sq: float, prior_var: float, nominal_var: float) -> None:
        """One accepted update's ν², H P⁻ Hᵀ and nominal R."""
        if not nominal_var > 0.0:
            return
        x = min((innovation_sq - prior_var) / nominal_var, 4.0 * self.max_scale)
        if x != x:   # NaN
            return
        self.ratio += self.weight * (x - self.ratio)
        self.samples += 1


class AccelIntegrator:
    """Zero-order-held horizontal vehicle acceleration and its running integrals.

    Stores (t, a, V, X) per sample with V = ∫a, X = ∫V from the first sample, so the control
    effect between any two stamps is O(log n): Δv = V(t1) − V(t0),
    Δp = X(t1) − X(t0) − V(t0)(t1 − t0) (exact for piecewise-constant acceleration).
    Acceleration before the first sample is taken as zero.
    """

    __slots__ = ('_ax', '_ay', '_t', '_vx', '_vy', '_xx', '_xy', 'history_s')

    def __init__(self, history_s: float = 3.0) -> None:
        self.history_s = history_s
        self.clear()

    def clear(self) -> None:
        self._t: list[float] = []
        self._ax: list[float] = []
        self._ay: list[float] = []
        self._vx: list[float] = []
        self._vy: list[float] = []
        self._xx: list[float] = []
        self._xy: list[float] = []

    @property
    def last_t(self) -> float | None:
        return self._t[-1] if self._t else None

    def add(self, t_s: float, ax: float, ay: float) -> bool:
        """Append a sample; False (ignored) if t_s is not after the previous sample."""
        ts = self._t
        if not ts:
            vx = vy = xx = xy = 0.0
        else:
            t0 = ts[-1]
            if t_s <= t0:
                return False
            dt = t_s - t0
            a0x, a0y, v0x, v0y = self._ax[-1], self._ay[-1], self._vx[-1], self._vy[-1]
            vx = v0x + a0x * dt
            vy = v0y + a0y * dt
            xx = self._xx[-1] + dt * (v0x + 0.5 * a0x * dt)
            xy = self._xy[-1] + dt * (v0y + 0.5 * a0y * dt)
        ts.append(t_s)
        self._ax.append(ax)
        self._ay.append(ay)
        self._vx.append(vx)
        self._vy.append(vy)
        self._xx.append(xx)
        self._xy.append(xy)
        if ts[0] < t_s - 2.0 * self.history_s and len(ts) > 64:
            k = bisect_right(ts, t_s - self.history_s)
            for lst in (ts, self._ax, self._ay, self._vx, self._vy, self._xx, self._xy):
                del lst[:k]
        return True

    def integrals(self, t_s: float) -> tuple[float, float, float, float]:
        """(V_x, X_x, V_y, X_y) at t_s."""
        ts = self._t
        # usually asked at or after the newest sample (state "now"): no search needed
        k = len(ts) - 1 if ts and t_s >= ts[-1] else bisect_right(ts, t_s) - 1
        if k < 0:
            return 0.0, 0.0, 0.0, 0.0
        dt = t_s - ts[k]
        ax, ay, vx, vy = self._ax[k], self._ay[k], self._vx[k], self._vy[k]
        return (vx + ax * dt, self._xx[k] + dt * (vx + 0.5 * ax * dt),
                vy + ay * dt, self._xy[k] + dt * (vy + 0.5 * ay * dt))

    def displacement(self, t0: float, t1: float) -> tuple[float, float, float, float]:
        """(Δp_x, Δv_x, Δp_y, Δv_y) caused by the acceleration alone over [t0, t1]."""
        ts = self._t
        if not ts or t1 <= ts[0]:
            return 0.0, 0.0, 0.0, 0.0
        # integrals(t0) and integrals(t1) written out (this runs ~4 times per 10 ms tick)
        ax, ay, vx, vy, xx, xy = self._ax, self._ay, self._vx, self._vy, self._xx, self._xy
        last = len(ts) - 1
        k = last if t0 >= ts[last] else bisect_right(ts, t0) - 1
        if k < 0:
            v0x = x0x = v0y = x0y = 0.0
        else:
            h = t0 - ts[k]
            a, b, v, w = ax[k], ay[k], vx[k], vy[k]
            v0x, x0x = v + a * h, xx[k] + h * (v + 0.5 * a * h)
            v0y, x0y = w + b * h, xy[k] + h * (w + 0.5 * b * h)
        k = last if t1 >= ts[last] else bisect_right(ts, t1) - 1
        h = t1 - ts[k]   # k >= 0: t1 > ts[0]
        a, b, v, w = ax[k], ay[k], vx[k], vy[k]
        v1x, x1x = v + a * h, xx[k] + h * (v + 0.5 * a * h)
        v1y, x1y = w + b * h, xy[k] + h * (w + 0.5 * b * h)
        dt = t1 - t0
        return x1x - x0x - v0x * dt, v1x - v0x, x1y - x0y - v0y * dt, v1y - v0y

    def relative_control(self, t0: float, t1: float) -> tuple[float, float, float, float]:
        """(Δp_x, Δv_x, Δp_y, Δv_y) of the *relative* state, u = −a_vehicle, over [t0, t1]."""
        dpx, dvx, dpy, dvy = self.displacement(t0, t1)
        return -dpx, -dvx, -dpy, -dvy


@dataclass(frozen=True)
class HorizontalParams:
    """Horizontal filter and track management."""

    accel_psd_m2ps3: float = 0.2      # q: relative velocity random walk, Q = diag(0, q dt) (31)
    sigma0_m: float = 0.02            # measurement σ = sigma0_m + sigma_per_m · h
    sigma_per_m: float = 0.015        # m per m of height (≈ 0.9° of angular error)
    nis_gate: float = 13.8            # 2-D χ² gate on the NIS (13.8 ≈ 99.9 %)
    acquire_hits: int = 3             # consistent detections before ``tracked``
    lost_timeout_s: float = 1.0       # no accepted detection for this long → lost
    init_vel_sigma_mps: float = 1.5   # velocity σ at (re-)initialisation
    use_accel_input: bool = True      # u = −vehicle acceleration (beyond the paper)
    accel_history_s: float = 3.0
    # rival candidates (false blobs): see the module docstring
    rival_gate_m: float = 0.2         # a detection this close to a rival's offset is that rival
    rival_confirm_hits: int = 5       # net detections (a frame without it takes one back)
    #                                   before a rival makes the target ambiguous
    rival_timeout_s: float = 1.0      # an unresolved rival unseen this long is dropped
    rejected_rival_timeout_s: float = 30.0  # a rejected rival is remembered this long
    ambiguity_min_sep_m: float = 0.15  # rivals closer than this to the track do not matter
    verify_radius_m: float = 0.2      # lidar spot this close to a hypothesis → surface sample
    #                                   (≥ the gear's half-width: ground that close to a
    #                                   hypothesis makes it no landing point anyway)
    verify_dwell_s: float = 0.5       # ... after hovering there this long (filter settled)
    deck_rise_m: float = 0.2          # the beacon's surface is higher by at least this
    max_rivals: int = 4
    # adaptive measurement noise (NoiseScale): R = λ σ² with λ from the innovations
    adapt_noise: bool = True
    adapt_weight: float = 0.02        # per accepted frame (≈ 1 s at 50 Hz)
    adapt_max_scale: float = 25.0     # λ ≤ this (σ up to 5× the configured one)
    # the deck's acceleration (DeckAccelKF, decision 13e): white-jerk PSD, initial σ, and the
    # σ below which it is published (fed forward by the planner)
    deck_jerk_psd_m2ps5: float = 1.0
    deck_accel_init_sigma_mps2: float = 2.0
    deck_accel_max_sigma_mps2: float = 1.0
    deck_accel_max_height_m: float = 1.5   # ... and the camera at most this high

    def __post_init__(self) -> None:
        o = 'HorizontalParams'
        for name in ('deck_jerk_psd_m2ps5', 'deck_accel_init_sigma_mps2',
                     'deck_accel_max_sigma_mps2', 'deck_accel_max_height_m'):
            chk.positive(f'{o}.{name}', getattr(self, name))
        if not isinstance(self.adapt_noise, bool):
            raise ValueError(f'{o}.adapt_noise must be a bool, got {self.adapt_noise!r}')
        chk.in_range(f'{o}.adapt_weight', self.adapt_weight, 0.0, 1.0)
        chk.require(self.adapt_max_scale >= 1.0, f'{o}.adapt_max_scale', 'must be >= 1',
                    self.adapt_max_scale)
        chk.non_negative(f'{o}.accel_psd_m2ps3', self.accel_psd_m2ps3)
        chk.positive(f'{o}.sigma0_m', self.sigma0_m)
        chk.non_negative(f'{o}.sigma_per_m', self.sigma_per_m)
        chk.positive(f'{o}.nis_gate', self.nis_gate)
        chk.integer_at_least(f'{o}.acquire_hits', self.acquire_hits, 1)
        chk.positive(f'{o}.lost_timeout_s', self.lost_timeout_s)
        chk.positive(f'{o}.init_vel_sigma_mps', self.init_vel_sigma_mps)
        if not isinstance(self.use_accel_input, bool):
            raise ValueError(f'{o}.use_accel_input must be a bool, got {self.use_accel_input!r}')
        chk.positive(f'{o}.accel_history_s', self.accel_history_s)
        for name in ('rival_gate_m', 'rival_timeout_s', 'rejected_rival_timeout_s',
                     'ambiguity_min_sep_m', 'verify_radius_m', 'verify_dwell_s',
                     'deck_rise_m'):
            chk.positive(f'{o}.{name}', getattr(self, name))
        chk.integer_at_least(f'{o}.rival_confirm_hits', self.rival_confirm_hits, 1)
        chk.integer_at_least(f'{o}.max_rivals', self.max_rivals, 0)
        if self.accel_history_s < self.lost_timeout_s:
            raise ValueError(f'{o}.accel_history_s must be >= lost_timeout_s')

    def sigma_m(self, height_m: float) -> float:
        return self.sigma0_m + self.sigma_per_m * max(0.0, height_m)


_SAMPLED = -math.inf   # ``t_over`` once the current visit has given its first settled sample


def _sample(t_over: float | None, surface: float | None, t_s: float, surface_m: float,
            dwell_s: float) -> tuple[float, float | None]:
    """Surface evidence while hovering over a hypothesis: nothing for the first ``dwell_s``
    of a visit, then the *lowest* surface level seen during this visit (the previous visit's
    value is replaced at the first settled frame).

    The lowest, not an average: a beacon sits on a deck that extends all around it, so any
    ground seen within ``verify_radius_m`` of a hypothesis (a glint at or just inside a pad
    edge, the lidar spot displaced by the tilt) marks it as not the beacon, and an average
    took in the deck seen while leaving a glint beside the edge (campaign seed 100058: the
    glint's ground 0.05 m averaged up to 0.44 m, too close to the deck's 0.59 m: endless hold).
    The levels are piecewise constant (surface steps only), so the minimum carries no noise.
    ``t_over`` None = not over it; a time = hovering since then; ``_SAMPLED`` = settled."""
    if t_over is None:
        return t_s, surface                 # a visit starts
    if t_over == _SAMPLED:
        return t_over, surface_m if surface is None else min(surface, surface_m)
    if t_s - t_over < dwell_s:
        return t_over, surface
    return _SAMPLED, surface_m              # first settled frame of this visit


class _Rival:
    """A persistent detection the track does not explain: its offset from the track (ENU)."""

    __slots__ = ('dx', 'dy', 'hits', 'rejected', 'surface', 't_over', 't_seen')

    def __init__(self, dx: float, dy: float, t_s: float) -> None:
        self.dx, self.dy = dx, dy
        self.hits = 1
        self.t_seen = t_s
        self.surface: float | None = None   # surface height seen from over it
        self.t_over: float | None = None    # since when the vehicle hovers over it
        self.rejected = False


class HorizontalTracker:
    """Track management around :class:`AxisPairKF` (latency, gating, acquisition, loss).

    States: idle (nothing) → acquiring (a candidate filter, ``hits`` consistent detections)
    → tracking (``hits >= acquire_hits``) → idle again after ``lost_timeout_s`` without an
    accepted detection. The filter lives at the stamp of its last measurement; measurements
    are applied at their own (exposure) stamps and must arrive in order; :meth:`state`
    predicts to any later time without changing the filter.
    """

    def __init__(self, params: HorizontalParams | None = None) -> None:
        self.params = params if params is not None else HorizontalParams()
        self.kf = AxisPairKF()
        self.deck_kf = DeckAccelKF()
        self.accel = AccelIntegrator(self.params.accel_history_s)
        self.rejected: dict[str, int] = {'nan': 0, 'out_of_order': 0, 'gated': 0}
        self.events: dict[str, int] = {'acquired': 0, 'lost': 0, 'restarts': 0,
                                        'rescaled': 0, 'rivals_rejected': 0, 'switches': 0,
                                        'probes': 0}
        #: the camera's noise scale: a property of the sensor, kept across track restarts
        self.noise = NoiseScale(self.params.adapt_weight, self.params.adapt_max_scale)
        self.reset()

    def reset(self) -> None:
        self.mode = 'idle'
        self.hits = 0
        self.t_filter: float | None = None
        self.t_last_frame: float | None = None
        self.t_last_accept: float | None = None
        self.visible = False
        self.last_nis = 0.0
        self.height_m = math.inf              # the height of the last accepted detection
        self.rivals: list[_Rival] = []
        self.surface: float | None = None     # surface height seen from over the track
        self.t_over: float | None = None
        self._amb = (0.0, 0.0)                # squared offsets of the unresolved rivals

    @property
    def ambiguous(self) -> bool:
        """A confirmed, unresolved rival exists (the target may be a false blob)."""
        return self._amb[0] + self._amb[1] > 0.0

    @property
    def tracked(self) -> bool:
        return self.mode == 'tracking'

    def on_accel(self, t_s: float, ax: float, ay: float) -> None:
        """Vehicle horizontal acceleration, ENU, gravity removed."""
        if not math.isfinite(t_s + ax + ay):   # NaN/inf anywhere (overflow needs ~1e308)
            self.rejected['nan'] += 1
            return
        if not self.accel.add(t_s, ax, ay):
            self.rejected['out_of_order'] += 1

    def rescale(self, k: float) -> None:
        """The height used to scale the camera offsets changed by the factor k (surface
        re-base): scale the estimate so that it stays consistent with the measurements."""
        if self.t_filter is None or not (math.isfinite(k) and k > 0.0):
            return
        self.kf.scale(k)
        self.deck_kf.scale(k)
        # the rivals' offsets are measurements in the same scale: a rival not rescaled no
        # longer matches its own blob (a new, unvisited rival each time: endless probing)
        for rv in self.rivals:
            rv.dx *= k
            rv.dy *= k
        self.events['rescaled'] += 1

    def _control(self, t0: float, t1: float) -> tuple[float, float, float, float]:
        if not self.params.use_accel_input:
            return 0.0, 0.0, 0.0, 0.0
        return self.accel.relative_control(t0, t1)

    def _check_lost(self, t_s: float) -> None:
        last = self.t_last_accept
        if self.mode != 'idle' and last is not None and t_s - last > self.params.lost_timeout_s:
            if self.mode == 'tracking':
                self.events['lost'] += 1
            self.mode = 'idle'
            self.hits = 0

    def _start(self, t_s: float, x: float, y: float, r: float,
               prior_velocity_mps: tuple[float, float]) -> None:
        p = self.params
        v0 = p.init_vel_sigma_mps
        vx, vy = prior_velocity_mps
        self.kf.reset(x, y, r, v0 * v0, vx, vy)
        a0 = p.deck_accel_init_sigma_mps2
        self.deck_kf.reset(x, y, r, v0 * v0, a0 * a0, vx, vy)
        self.t_filter = t_s
        self.t_last_accept = t_s
        self.mode = 'acquiring'
        self.hits = 1
        self.last_nis = 0.0
        self.rivals = []          # their offsets were relative to the old track
        self.surface = None
        self.t_over = None
        self._amb = (0.0, 0.0)
        if self.params.acquire_hits <= 1:
            self.mode = 'tracking'
            self.events['acquired'] += 1

    def update(self, t_s: float, candidates: list[tuple[float, float]],
               height_m: float, surface_m: float | None = None,
               spot_m: tuple[float, float] = (0.0, 0.0),
               top_m: float | None = None,
               prior_velocity_mps: tuple[float, float] = (0.0, 0.0)) -> bool:
        """One camera frame: candidate beacon offsets (ENU, m), best first; True if accepted.

        ``t_s`` is the exposure stamp; frames must be strictly in order (else rejected and
        counted). Among the candidates passing the NIS gate the one with the smallest NIS is
        used; others are counted as ``gated`` and feed the rivals. An empty list is a frame
        without a detection. ``surface_m`` is the level of the surface under the vehicle at t_s,
        None if unknown: it resolves rivals. Only differences matter; ApronEstimator passes
        ``VerticalFilter.surface_level_m`` (the surface steps, without the heave).
        ``spot_m`` is where that surface was seen, horizontally from the vehicle (ENU): the
        lidar spot, displaced by the tilt; a hypothesis is sampled while the spot is near it.
        ``top_m`` is the deck's level (the highest surface, the estimator's decision 12d): a
        track sampled more than ``deck_rise_m`` below it is on the ground, not the beacon.
        ``prior_velocity_mps``: the relative velocity (ENU) a track started by this frame
        begins with — the owner's best prior, deck velocity minus the vehicle's (README, D7).
        """
        if not (math.isfinite(t_s) and math.isfinite(height_m)):
            self.rejected['nan'] += 1
            return False
        if self.t_last_frame is not None and t_s <= self.t_last_frame:
            self.rejected['out_of_order'] += 1
            return False
        if self.t_filter is not None and t_s <= self.t_filter:
            self.rejected['out_of_order'] += 1
            return False
        self.t_last_frame = t_s
        self._check_lost(t_s)
        self.visible = False
        good = [c for c in candidates if math.isfinite(c[0]) and math.isfinite(c[1])]
        self.rejected['nan'] += len(candidates) - len(good)
        if not good:
            return False
        sigma = self.params.sigma_m(height_m)
        r0 = sigma * sigma
        r = r0 * self.noise.scale if self.params.adapt_noise else r0
        if self.mode == 'idle' or self.t_filter is None:   # (a track always has a filter time)
            self._start(t_s, good[0][0], good[0][1], r, prior_velocity_mps)
            self.visible = True
            return True
        kf = self.kf
        dpx, dvx, dpy, dvy = self._control(self.t_filter, t_s)
        kf.predict(t_s - self.t_filter, self.params.accel_psd_m2ps3, dpx, dvx, dpy, dvy)
        self.deck_kf.predict(t_s - self.t_filter, self.params.deck_jerk_psd_m2ps5, dpx, dvx,
                             dpy, dvy)
        self.t_filter = t_s
        best_i, best_nis = -1, math.inf
        rejected = [rv for rv in self.rivals if rv.rejected] if self.rivals else None
        for i, c in enumerate(good):
            nis = kf.nis(c[0], c[1], r)
            if nis < best_nis and not (rejected and self._explained(c, nis, r, rejected)):
                best_i, best_nis = i, nis
        if best_i < 0:
            # every detection sits where a rejected rival is expected: none is the track's
            # (or no finite NIS at all, with no rival rejected)
            self.rejected['gated'] += len(good)
            if rejected:
                self._seen_rejected(t_s, good, rejected)
            return False
        if best_nis > self.params.nis_gate:
            self.rejected['gated'] += len(good)
            if self.mode == 'acquiring':
                # inconsistent with the candidate track: start over from this detection
                self.events['restarts'] += 1
                self._start(t_s, good[0][0], good[0][1], r, prior_velocity_mps)
                self.visible = True
                return True
            return False
        self.rejected['gated'] += len(good) - 1
        best = good[best_i]
        if self.params.adapt_noise and self.mode == 'tracking':
            nx, ny = best[0] - kf.px, best[1] - kf.py
            self.noise.update(0.5 * (nx * nx + ny * ny), 0.5 * (kf.ax + kf.ay), r0)
        kf.update(best[0], best[1], r)
        self.deck_kf.update(best[0], best[1], r)
        if self.mode == 'tracking' and (len(good) > 1 or self.rivals):
            self._rivals(t_s, good, best_i, surface_m, spot_m, top_m)
        self.last_nis = best_nis
        self.t_last_accept = t_s
        self.height_m = height_m
        self.visible = True
        if self.mode == 'acquiring':
            self.hits += 1
            if self.hits >= self.params.acquire_hits:
                self.mode = 'tracking'
                self.events['acquired'] += 1
        return True

    # -- rivals (false blobs) ----------------------------------------------------------------
    def _explained(self, c: tuple[float, float], nis_track: float, r: float,
                   rejected: list[_Rival]) -> bool:
        """True if detection ``c`` is closer (NIS) to where a rejected rival is expected
        (track estimate + its offset) than to the track: it must not update the track.

        Without this the track slides onto a rejected glint whenever the beacon leaves the
        image and the track's variance grows (README "False blobs", seed 100031)."""
        kf = self.kf
        for rv in rejected:
            nx = c[0] - kf.px - rv.dx
            ny = c[1] - kf.py - rv.dy
            if nx * nx / (kf.ax + r) + ny * ny / (kf.ay + r) < nis_track:
                return True
        return False

    def _seen_rejected(self, t_s: float, good: list[tuple[float, float]],
                       rejected: list[_Rival]) -> None:
        """A frame that shows only rejected rivals keeps them alive (no offset update: the
        track was not seen in it)."""
        kf = self.kf
        gate2 = self.params.rival_gate_m * self.params.rival_gate_m
        for c in good:
            for rv in rejected:
                if (c[0] - kf.px - rv.dx) ** 2 + (c[1] - kf.py - rv.dy) ** 2 < 4.0 * gate2:
                    rv.t_seen = t_s
                    break

    def _rivals(self, t_s: float, good: list[tuple[float, float]],
                best_i: int, surface_m: float | None,
                spot_m: tuple[float, float] = (0.0, 0.0),
                top_m: float | None = None) -> None:
        """Associate the unexplained detections with rivals, sample the surface under the
        track and the rivals, resolve or probe; refresh the ambiguity spread.

        A rival's offset is measured from the track's own detection in the same frame (not
        from the filter's estimate, whose corrections would shift every offset).
        ``best_i`` indexes the track's own detection in ``good`` (an index, not an identity
        test: compiled, a tuple of floats is a value and has no identity)."""
        p = self.params
        kf = self.kf
        gate2 = p.rival_gate_m * p.rival_gate_m
        rivals = self.rivals
        best = good[best_i]
        for i, c in enumerate(good):
            if i == best_i:
                continue
            dx, dy = c[0] - best[0], c[1] - best[1]
            near, d2min = None, gate2
            for rv in rivals:
                d2 = (dx - rv.dx) ** 2 + (dy - rv.dy) ** 2
                if d2 < d2min:
                    near, d2min = rv, d2
            if near is None:
                if len(rivals) < p.max_rivals:
                    rivals.append(_Rival(dx, dy, t_s))
                elif p.max_rivals:
                    # full: the weakest unconfirmed one (a flicker) makes room
                    weak = min(rivals, key=lambda rv: (rv.rejected or rv.surface is not None,
                                                       rv.hits))
                    if not (weak.rejected or weak.surface is not None) and (
                            weak.hits < p.rival_confirm_hits):
                        rivals[rivals.index(weak)] = _Rival(dx, dy, t_s)
                continue
            near.dx += 0.2 * (dx - near.dx)    # slow average: both points are near static
            near.dy += 0.2 * (dy - near.dy)
            near.hits += 1
            near.t_seen = t_s
        # leaky confirmation: a frame without an unconfirmed rival takes a hit back, so only
        # a blob seen in most frames (a persistent glint) confirms; random flickers that
        # happen to fall in the gate now and then never do
        for rv in rivals:
            if rv.t_seen != t_s and 0 < rv.hits < p.rival_confirm_hits:
                rv.hits -= 1
        # While the track itself is unverified (a probe, or a track restarted on whichever
        # blob was in view) every confirmed, unrejected rival is kept: otherwise the beacon
        # leaving the image while the vehicle hovers over a glint made the glint the only,
        # unambiguous hypothesis and the planner descended on it (seeds 100052, 300054: edge
        # strikes). Once the track is verified, the usual timeouts apply.
        # a track verified on a surface well below the deck's (a glint on the ground beside
        # it) counts as unverified: its rivals are kept (fault_false_blobs seed 100003, pid:
        # the beacon out of view while the vehicle hovered over a ground glint timed out,
        # the glint was descended on: an edge strike)
        low = (self.surface is not None and top_m is not None
               and self.surface < top_m - p.deck_rise_m)
        unverified = self.surface is None or low
        confirm = p.rival_confirm_hits
        rivals[:] = [rv for rv in rivals
                     if (unverified and not rv.rejected
                         and (rv.surface is not None or rv.hits >= confirm))
                     or t_s - rv.t_seen <= (p.rejected_rival_timeout_s if rv.rejected
                                            else p.rival_timeout_s)]
        # surface samples: the lidar spot is on a hypothesis (rel = beacon − vehicle ≈ spot)
        r2 = p.verify_radius_m * p.verify_radius_m
        if surface_m is not None:
            ex, ey = kf.px - spot_m[0], kf.py - spot_m[1]
            if ex * ex + ey * ey < r2:
                self.t_over, self.surface = _sample(self.t_over, self.surface, t_s,
                                                    surface_m, p.verify_dwell_s)
            else:
                self.t_over = None
            for rv in rivals:
                # only confirmed rivals: a sample keeps a rival (above), a flicker must not
                if rv.hits >= p.rival_confirm_hits and (ex + rv.dx) ** 2 + (ey + rv.dy) ** 2 < r2:
                    rv.t_over, rv.surface = _sample(rv.t_over, rv.surface, t_s, surface_m,
                                                    p.verify_dwell_s)
                else:
                    rv.t_over = None
        sep2 = p.ambiguity_min_sep_m * p.ambiguity_min_sep_m
        open_ = [rv for rv in rivals if not rv.rejected and rv.hits >= p.rival_confirm_hits
                 and rv.dx * rv.dx + rv.dy * rv.dy > sep2]
        track_surface = self.surface
        for rv in open_:
            if low and track_surface is not None and (
                    rv.surface is None or rv.surface > track_surface + p.deck_rise_m):
                # the track is on the ground: the beacon is more likely this rival
                self._switch(rv, reject_old=True)
                self.events['switches'] += 1
                self.events['rivals_rejected'] += 1
                break
            if rv.surface is None or self.surface is None:
                continue
            if rv.surface > self.surface + p.deck_rise_m:
                self._switch(rv, reject_old=True)       # the rival is on the deck
                self.events['switches'] += 1
                self.events['rivals_rejected'] += 1
                break
            if self.surface > rv.surface + p.deck_rise_m:
                rv.rejected = True
                self.events['rivals_rejected'] += 1
        # a switch replaces self.rivals: re-read it (a stale list kept the switched-to rival
        # open and the target ambiguous after the switch)
        open_ = [rv for rv in self.rivals if not rv.rejected
                 and rv.hits >= p.rival_confirm_hits and rv.dx * rv.dx + rv.dy * rv.dy > sep2]
        if open_ and self.surface is not None:
            # (only one in view lately: a kept rival that vanished is not worth a flight)
            unvisited = [rv for rv in open_ if rv.surface is None
                         and t_s - rv.t_seen <= p.rival_timeout_s]
            if unvisited:
                # the track is verified, a rival is not: fly there (the planner follows)
                self._switch(unvisited[0], reject_old=False)
                self.events['probes'] += 1
        self._amb = (max((rv.dx * rv.dx for rv in open_), default=0.0),
                     max((rv.dy * rv.dy for rv in open_), default=0.0))

    def _switch(self, rv: _Rival, reject_old: bool) -> None:
        """Move the track onto rival ``rv``; the old track becomes a rival at −offset."""
        kf = self.kf
        dx, dy = rv.dx, rv.dy
        kf.px += dx
        kf.py += dy
        self.deck_kf.shift(dx, dy)
        old = _Rival(-dx, -dy, rv.t_seen)
        old.hits = max(rv.hits, self.params.rival_confirm_hits)
        old.surface = self.surface
        old.rejected = reject_old
        self.surface, self.t_over = rv.surface, None
        for other in self.rivals:
            if other is not rv:
                other.dx -= dx
                other.dy -= dy
        self.rivals = [other for other in self.rivals if other is not rv] + [old]

    def deck_accel(self, t_s: float) -> tuple[float, float] | None:
        """The deck's acceleration (ENU) while tracked, unambiguous, known to
        ``deck_accel_max_sigma_mps2`` and seen from at most ``deck_accel_max_height_m``; else
        None. Higher up, the camera's attitude and timing errors, which scale with the
        height, turn the vehicle's own tilting into apparent deck motion (decision 13e)."""
        since = math.inf if self.t_last_accept is None else t_s - self.t_last_accept
        p = self.params
        if (self.mode != 'tracking' or since > p.lost_timeout_s or self.ambiguous
                or self.height_m > p.deck_accel_max_height_m
                or self.deck_kf.accel_sigma_mps2 > p.deck_accel_max_sigma_mps2):
            return None
        return self.deck_kf.accel_mps2

    def state(self, t_s: float) -> tuple[float, float, float, float, float, float, bool, float]:
        """(x, y, vx, vy, var_x, var_y, tracked, time_since_seen_s) predicted to t_s.

        Does not change the filter. Before the first detection: zeros, variance 1e4 m².
        While :attr:`ambiguous` the variances include the squared offsets of the unresolved
        rivals (the spread of the hypotheses).
        """
        if self.t_filter is None or self.t_last_accept is None or not math.isfinite(t_s):
            return 0.0, 0.0, 0.0, 0.0, _UNKNOWN_VAR_M2, _UNKNOWN_VAR_M2, False, math.inf
        since = max(0.0, t_s - self.t_last_accept)
        tracked = self.mode == 'tracking' and since <= self.params.lost_timeout_s
        kf = self.kf
        dt = t_s - self.t_filter
        ax2, ay2 = self._amb
        if dt <= 0.0:
            return kf.px, kf.py, kf.vx, kf.vy, kf.ax + ax2, kf.ay + ay2, tracked, since
        dpx, dvx, dpy, dvy = self._control(self.t_filter, t_s)
        x, y, vx, vy, var_x, var_y = kf.predicted(dt, self.params.accel_psd_m2ps3,
                                                  dpx, dvx, dpy, dvy)
        return x, y, vx, vy, var_x + ax2, var_y + ay2, tracked, since
