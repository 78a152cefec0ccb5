"""Short-horizon (0-3 s) prediction of the pad's vertical motion and tilt, with measured error.

A :class:`ChannelPredictor` resamples one scalar stream (the vertical filter's surface height,
or a component of the pad normal from ship telemetry) onto a grid of ``model_dt_s``, splices
it across surface re-bases, and predicts it by an autoregressive model of its increments
(ARIMA(p, 1, 0)) fitted online by recursive least squares with forgetting; the rate is the
central difference of the predicted path. Its uncertainty is measured, not modelled: each
predicted path is scored against the grid values that arrive later, giving the mean-square
error per horizon and the covariance of the rate errors across horizons (the commit-window
finder's input). :class:`DeckPredictor` holds the heave and tilt channels. docs/predictor.md.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import math

from deckland_common.frames import rot_body_to_world

from deckland_common import validate as chk


@dataclass(frozen=True, slots=True)
class ChannelParams:
    """One predicted stream. Defaults: the pad height from the 100 Hz vertical filter."""

    model_dt_s: float = 0.2        # grid step of the model (s)
    ar_order: int = 40             # lags of the increment model: 8 s of memory (> the paper
    #                                triangle's 6.7 s period, > sea-state peak periods 6-7 s)
    forgetting: float = 0.997      # RLS forgetting per grid step: memory 0.2/0.003 ≈ 67 s
    horizon_s: float = 3.0         # longest prediction (s)
    reference_halfwidth: int = 1   # the realised rate the predicted one is scored against:
    #                                central difference over ± this many grid steps
    calibration_memory_s: float = 40.0   # memory of the measured error statistics (s)
    warmup_updates: int = 40       # model updates before its paths are scored (the first
    #                                fits of an AR(40) are poor for ~8 s, docs/predictor.md)
    min_calibration: int = 50      # fully scored paths before the channel is ready (10 s:
    #                                more than one paper-triangle period)
    max_gap_s: float = 1.0         # a longer silence restarts the history
    gate_sigma: float = 8.0        # a sample this many σ off the prediction is an outlier ...
    gate_floor: float = 0.25       # ... and at least this far (channel units)
    gate_restart: int = 10         # this many outliers in a row restart the history
    prior_sigma: float = 1.0       # σ of value and rate before calibration (channel units)
    rls_p0: float = 100.0          # initial RLS covariance (per parameter)
    rls_trace_max: float = 1.0e5   # forgetting is suspended while trace(P)/p exceeds this

    def __post_init__(self) -> None:
        o = 'ChannelParams'
        for name in ('model_dt_s', 'horizon_s', 'calibration_memory_s', 'max_gap_s',
                     'gate_sigma', 'gate_floor', 'prior_sigma', 'rls_p0', 'rls_trace_max'):
            chk.positive(f'{o}.{name}', getattr(self, name))
        chk.integer_at_least(f'{o}.ar_order', self.ar_order, 1)
        chk.integer_at_least(f'{o}.reference_halfwidth', self.reference_halfwidth, 1)
        chk.integer_at_least(f'{o}.min_calibration', self.min_calibration, 1)
        chk.integer_at_least(f'{o}.warmup_updates', self.warmup_updates, 0)
        chk.integer_at_least(f'{o}.gate_restart', self.gate_restart, 1)
        chk.require(chk.is_finite_number(self.forgetting) and 0.9 <= self.forgetting <= 1.0,
                    f'{o}.forgetting', 'must be in [0.9, 1]', self.forgetting)
        chk.require(self.horizon_s >= 2 * self.model_dt_s, f'{o}.horizon_s',
                    'must be at least 2 model steps', self.horizon_s)
        chk.require(self.max_gap_s >= self.model_dt_s, f'{o}.max_gap_s',
                    'must be >= model_dt_s', self.max_gap_s)
        chk.require(self.rls_trace_max >= self.rls_p0, f'{o}.rls_trace_max',
                    'must be >= rls_p0', self.rls_trace_max)


def tilt_channel_params() -> ChannelParams:
    """Pad-normal components from ship telemetry (1-10 Hz, delayed): a coarser grid with the
    same 8 s memory (ship roll periods 4-10 s, FACTS.md), gaps up to 2.5 s bridged; ready
    after ~19 s of telemetry (planner README, "Tilt at contact")."""
    return ChannelParams(model_dt_s=0.5, ar_order=16, forgetting=0.99, max_gap_s=2.5,
                         gate_floor=0.1, prior_sigma=0.3, min_calibration=16,
                         warmup_updates=16)


@dataclass(frozen=True, slots=True)
class ForecastPoint:
    """A channel's prediction at one time: value and rate with their measured σ."""

    valid: bool            # ready and the time is inside the horizon
    value: float           # in the caller's current datum (re-bases applied)
    rate: float            # d value / dt
    sigma_value: float
    sigma_rate: float
    horizon_s: float       # time since the newest grid value the prediction starts from

    @staticmethod
    def invalid(horizon_s: float = math.nan) -> ForecastPoint:
        return ForecastPoint(False, math.nan, math.nan, math.inf, math.inf, horizon_s)


@dataclass(frozen=True, slots=True)
class PathSnapshot:
    """A channel's whole predicted path on its grid, frozen (for the finder and the monitor).

    Index j is the grid time ``origin_s + j·dt_s`` (j = 0..n, n·dt_s = horizon). ``values``
    are in the channel's spliced series (``offset`` converts to the current datum: value +
    offset); ``rate_cov`` is the (n+1)×(n+1) covariance of the rate errors, row-major.
    """

    ready: bool
    origin_s: float
    dt_s: float
    values: tuple[float, ...]
    rates: tuple[float, ...]
    sigma_values: tuple[float, ...]
    sigma_rates: tuple[float, ...]
    rate_cov: tuple[float, ...]
    offset: float
    restarts: int

    @property
    def end_s(self) -> float:
        return self.origin_s + (len(self.values) - 1) * self.dt_s

    def at(self, t_s: float) -> ForecastPoint:
        """Linear interpolation on the grid (clamped to the origin for earlier times)."""
        n = len(self.values) - 1
        if not self.ready or not math.isfinite(t_s) or n < 1:
            return ForecastPoint.invalid()
        h = t_s - self.origin_s
        f = h / self.dt_s if h > 0.0 else 0.0
        if f > n + 1e-9:
            return ForecastPoint.invalid(h)
        j = min(int(f), n - 1)
        r = f - j
        v, s = self.values, self.sigma_values
        q, u = self.rates, self.sigma_rates
        return ForecastPoint(True, v[j] + r * (v[j + 1] - v[j]) + self.offset,
                             q[j] + r * (q[j + 1] - q[j]), s[j] + r * (s[j + 1] - s[j]),
                             u[j] + r * (u[j + 1] - u[j]), h)


class _Path:
    """One predicted path awaiting its scores."""

    __slots__ = ('origin', 'rate_err', 'rates', 'values')

    def __init__(self, origin: int, values: list[float], rates: list[float]) -> None:
        self.origin = origin          # grid index of the newest value it started from
        self.values = values          # predicted values at offsets 1..n+s
        self.rates = rates            # predicted rates at horizons 0..n
        self.rate_err: list[float] = []


class ChannelPredictor:
    """One stream: resampling, re-base splicing, ARIMA(p,1,0) by RLS, measured errors."""

    def __init__(self, params: ChannelParams | None = None) -> None:
        self.params = params if params is not None else ChannelParams()
        p = self.params
        self._dt = p.model_dt_s
        self._order = p.ar_order
        self._n = round(p.horizon_s / p.model_dt_s)
        self._s = p.reference_halfwidth
        self.rejected: dict[str, int] = {'nan': 0, 'out_of_order': 0, 'outlier': 0}
        self.restarts = 0
        self.rebases = 0
        self.cells = 0                       # grid values produced so far
        n1 = self._n + 1
        self._theta = [0.0] * self._order
        self._theta[0] = 1.0                 # prior: the last increment persists
        self._P = [p.rls_p0 if i == j else 0.0 for i in range(self._order)
                   for j in range(i, self._order)]          # upper triangle, flat
        self._trace = p.rls_p0 * self._order
        self._updates = 0
        self._msz = [0.0] * n1               # mean-square value error per horizon
        self._count_z = 0                    # paths scored to the end (values)
        self._cov = [0.0] * (n1 * n1)        # rate-error second moments across horizons
        self._count_v = 0                    # paths scored to the end (rates)
        self.residual_ms = 0.0               # mean-square one-step increment residual
        self._epoch = 0
        self._epoch_seen = False
        self.offset = 0.0                    # current datum − spliced series
        self._gate = p.gate_floor
        self._clear_history()

    # -- history ---------------------------------------------------------------------------
    def _clear_history(self) -> None:
        self._y: list[float] = []            # newest last: grid values of the series
        self._d: list[float] = []            # newest first: the last p increments
        self._k_last = -1                    # grid index of _y[-1]
        self._paths: list[_Path] = []
        self._cur: _Path | None = None       # the path from the newest grid value
        self._blk_k = -1                     # cell of the block being accumulated
        self._blk_n = 0
        self._blk_t = 0.0
        self._blk_y = 0.0
        self._prev: tuple[float, float] | None = None   # (t, y) of the last closed block
        self._last: tuple[float, float] | None = None   # (t, y) of the newest block
        self._t_in = -math.inf               # stamp of the newest accepted sample
        self._outliers = 0

    def restart(self) -> None:
        """Forget the history (the model and the error statistics are kept)."""
        self.restarts += 1
        self._clear_history()

    @property
    def ready(self) -> bool:
        return (self._cur is not None and self._count_v >= self.params.min_calibration
                and self._count_z >= self.params.min_calibration)

    @property
    def origin_s(self) -> float:
        """Grid time of the newest value (predictions start there); -inf before any."""
        return (self._k_last + 0.5) * self._dt if self._y else -math.inf

    @property
    def last_sample_s(self) -> float:
        return self._t_in

    def grid_value(self, k: int) -> float:
        """The spliced series at grid index k (NaN when no longer held)."""
        i = len(self._y) - 1 - (self._k_last - k)
        return self._y[i] if 0 <= i < len(self._y) else math.nan

    @property
    def newest_index(self) -> int:
        return self._k_last

    # -- input -----------------------------------------------------------------------------
    def on_sample(self, t_s: float, value: float, epoch: int = 0,
                  rebase: float = 0.0) -> bool:
        """One sample (stamp = measurement time). ``epoch``/``rebase``: the source's surface
        epoch and its last datum step; a change of epoch by one is spliced out with
        ``rebase``, any other change by the predicted value. False = rejected (counted)."""
        if not math.isfinite(t_s + value + rebase):
            self.rejected['nan'] += 1
            return False
        if t_s <= self._t_in or (self._y and t_s < self.origin_s):
            self.rejected['out_of_order'] += 1
            return False
        if not self._epoch_seen:
            self._epoch, self._epoch_seen = epoch, True
        elif epoch != self._epoch:
            self.rebases += 1
            if epoch == self._epoch + 1:
                self.offset += rebase
            else:
                pred = self._predict_series(t_s)
                if math.isfinite(pred):
                    self.offset = value - pred
                else:
                    self.restart()
                    self.offset = 0.0
            self._epoch = epoch
        y = value - self.offset
        if self._t_in > -math.inf and t_s - self._t_in > self.params.max_gap_s:
            self.restart()
        pred = self._predict_series(t_s)
        if math.isfinite(pred) and abs(y - pred) > self._gate:
            self.rejected['outlier'] += 1
            self._outliers += 1
            if self._outliers >= self.params.gate_restart:
                self.restart()
            return False
        self._outliers = 0
        self._t_in = t_s
        k = math.floor(t_s / self._dt)
        if k != self._blk_k:
            if self._blk_n > 0:
                self._close_block()
            self._blk_k, self._blk_n, self._blk_t, self._blk_y = k, 0, 0.0, 0.0
        self._blk_n += 1
        self._blk_t += t_s
        self._blk_y += y
        return True

    def _close_block(self) -> None:
        """A block's mean (time, value); grid values up to half a step past it are emitted
        by interpolation (extrapolation) from the previous block."""
        tb = self._blk_t / self._blk_n
        yb = self._blk_y / self._blk_n
        last = self._last
        self._prev, self._last = last, (tb, yb)
        if last is None:
            return
        t1, y1 = last
        if tb - t1 > self.params.max_gap_s:
            self.restart()
            self._last = (tb, yb)
            return
        dt = self._dt
        k = self._k_last + 1 if self._y else math.ceil(t1 / dt - 0.5)
        slope = (yb - y1) / (tb - t1) if tb > t1 else 0.0
        while (k + 0.5) * dt <= tb + 0.5 * dt:
            tk = (k + 0.5) * dt
            if tk >= t1 - 0.5 * dt:
                self._push(k, y1 + slope * (tk - t1))
            k += 1

    def _push(self, k: int, y: float) -> None:
        if self._y and k != self._k_last + 1:
            self.restart()
        s = self._s
        self._y.append(y)
        self._k_last = k
        self.cells += 1
        hist = len(self._y)
        if hist > max(self._order + 1, 2 * s + 1, 3) + 1:
            del self._y[0]
        if hist >= 2:
            d = y - self._y[-2]
            if len(self._d) >= self._order:
                self._rls(d)
            self._d.insert(0, d)
            if len(self._d) > self._order:
                self._d.pop()
        self._score(k)
        if len(self._d) >= self._order and len(self._y) >= 3:
            self._update_gate()
            self._cur = self._make_path(k)
            if self._updates >= self.params.warmup_updates:
                self._paths.append(self._cur)

    # -- model -----------------------------------------------------------------------------
    def _rls(self, target: float) -> None:
        """θ ← θ + g e, P ← (P − g (Pφ)ᵀ)/λ with g = Pφ/(λ + φᵀPφ) (φ: the last p increments).

        P is kept as its upper triangle, row-major and flat (the update is symmetric, so half
        of it is enough). Forgetting is skipped while trace(P)/p would exceed
        ``rls_trace_max`` (directions the signal does not excite would otherwise grow as
        λ⁻ᵏ)."""
        phi = self._d
        P = self._P
        th = self._theta
        n = self._order
        lam = self.params.forgetting
        pphi = [0.0] * n
        k = 0
        for i in range(n):                  # Pφ from the upper triangle
            pi = phi[i]
            acc = pphi[i] + P[k] * pi
            k += 1
            for j in range(i + 1, n):
                pij = P[k]
                acc += pij * phi[j]
                pphi[j] += pij * pi
                k += 1
            pphi[i] = acc
        den = lam
        err = target
        for i in range(n):
            den += phi[i] * pphi[i]
            err -= th[i] * phi[i]
        if not (den > 0.0 and math.isfinite(den + err)):
            return
        self.residual_ms += 0.02 * (err * err - self.residual_ms)
        inv = 1.0 / den
        trace = self._trace
        for i in range(n):
            trace -= pphi[i] * pphi[i] * inv
        scale = 1.0 / lam if trace / (n * lam) <= self.params.rls_trace_max else 1.0
        self._trace = trace * scale
        k = 0
        for i in range(n):
            gi = pphi[i] * inv
            th[i] += gi * err
            for j in range(i, n):
                P[k] = (P[k] - gi * pphi[j]) * scale
                k += 1
        self._updates += 1

    def _make_path(self, k: int) -> _Path:
        """Iterate the increment model from grid index k over n + 2 steps; the rate is the
        fourth-order central difference (z₋₂ − 8z₋₁ + 8z₁ − z₂)/12Δ of the path (history
        before the origin), which keeps 99.6 % of a 2.3 s tone where the three-point one
        keeps 95 %."""
        n_steps = self._n + max(self._s, 2)
        th = self._theta
        d = self._d[: self._order]
        z = self._y[-1]
        values = [0.0] * n_steps
        order = self._order
        for i in range(n_steps):
            nxt = 0.0
            for j in range(order):
                nxt += th[j] * d[j]
            d.insert(0, nxt)
            d.pop()
            z += nxt
            values[i] = z
        hist = self._y
        last = len(hist) - 1

        def at(i: int) -> float:
            return values[i - 1] if i >= 1 else hist[last + i]

        inv = 1.0 / (12.0 * self._dt)
        rates = [(at(i - 2) - 8.0 * at(i - 1) + 8.0 * at(i + 1) - at(i + 2)) * inv
                 for i in range(self._n + 1)]
        return _Path(k, values, rates)

    def _predict_series(self, t_s: float) -> float:
        """The current path at t_s (spliced series), NaN without a path or past its end."""
        cur = self._cur
        if cur is None:
            return math.nan
        f = (t_s - self.origin_s) / self._dt
        if f <= 0.0:
            return self._y[-1]
        j = int(f)
        if j >= self._n:
            return math.nan
        a = self._y[-1] if j == 0 else cur.values[j - 1]
        return a + (f - j) * (cur.values[j] - a)

    # -- measured errors -------------------------------------------------------------------
    def _score(self, k: int) -> None:
        """Score every waiting path against grid value k (value) and k − s (rate)."""
        if not self._paths:
            return
        y = self._y[-1]
        s = self._s
        n = self._n
        n1 = n + 1
        mem = self.params.calibration_memory_s / self._dt
        real_rate = math.nan
        if len(self._y) >= 2 * s + 1:
            real_rate = (y - self._y[-1 - 2 * s]) / (2.0 * s * self._dt)
        keep: list[_Path] = []
        for path in self._paths:
            j = k - path.origin
            if 1 <= j <= n:
                e = path.values[j - 1] - y
                a = max(1.0 / (self._count_z + 1.0), 1.0 / mem)
                self._msz[j] += a * (e * e - self._msz[j])
                if j == n:
                    self._count_z += 1
            i = j - s
            if 0 <= i <= n and math.isfinite(real_rate):
                path.rate_err.append(path.rates[i] - real_rate)
            if i >= n:
                if len(path.rate_err) == n1:
                    self._count_v += 1
                    a = max(1.0 / self._count_v, 1.0 / mem)
                    err = path.rate_err
                    cov = self._cov
                    for r in range(n1):
                        er = err[r]
                        row = r * n1
                        for c in range(n1):
                            cov[row + c] += a * (er * err[c] - cov[row + c])
                continue
            keep.append(path)
        self._paths = keep

    def _update_gate(self) -> None:
        """Outlier gate of the samples until the next grid value (at most two steps past the
        origin): gate_sigma × the measured σ two steps ahead, at least gate_floor."""
        p = self.params
        sigma = math.sqrt(self._msz[2]) if self._count_z > 0 else p.prior_sigma
        self._gate = max(p.gate_floor, p.gate_sigma * sigma)

    # -- output ----------------------------------------------------------------------------
    def _sigmas(self) -> tuple[list[float], list[float]]:
        """Measured σ of value and rate per horizon (the prior before calibration)."""
        n1 = self._n + 1
        prior = self.params.prior_sigma
        sz = [math.sqrt(m) for m in self._msz] if self._count_z > 0 else [prior] * n1
        sz[0] = sz[1]                  # the newest grid value carries its own noise
        c = self._cov
        sv = ([math.sqrt(max(c[i * n1 + i], 0.0)) for i in range(n1)] if self._count_v > 0
              else [prior] * n1)
        return sz, sv

    def snapshot(self) -> PathSnapshot:
        """The current predicted path, its measured σ and rate-error covariance (a copy)."""
        cur = self._cur
        n1 = self._n + 1
        if cur is None:
            return PathSnapshot(False, self.origin_s, self._dt, (), (), (), (), (),
                                self.offset, self.restarts)
        values = [self._y[-1], *cur.values[: self._n]]
        sz, sv = self._sigmas()
        prior = self.params.prior_sigma
        cov = (list(self._cov) if self._count_v > 0 else
               [prior * prior if i == j else 0.0 for i in range(n1) for j in range(n1)])
        return PathSnapshot(self.ready, self.origin_s, self._dt, tuple(values),
                            tuple(cur.rates), tuple(sz), tuple(sv), tuple(cov), self.offset,
                            self.restarts)

    def forecast(self, t_s: float) -> ForecastPoint:
        """Value and rate at t_s (current datum) with their measured σ."""
        cur = self._cur
        if not self.ready or cur is None or not math.isfinite(t_s):
            return ForecastPoint.invalid()
        h = t_s - self.origin_s
        f = h / self._dt if h > 0.0 else 0.0
        n = self._n
        if f > n + 1e-9:
            return ForecastPoint.invalid(h)
        j = min(int(f), n - 1)
        r = f - j
        v0 = self._y[-1] if j == 0 else cur.values[j - 1]
        v1 = cur.values[j]
        q = cur.rates
        sz, sv = self._sigmas()
        return ForecastPoint(True, v0 + r * (v1 - v0) + self.offset,
                             q[j] + r * (q[j + 1] - q[j]), sz[j] + r * (sz[j + 1] - sz[j]),
                             sv[j] + r * (sv[j + 1] - sv[j]), h)

    def frequency_hz(self) -> float:
        """The peak of the fitted model's spectrum (of the increments), by a grid search
        refined by a parabola; NaN before the model has a full history."""
        if self._cur is None:
            return math.nan
        nyq = 0.5 / self._dt
        best_f, best_p = math.nan, -math.inf
        m = 400
        powers = [0.0] * (m + 1)
        for i in range(1, m + 1):
            f = nyq * i / (m + 1)
            powers[i] = self._ar_power(f)
            if powers[i] > best_p:
                best_f, best_p = f, powers[i]
        if not math.isfinite(best_f):
            return math.nan
        lo, hi = best_f - nyq / (m + 1), best_f + nyq / (m + 1)
        for _ in range(60):                 # golden-section refinement of the peak
            a = hi - 0.618033988749895 * (hi - lo)
            b = lo + 0.618033988749895 * (hi - lo)
            if self._ar_power(a) > self._ar_power(b):
                hi = b
            else:
                lo = a
        return 0.5 * (lo + hi)

    def _ar_power(self, f_hz: float) -> float:
        w = 2.0 * math.pi * f_hz * self._dt
        re, im = 1.0, 0.0
        for j in range(self._order):
            re -= self._theta[j] * math.cos(w * (j + 1))
            im += self._theta[j] * math.sin(w * (j + 1))
        den = re * re + im * im
        return 1.0 / den if den > 0.0 else math.inf


@dataclass(frozen=True, slots=True)
class DeckPredictorParams:
    """The heave channel (vertical filter surface height) and the two tilt channels."""

    heave: ChannelParams = field(default_factory=ChannelParams)
    tilt: ChannelParams = field(default_factory=tilt_channel_params)

    def __post_init__(self) -> None:
        for name in ('heave', 'tilt'):
            chk.require(isinstance(getattr(self, name), ChannelParams),
                        f'DeckPredictorParams.{name}', 'must be a ChannelParams',
                        getattr(self, name))


@dataclass(frozen=True, slots=True)
class DeckSnapshot:
    """Heave path and, when telemetry feeds them, the pad-normal component paths."""

    heave: PathSnapshot
    tilt_x: PathSnapshot
    tilt_y: PathSnapshot


class DeckPredictor:
    """Pad height (from the vertical filter) and pad tilt (from ship telemetry), predicted.

    Tilt is carried as the horizontal components (n_x, n_y) of the pad's unit normal in the
    map frame (ENU): frame-safe under yaw, and the relative tilt to the vehicle is
    ≈ |n_pad − n_vehicle| for small angles.
    """

    def __init__(self, params: DeckPredictorParams | None = None) -> None:
        self.params = params if params is not None else DeckPredictorParams()
        self.heave = ChannelPredictor(self.params.heave)
        self.tilt_x = ChannelPredictor(self.params.tilt)
        self.tilt_y = ChannelPredictor(self.params.tilt)
        self.rejected: dict[str, int] = {'tilt_invalid': 0}   # besides the channels' own

    def on_surface(self, t_s: float, height_m: float, epoch: int = 0,
                   rebase_m: float = 0.0) -> bool:
        """A vertical-filter sample: surface height (world datum), its epoch and last
        re-base step (``VerticalState.surface_epoch`` / ``last_rebase_m``)."""
        return self.heave.on_sample(t_s, height_m, epoch, rebase_m)

    def on_tilt(self, t_s: float, normal_x: float, normal_y: float) -> bool:
        """Pad normal's horizontal components (map frame), stamped at measurement time."""
        if not math.isfinite(t_s + normal_x + normal_y) or normal_x * normal_x + (
                normal_y * normal_y) >= 1.0:
            self.rejected['tilt_invalid'] += 1
            return False
        ok_x = self.tilt_x.on_sample(t_s, normal_x)
        ok_y = self.tilt_y.on_sample(t_s, normal_y)
        return ok_x and ok_y

    @property
    def ready(self) -> bool:
        return self.heave.ready

    @property
    def tilt_ready(self) -> bool:
        return self.tilt_x.ready and self.tilt_y.ready

    def snapshot(self) -> DeckSnapshot:
        return DeckSnapshot(self.heave.snapshot(), self.tilt_x.snapshot(),
                            self.tilt_y.snapshot())


def pad_normal_xy(roll_rad: float, pitch_rad: float, yaw_rad: float) -> tuple[float, float]:
    """(n_x, n_y): the pad frame's z axis in the map, R e3 of :func:`rot_body_to_world`."""
    r = rot_body_to_world(roll_rad, pitch_rad, yaw_rad)
    return r[0][2], r[1][2]


class TiltCoupling:
    """How the vehicle's tilt follows the deck's, learnt online: per map axis
    n_vehicle ≈ trim + K n_pad (n: the horizontal part of R e3, :func:`pad_normal_xy`).

    A vehicle holding station over a rolling pad tilts with the pad's sway, in phase with the
    roll (a pad h above the roll axis sways with a = h ω² φ: K ≈ −h ω²/g), and with a trim
    against the wind; the relative tilt at contact is then (1 − K) n_pad − trim, smallest
    near the level deck, not at the vehicle's tilt of now (planner README, "Tilt at contact").
    Exponential moments with time constant ``tau_s``; :meth:`model` is None until
    ``min_time_s`` of samples and while the pad's tilt varies by less than ``min_sigma``.
    """

    def __init__(self, tau_s: float = 10.0, min_time_s: float = 5.0,
                 min_sigma: float = 0.005) -> None:
        chk.positive('TiltCoupling.tau_s', tau_s)
        chk.non_negative('TiltCoupling.min_time_s', min_time_s)
        chk.positive('TiltCoupling.min_sigma', min_sigma)
        self.tau_s, self.min_time_s, self.min_sigma = tau_s, min_time_s, min_sigma
        self.reset()

    def reset(self) -> None:
        self._t0 = math.nan
        self._t = math.nan
        # per axis: E[d], E[v], E[d²], E[d v], E[v²]
        self._m = [[0.0] * 5, [0.0] * 5]

    def on_sample(self, t_s: float, pad_nx: float, pad_ny: float, vehicle_nx: float,
                  vehicle_ny: float) -> bool:
        """One pair of normals at ``t_s``; False (ignored) when not finite or not newer."""
        if not (math.isfinite(t_s + pad_nx + pad_ny + vehicle_nx + vehicle_ny)):
            return False
        if math.isnan(self._t):
            self._t0 = self._t = t_s
            for m, d, v in zip(self._m, (pad_nx, pad_ny), (vehicle_nx, vehicle_ny),
                               strict=True):
                m[:] = [d, v, d * d, d * v, v * v]
            return True
        if t_s <= self._t:
            return False
        a = 1.0 - math.exp(-(t_s - self._t) / self.tau_s)
        self._t = t_s
        for m, d, v in zip(self._m, (pad_nx, pad_ny), (vehicle_nx, vehicle_ny), strict=True):
            for i, x in enumerate((d, v, d * d, d * v, v * v)):
                m[i] += a * (x - m[i])
        return True

    def model(self) -> tuple[tuple[float, float], tuple[float, float],
                             tuple[float, float]] | None:
        """((K_x, K_y), (trim_x, trim_y), (σ_x, σ_y) of the residual), or None."""
        if math.isnan(self._t) or self._t - self._t0 < self.min_time_s:
            return None
        gains, trims, sig = [], [], []
        for md, mv, dd, dv, vv in self._m:
            var_d = dd - md * md
            if var_d < self.min_sigma * self.min_sigma:
                return None
            cov = dv - md * mv
            k = max(-3.0, min(1.0, cov / var_d))
            gains.append(k)
            trims.append(mv - k * md)
            sig.append(math.sqrt(max(0.0, vv - mv * mv - 2.0 * k * cov + k * k * var_d)))
        return (gains[0], gains[1]), (trims[0], trims[1]), (sig[0], sig[1])
