"""When to commit the final descent, and when the deck broke its prediction (pure).

:func:`find_window` scans commit times against the predicted deck (a :class:`DeckSnapshot`):
for each it flies the planner's final descent (:class:`DescentPlan`: height, relative closing
speed, how the vehicle follows the deck) against the predicted deck velocity, finds the
contact, and accepts the commit when the contact's relative normal speed and relative tilt
stay within limits at the stated confidence, around the contact and for ``settle_s`` after.
Every bound is a linear functional of the predicted rate path under its measured error
covariance. :class:`PredictionMonitor` watches a committed prediction and reports when the
deck leaves its interval (the planner's go-around). docs/predictor.md.
"""

from __future__ import annotations

from dataclasses import dataclass
import math
from statistics import NormalDist

from deckland_common import validate as chk
from landing_planner.deck_predictor import (
    ChannelPredictor,
    DeckPredictor,
    DeckSnapshot,
    PathSnapshot,
)


@dataclass(frozen=True, slots=True)
class CommitParams:
    """Limits of the contact and how the window is searched."""

    max_normal_speed_mps: float = 0.15   # issue 13 target: first-contact p95 ≤ 0.15 m/s
    min_normal_speed_mps: float = 0.02   # predicted closing speed at contact at least this
    max_tilt_rad: float = 0.0873         # 5°, issue 13 target on the relative tilt
    confidence: float = 0.95             # of the upper limits together (union bound)
    commit_step_s: float = 0.1           # commit times scanned
    substep_s: float = 0.05              # integration step of the descent
    settle_s: float = 0.3                # limits hold this long after contact (the planner's
    #                                      landed hold time, planner README decision 7)
    min_window_s: float = 0.2            # shorter runs of good commit times are not offered
    require_tilt: bool = False           # no window without a ready tilt prediction

    def __post_init__(self) -> None:
        o = 'CommitParams'
        for name in ('max_normal_speed_mps', 'max_tilt_rad', 'commit_step_s', 'substep_s'):
            chk.positive(f'{o}.{name}', getattr(self, name))
        for name in ('min_normal_speed_mps', 'settle_s', 'min_window_s'):
            chk.non_negative(f'{o}.{name}', getattr(self, name))
        chk.require(self.min_normal_speed_mps < self.max_normal_speed_mps,
                    f'{o}.min_normal_speed_mps', 'must be < max_normal_speed_mps',
                    self.min_normal_speed_mps)
        chk.require(chk.is_finite_number(self.confidence) and 0.5 <= self.confidence < 1.0,
                    f'{o}.confidence', 'must be in [0.5, 1)', self.confidence)
        ratio = self.commit_step_s / self.substep_s
        chk.require(abs(ratio - round(ratio)) < 1e-9, f'{o}.commit_step_s',
                    'must be a whole multiple of substep_s', self.commit_step_s)
        chk.require(isinstance(self.require_tilt, bool), f'{o}.require_tilt',
                    'must be a bool', self.require_tilt)


@dataclass(frozen=True, slots=True)
class DescentPlan:
    """The final descent the planner would fly from a commit.

    The vehicle follows the measured deck through a first-order lag ``follow_lag_s`` (its
    deck-relative loop plus the estimator's lag; 0 = perfectly, ``math.inf`` = a deck-blind
    world-frame descent) and adds the relative closing speed: v_vehicle = v_follow − closing
    speed, dv_follow/dt = (v_deck − v_follow)/follow_lag. Until the commit it only follows.
    With ``feedforward`` it also feeds the predicted deck velocity forward, which it follows
    through its own response lag ``feedforward_lag_s``; the prediction's error still goes
    through ``follow_lag_s``. ``hold_world``: until the commit the vehicle holds its world
    height (at ``vehicle_vz_mps``, with ``follow_lag_s = inf``) instead of its height above
    the pad — a hover above the deck's crests, waiting to descend onto one.
    """

    height_m: float                 # gear above the pad now
    closing_speed_mps: float        # planned relative closing speed after the commit
    follow_lag_s: float = 0.25
    vehicle_vz_mps: float = 0.0     # the vehicle's world vertical speed now (ENU, up +)
    vehicle_normal_x: float = 0.0   # the vehicle's normal (R e3) in the map, at contact:
    vehicle_normal_y: float = 0.0   # this + normal_gain · the pad's normal then (TiltCoupling)
    normal_gain_x: float = 0.0
    normal_gain_y: float = 0.0
    normal_sigma_x: float = 0.0     # σ of the vehicle's normal about that model
    normal_sigma_y: float = 0.0
    feedforward: bool = False
    feedforward_lag_s: float = 0.1  # 1/Λ of the DOB sliding surface (14), Λ = 10.5 s⁻¹
    hold_world: bool = False

    def __post_init__(self) -> None:
        o = 'DescentPlan'
        for name in ('feedforward', 'hold_world'):
            chk.require(isinstance(getattr(self, name), bool), f'{o}.{name}', 'must be a bool',
                        getattr(self, name))
        chk.positive(f'{o}.height_m', self.height_m)
        chk.positive(f'{o}.closing_speed_mps', self.closing_speed_mps)
        chk.require(chk.is_number(self.follow_lag_s) and self.follow_lag_s >= 0.0
                    and not math.isnan(self.follow_lag_s), f'{o}.follow_lag_s',
                    'must be >= 0 (inf allowed)', self.follow_lag_s)
        chk.non_negative(f'{o}.feedforward_lag_s', self.feedforward_lag_s)
        for name in ('vehicle_vz_mps', 'vehicle_normal_x', 'vehicle_normal_y',
                     'normal_gain_x', 'normal_gain_y'):
            chk.finite(f'{o}.{name}', getattr(self, name))
        for name in ('normal_sigma_x', 'normal_sigma_y'):
            chk.non_negative(f'{o}.{name}', getattr(self, name))


@dataclass(frozen=True, slots=True)
class CommitWindow:
    """The next window of commit times (NaN fields when none is found)."""

    found: bool
    reason: str                   # 'ok', 'not_ready', 'tilt_not_ready', 'no_window'
    commit_now: bool = False      # a descent started now lands inside the window
    open_s: float = math.nan      # first good commit time
    close_s: float = math.nan     # last good commit time scanned (the run may go on)
    contact_s: float = math.nan   # contact time of a commit at open_s
    normal_speed_mps: float = math.nan      # predicted relative normal speed there
    normal_speed_hi_mps: float = math.nan   # its bound at the confidence, over the contact
    #                                         time's uncertainty and the settling after it
    tilt_hi_rad: float = math.nan           # the relative tilt's bound (NaN: not checked)
    now_contact_s: float = math.nan         # a commit now, whether it is good or not:
    now_speed_mps: float = math.nan         # its contact time, predicted speed and bound
    now_speed_hi_mps: float = math.nan
    best_commit_s: float = math.nan         # the scanned commit nearest to the limits: the
    best_speed_hi_mps: float = math.nan     # lowest risk (a fallback for a planner that
    best_tilt_hi_rad: float = math.nan      # cannot wait), its speed and tilt bounds
    best_risk: float = math.nan             # max(speed bound / limit, tilt bound / limit)


def _z(p: float) -> float:
    return NormalDist().inv_cdf(p)


def _lag_factor(tau_s: float, dt_s: float) -> float:
    """1 − exp(−dt/τ): 1 for τ = 0 (no lag), 0 for τ = inf (never follows)."""
    if tau_s <= 0.0:
        return 1.0
    return 0.0 if math.isinf(tau_s) else 1.0 - math.exp(-dt_s / tau_s)


def _grid_weights(path: PathSnapshot, t_s: float) -> tuple[int, float]:
    """Grid interval j and fraction r of t_s on the path (clamped to it)."""
    n = len(path.rates) - 1
    f = (t_s - path.origin_s) / path.dt_s
    if f <= 0.0:
        return 0, 0.0
    j = min(int(f), n - 1)
    return j, min(f - j, 1.0)


def _quad(w: list[float], cov: tuple[float, ...], n1: int) -> float:
    """wᵀ C w (C row-major n1×n1) over the entries of w above 1 % of its largest: the follow
    lag's weights decay exponentially; the dropped ones change σ by well under 1 %."""
    big = 0.0
    for x in w:
        big = max(big, abs(x))
    cut = 1e-2 * big
    idx = [i for i in range(n1) if abs(w[i]) > cut]
    acc = 0.0
    for i in idx:
        wi = w[i]
        row = i * n1
        for j in idx:
            acc += wi * w[j] * cov[row + j]
    return max(acc, 0.0)


def find_window(t_now_s: float, deck: DeckSnapshot, plan: DescentPlan,
                params: CommitParams | None = None) -> CommitWindow:
    """The next window of commit times ≥ t_now_s whose contact meets the limits."""
    p = params if params is not None else CommitParams()
    hv = deck.heave
    if not hv.ready or not math.isfinite(t_now_s):
        return CommitWindow(False, 'not_ready')
    tilt = deck.tilt_x.ready and deck.tilt_y.ready
    if p.require_tilt and not tilt:
        return CommitWindow(False, 'tilt_not_ready')
    alpha = 1.0 - p.confidence
    z_v = _z(1.0 - alpha / (2.0 if tilt else 1.0))     # the speed's upper tail
    z_t = _z(1.0 - alpha / 8.0)                           # each tilt axis, two-sided
    n1 = len(hv.rates)
    cov = hv.rate_cov
    dt = p.substep_s
    m_end = math.floor((hv.end_s - t_now_s) / dt + 1e-9)
    if m_end < 2:
        return CommitWindow(False, 'no_window')
    beta = _lag_factor(plan.follow_lag_s, dt)
    beta_mean = _lag_factor(plan.feedforward_lag_s, dt) if plan.feedforward else beta
    c = plan.closing_speed_mps
    rates = hv.rates
    # along the sub-grid: deck velocity, follow velocity, ∫(v_f − v_d), and their weights
    # on the predicted grid rates (for the variances)
    rel: list[float] = []          # c + v_d − v_f: the closing speed if contact happened here
    sig: list[float] = []          # its σ
    gint: list[float] = []         # ∫ (v_f − v_d) dt since t_now
    wint: list[list[float]] = []   # weights of that integral
    vf = plan.vehicle_vz_mps
    wf = [0.0] * n1
    gi = 0.0
    wg = [0.0] * n1
    vd_prev = 0.0
    wd_prev = [0.0] * n1
    for m in range(m_end + 1):
        j, r = _grid_weights(hv, t_now_s + m * dt)
        vd = rates[j] + r * (rates[j + 1] - rates[j])
        wd = [0.0] * n1
        wd[j] = 1.0 - r
        wd[j + 1] += r
        if m > 0:
            vmid = 0.5 * (vd_prev + vd)
            vf_new = vf + beta_mean * (vmid - vf)
            gi += dt * 0.5 * ((vf - vd_prev) + (vf_new - vd))
            wf_new = [a + beta * (0.5 * (b + e) - a) for a, b, e in zip(wf, wd_prev, wd,
                                                                     strict=True)]
            wg = [g + dt * 0.5 * ((a - b) + (an - e))
                  for g, a, b, an, e in zip(wg, wf, wd_prev, wf_new, wd, strict=True)]
            vf, wf = vf_new, wf_new
        rel.append(c + vd - vf)
        sig.append(math.sqrt(_quad([a - b for a, b in zip(wd, wf, strict=True)], cov, n1)))
        gint.append(gi)
        wint.append(wg)
        vd_prev, wd_prev = vd, wd
    step = round(p.commit_step_s / dt)
    settle_m = p.settle_s / dt
    best: CommitWindow | None = None
    run_open = -1.0
    run_first: CommitWindow | None = None
    run_last = -1.0
    now = (math.nan, math.nan, math.nan)
    best_risk, best_t, best_hi, best_tilt = math.inf, math.nan, math.nan, math.nan
    for mc in range(0, m_end + 1, step):
        verdict = _assess(mc, plan.height_m, c, dt, rel, sig, gint, wint, cov, n1, z_v,
                          settle_m, plan.hold_world, p)
        if verdict is None:             # no contact inside the horizon: later commits neither
            break
        ok, t_contact_m, lo_m, hi_m, speed, speed_hi = verdict
        if mc == 0:
            now = (t_now_s + t_contact_m * dt, speed, speed_hi)
        tilt_hi = math.nan
        if tilt and math.isfinite(speed_hi):
            tilt_hi = _tilt_bound(deck, t_now_s, lo_m, hi_m, dt, plan, z_t)
            if ok:
                ok = tilt_hi <= p.max_tilt_rad
        risk = _risk(speed, speed_hi, tilt_hi, p)
        if risk < best_risk:
            best_risk, best_t, best_hi, best_tilt = risk, t_now_s + mc * dt, speed_hi, tilt_hi
        t_c = t_now_s + mc * dt
        if ok:
            if run_first is None:
                run_open = t_c
                run_first = CommitWindow(True, 'ok', False, t_c, t_c,
                                         t_now_s + t_contact_m * dt, speed, speed_hi,
                                         tilt_hi)
            run_last = t_c
        elif run_first is not None:
            if run_last - run_open >= p.min_window_s - 1e-9:
                best = run_first
                break
            run_first = None
    if best is None and run_first is not None and run_last - run_open >= p.min_window_s - 1e-9:
        best = run_first
    if best is None:
        return CommitWindow(False, 'no_window', now_contact_s=now[0], now_speed_mps=now[1],
                            now_speed_hi_mps=now[2], best_commit_s=best_t,
                            best_speed_hi_mps=best_hi, best_tilt_hi_rad=best_tilt,
                            best_risk=best_risk if math.isfinite(best_risk) else math.nan)
    return CommitWindow(True, 'ok', best.open_s <= t_now_s + 0.5 * p.commit_step_s,
                        best.open_s, run_last, best.contact_s, best.normal_speed_mps,
                        best.normal_speed_hi_mps, best.tilt_hi_rad, now[0], now[1], now[2],
                        best_t, best_hi, best_tilt,
                        best_risk if math.isfinite(best_risk) else math.nan)


def _risk(speed: float, speed_hi: float, tilt_hi: float, p: CommitParams) -> float:
    """How far a commit is from the limits: the larger of its speed and tilt bounds, each
    over its limit (≤ 1: inside them; the tilt counts only when predicted). A commit whose
    contact is not a closing one (predicted speed ≤ 0) or lies past the tilt horizon is not
    offered: inf."""
    if not (math.isfinite(speed_hi) and speed > 0.0):
        return math.inf
    r = speed_hi / p.max_normal_speed_mps
    if math.isfinite(tilt_hi):
        r = max(r, tilt_hi / p.max_tilt_rad)
    elif not math.isnan(tilt_hi):
        return math.inf             # past the tilt horizon
    return r


def _assess(mc: int, height_m: float, c: float, dt: float, rel: list[float],
            sig: list[float], gint: list[float], wint: list[list[float]],
            cov: tuple[float, ...], n1: int, z: float, settle_m: float, hold_world: bool,
            p: CommitParams) -> tuple[bool, float, float, float, float, float] | None:
    """A commit at sub-grid index mc: (ok, contact index, checked span lo..hi, predicted
    speed, its upper bound) in sub-grid units; None when there is no contact in the horizon.
    h(t) = height − c (t − t_c) + G(t) − G(t_c), G = ∫ (v_f − v_d); holding the world height,
    h(t_c) = height + G(t_c) instead, and the deck must not reach the vehicle before t_c."""
    m_end = len(rel) - 1
    g0 = 0.0 if hold_world else gint[mc]
    if hold_world and min(gint[: mc + 1]) <= -height_m:
        return False, float(mc), float(mc), float(mc), math.nan, math.nan
    h_prev = height_m + gint[mc] - g0
    for m in range(mc + 1, m_end + 1):
        h = height_m - c * (m - mc) * dt + gint[m] - g0
        if h <= 0.0:
            tm = m - h / (h - h_prev) if h_prev > h else float(m)   # linear root in (m−1, m]
            break
        h_prev = h
    else:
        return None
    j = min(int(tm), m_end - 1)
    r = tm - j
    speed = rel[j] + r * (rel[j + 1] - rel[j])
    s_speed = sig[j] + r * (sig[j + 1] - sig[j])
    if speed <= 0.0:
        return False, tm, tm, tm, speed, speed + z * s_speed
    w0 = wint[0] if hold_world else wint[mc]
    wt = [a + r * (b - a) - e for a, b, e in zip(wint[j], wint[j + 1], w0, strict=True)]
    s_h = math.sqrt(_quad(wt, cov, n1))
    d_m = z * s_h / speed / dt             # contact-time uncertainty, sub-grid units
    lo_m, hi_m = max(tm - d_m, float(mc)), tm + d_m + settle_m
    bound = speed + z * s_speed          # the bound over the whole span: what is checked
    m = math.ceil(lo_m)
    while m <= min(hi_m, float(m_end)):
        bound = max(bound, rel[m] + z * sig[m])
        m += 1
    ok = (hi_m <= m_end and bound <= p.max_normal_speed_mps
          and speed >= p.min_normal_speed_mps)
    return ok, tm, lo_m, hi_m, speed, bound


def _tilt_bound(deck: DeckSnapshot, t0_s: float, lo_m: float, hi_m: float, dt: float,
                plan: DescentPlan, z: float) -> float:
    """Largest bound of |n_pad − n_vehicle| over the span (inf past the tilt horizon), with
    n_vehicle = vehicle_normal + normal_gain · n_pad per axis (σ: the pad's prediction's,
    scaled by |1 − gain|, and the model's, in quadrature)."""
    worst = 0.0
    m = lo_m
    vx, vy = plan.vehicle_normal_x, plan.vehicle_normal_y
    gx, gy = 1.0 - plan.normal_gain_x, 1.0 - plan.normal_gain_y
    sx2, sy2 = plan.normal_sigma_x ** 2, plan.normal_sigma_y ** 2
    while True:
        t = t0_s + m * dt
        fx, fy = deck.tilt_x.at(t), deck.tilt_y.at(t)
        if not (fx.valid and fy.valid):
            return math.inf
        bx = abs(gx * fx.value - vx) + z * math.sqrt((gx * fx.sigma_value) ** 2 + sx2)
        by = abs(gy * fy.value - vy) + z * math.sqrt((gy * fy.sigma_value) ** 2 + sy2)
        worst = max(worst, math.asin(min(1.0, math.hypot(bx, by))))
        if m >= hi_m:
            return worst
        m = min(m + 1.0, hi_m)


@dataclass(frozen=True, slots=True)
class MonitorParams:
    """When a committed prediction counts as broken."""

    sigma: float = 4.0          # |realised − predicted| / σ(horizon) beyond this ...
    confirm: int = 1            # ... on this many grid values in a row
    max_silence_s: float = 0.5  # no sample this long while armed = broken ('stale')

    def __post_init__(self) -> None:
        chk.positive('MonitorParams.sigma', self.sigma)
        chk.integer_at_least('MonitorParams.confirm', self.confirm, 1)
        chk.positive('MonitorParams.max_silence_s', self.max_silence_s)


class PredictionMonitor:
    """Compares the grid values that arrive with a frozen (committed) prediction.

    ``arm`` freezes the heave (and, when ready, tilt) paths; ``update`` checks every new grid
    value of each channel: value against the frozen value, and the realised central-difference
    rate against the frozen rate, each in units of the measured σ at its horizon. Broken when
    that exceeds ``sigma`` on ``confirm`` consecutive values, when a channel restarts, or when
    the heave stream falls silent. Past the frozen horizon the monitor is ``expired``.
    """

    def __init__(self, params: MonitorParams | None = None) -> None:
        self.params = params if params is not None else MonitorParams()
        self.disarm()

    def disarm(self) -> None:
        self.armed = False
        self.broken = False
        self.expired = False
        self.reason = ''
        self.t_broken_s = math.nan
        self.worst_sigma = 0.0
        self._snaps: list[PathSnapshot] = []
        self._next: list[int] = []
        self._run: list[int] = []

    def arm(self, deck: DeckPredictor) -> bool:
        """Freeze the current predictions; False (not armed) if the heave is not ready."""
        self.disarm()
        snap = deck.snapshot()
        if not snap.heave.ready:
            return False
        self._snaps = [snap.heave]
        if snap.tilt_x.ready and snap.tilt_y.ready:
            self._snaps += [snap.tilt_x, snap.tilt_y]
        chans = self._channels(deck)
        self._next = [ch.newest_index + 1 for ch in chans[: len(self._snaps)]]
        self._run = [0] * len(self._snaps)
        self.armed = True
        return True

    @staticmethod
    def _channels(deck: DeckPredictor) -> list[ChannelPredictor]:
        return [deck.heave, deck.tilt_x, deck.tilt_y]

    def update(self, t_s: float, deck: DeckPredictor) -> bool:
        """Check what arrived since the last call; returns ``broken``."""
        if not self.armed or self.broken:
            return self.broken
        chans = self._channels(deck)
        if t_s - deck.heave.last_sample_s > self.params.max_silence_s:
            return self._break(t_s, 'stale')
        expired = True
        for i, snap in enumerate(self._snaps):
            ch = chans[i]
            if ch.restarts != snap.restarts:
                return self._break(t_s, f'restart:{i}')
            s = ch.params.reference_halfwidth
            dt = snap.dt_s
            while self._next[i] <= ch.newest_index:
                k = self._next[i]
                self._next[i] += 1
                tk = (k + 0.5) * dt
                if tk > snap.end_s + 1e-9:
                    continue
                u = 0.0
                pt = snap.at(tk)
                y = ch.grid_value(k)
                if pt.valid and math.isfinite(y):
                    u = abs(y - (pt.value - snap.offset)) / max(pt.sigma_value, 1e-9)
                y0 = ch.grid_value(k - 2 * s)
                tr = (k - s + 0.5) * dt
                if tr >= snap.origin_s and math.isfinite(y0):
                    pr = snap.at(tr)
                    rate = (y - y0) / (2.0 * s * dt)
                    if pr.valid:
                        u = max(u, abs(rate - pr.rate) / max(pr.sigma_rate, 1e-9))
                self.worst_sigma = max(self.worst_sigma, u)
                self._run[i] = self._run[i] + 1 if u > self.params.sigma else 0
                if self._run[i] >= self.params.confirm:
                    return self._break(t_s, f'deviation:{i}')
            expired = expired and (ch.newest_index + 0.5) * dt >= snap.end_s
        self.expired = expired
        return False

    def _break(self, t_s: float, reason: str) -> bool:
        self.broken = True
        self.reason = reason
        self.t_broken_s = t_s
        return True
