"""Landing planner: the paper's landing procedure (section 3.3) as an explicit state machine.

One handler per mode (a ``_State``: entry actions, transitions, horizontal and vertical
references) and one ``LandingPlanner._switch_to``; the flow, the Step numbers and the decisions
where the paper is silent are in the package README ("State machine"). The search attempts and
pattern are :mod:`landing_planner.search`. Outputs: a horizontal setpoint with velocity
feed-forward and a jerk-limited vertical reference (z_d, ż_d, z̈_d) for the altitude law (16),
above the surface below (a world-altitude ramp for the ``constant_rate`` baseline).

Pure: no rclpy, no wall clock; stepped with explicit ``t_s`` / ``dt_s``.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
import math
from typing import TYPE_CHECKING

from deckland_common.contract import (
    DECK_SOURCE_NONE,
    DECK_SOURCE_PREDICTION,
    VERTICAL_RELATIVE,
    VERTICAL_WORLD_RATE,
    Mode,
    PlannerOutput,
    VehicleState,
)

from landing_planner.commit_window import (
    CommitParams,
    CommitWindow,
    DescentPlan,
    MonitorParams,
    PredictionMonitor,
    find_window,
)
from landing_planner.deck_predictor import (
    ChannelParams,
    DeckPredictor,
    DeckPredictorParams,
    TiltCoupling,
    pad_normal_xy,
    tilt_channel_params,
)
from landing_planner.deck_track import DeckTrack, DeckTrackParams, TrackPoint
from landing_planner.reference import ReferenceGenerator, ReferenceLimits
from landing_planner.search import SearchPattern

if TYPE_CHECKING:  # pragma: no cover - typing only
    from deckland_common.contract import ApronState

__all__ = ['LandingPlanner', 'Mode', 'PlannerOutput', 'PlannerParams', 'VehicleState']

DESCENT_PROFILES = ('deck_relative', 'constant_rate')
_INT_FIELDS = ('max_searches', 'max_go_arounds', 'predictor_warmup_updates',
               'predictor_min_calibration')
_LANDING_MODES = (Mode.APPROACH, Mode.ALIGN, Mode.DESCEND, Mode.FINAL, Mode.SEARCH,
                  Mode.FALLBACK)
_AIRBORNE_MODES = (*_LANDING_MODES, Mode.TAKEOFF, Mode.HOLD)
_DECK_MODES = (Mode.ALIGN, Mode.DESCEND, Mode.FINAL)   # over the deck: align the heading
_MOVING_MPS = 0.2     # a deck once tracked faster than this is "moving" (no Step 14 landing)
_BEST_WAIT_S = 3.0     # FINAL hold past its timeout: wait this long at most for the best commit
_HOLD_LOST_FACTOR = 3.0   # FINAL hold: lost this many target_lost_timeout_s → search


@dataclass(frozen=True, slots=True)
class _TouchdownRule:
    """Final speed, commit plan speed and the LANDED press / hold / band of one deck kind."""

    final_speed_mps: float
    plan_speed_mps: float
    press_m: float
    hold_s: float
    height_tol_m: float


@dataclass(frozen=True, slots=True)
class PlannerParams:
    """Parameters of :class:`LandingPlanner` (SI units, validated at construction)."""

    landing_area_m: tuple[float, float] = (0.0, 0.0)   # where the apron should be (ENU)
    max_xy_dist_m: float = 3.0          # accept a target only this close to the area
    max_target_sigma_m: float = 0.2     # larger reported σ (e.g. rival blobs) → no descent
    acceptance_radius_m: float = 0.15   # horizontally close (paper section 4.2: 0.15 m)
    acceptance_hold_s: float = 0.5      # ... for this long before descending
    acceptance_hysteresis: float = 1.5  # leave the radius × this → pause and re-align
    align_speed_mps: float = 1.0        # slew limit of the setpoint toward the target
    approach_height_m: float = 2.0      # above the surface below (paper section 4.2)
    approach_speed_mps: float = 1.5     # horizontal, GPS leg (Step 2)
    approach_accel_mps2: float = 1.0
    approach_jerk_mps3: float = 2.0
    arrival_radius_m: float = 0.5       # "at the landing area" (vehicle to area)
    arrival_wait_s: float = 2.0         # at the area without a target → search (Step 3)
    vertical_speed_mps: float = 0.5     # climbs/descents to approach/search/hold heights
    vertical_accel_mps2: float = 0.5
    vertical_jerk_mps3: float = 2.0
    descent_speed_mps: float = 0.4      # Step 6, relative to the deck
    final_approach_height_m: float = 0.5  # Step 9 (like PX4 PLD_FAPPR_ALT)
    final_speed_mps: float = 0.08       # Step 10, relative to the deck (campaign: README)
    final_press_m: float = 0.3          # final target this far below contact height
    final_leash_m: float = 0.005        # FINAL: z_d at most this far below the measured h
    leash_filter_s: float = 0.2         # ... h low-passed with this time constant first
    search_height_m: float = 3.5        # Step 12, above the surface below
    search_speed_mps: float = 0.5
    search_radius_m: float = 1.0        # half side of the square pattern
    search_hold_s: float = 2.0          # hover at the pattern centre first
    search_timeout_s: float = 20.0      # per attempt
    max_searches: int = 3               # Step 11
    target_lost_timeout_s: float = 1.0
    fallback_speed_mps: float = 0.5     # Step 14, above the final-approach height
    gear_height_m: float = 0.15
    landed_height_tol_m: float = 0.05
    landed_speed_tol_mps: float = 0.3   # loose: the estimated closing speed is noisy on deck
    landed_hold_s: float = 0.3
    landed_press_m: float = 0.08        # ... while the reference presses this far below
    invalid_timeout_s: float = 0.5      # invalid vertical/vehicle state → safe mode after
    descent_profile: str = 'deck_relative'
    constant_rate_mps: float = 0.5      # 'constant_rate' profile: world descent rate
    # --- issue 13: a moving deck, yaw alignment, touchdown timed to the deck --------------
    timer_debounce_s: float = 0.3       # arrival/acceptance timers reset only after an
    #                                     excursion this long (one noisy sample does not)
    deck_velocity_filter_s: float = 0.5  # DeckTrack: time constant of the predicted velocity
    deck_confirm_s: float = 2.0         # DeckTrack: a beacon run's velocity used after this
    track_timeout_s: float = 60.0       # DeckTrack: a prediction older than this is no track
    deck_yaw_offset_rad: float = 0.0    # heading to hold relative to the deck's (any value)
    yaw_rate_max_radps: float = 0.5     # yaw alignment: rate limit of the heading command
    yaw_tolerance_rad: float = 0.1      # ... DESCEND only within this of the deck heading
    timed_touchdown: bool = True        # FINAL: hold, commit into a predicted window
    commit_clearance_m: float = 0.12    # FINAL hold: gear this far above the pad
    commit_timeout_s: float = 15.0      # FINAL hold without a ready prediction at most this
    #                                     long, then descend as before
    commit_search_s: float = 5.0        # ... with one, look for a window this long (from the
    #                                     later of the hold and the prediction's readiness:
    #                                     any 5 s of the paper triangle hold 1.7 s of downstroke)
    commit_leash_m: float = 0.02        # final_leash_m of a descent committed into a window
    commit_check_s: float = 0.1         # find_window every this often while holding
    commit_follow_lag_s: float = 0.25   # DescentPlan.follow_lag_s (vehicle + estimator lag)
    commit_plan_speed_mps: float = 0.065  # DescentPlan closing speed: what the leashed
    #                                     descent achieves (README), not final_speed_mps
    max_go_arounds: int = 2             # deck broke the prediction: at most this many
    predictor_warmup_updates: int = 20  # ChannelParams.warmup_updates of the heave channel
    predictor_min_calibration: int = 25  # ChannelParams.min_calibration (scored paths)
    # a deck moving under the vehicle (DeckTrack.rms_speed_mps): a firmer final descent and
    # LANDED (thrust off, the weight on the gear) sooner after contact: at hover thrust the gear
    # carries nothing and the swaying deck slides out from under it (README "Firm touchdown")
    moving_final_speed_mps: float = 0.15
    moving_commit_plan_speed_mps: float = 0.10
    moving_landed_press_m: float = 0.04
    moving_landed_hold_s: float = 0.1
    moving_landed_height_tol_m: float = 0.025  # ... within this of gear height (the deck
    #                                     receding under a vehicle 3 cm up refuses travel too)
    # a deck never seen (no fix from the beacon or telemetry) may have moved off the landing
    # area: the search climbs to where the camera's footprint (Pixy 60° x 47°: +-0.58 h x
    # +-0.43 h) is wide, turning so the wide axis sweeps round, and the area gate grows with
    # the distance such a deck can have gone (README "Deck never seen")
    wide_search_height_m: float = 8.0   # above the surface below; <= the beacon's range
    wide_search_climb_mps: float = 2.5   # below PX4 MPC_Z_VEL_MAX_UP (3 m/s)
    wide_search_accel_mps2: float = 1.0  # its climb (PX4 MPC_ACC_UP_MAX: 4 m/s^2)
    wide_search_yaw_rate_radps: float = 0.5
    max_deck_speed_mps: float = 1.0     # wide search: the gate grows this fast (0: fixed)

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name == 'descent_profile':
                if value not in DESCENT_PROFILES:
                    raise ValueError(f'PlannerParams.descent_profile must be one of '
                                     f'{list(DESCENT_PROFILES)}, got {value!r}')
            elif f.name == 'landing_area_m':
                if (not isinstance(value, (tuple, list)) or len(value) != 2
                        or not all(isinstance(v, (int, float)) and math.isfinite(v)
                                   for v in value)):
                    raise ValueError('PlannerParams.landing_area_m must be two finite '
                                     f'numbers (x, y), got {value!r}')
            elif f.name in _INT_FIELDS:
                if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                    raise ValueError(f'PlannerParams.{f.name} must be an int >= 0, '
                                     f'got {value!r}')
            elif f.name == 'timed_touchdown':
                if not isinstance(value, bool):
                    raise ValueError(f'PlannerParams.timed_touchdown must be a bool, '
                                     f'got {value!r}')
            elif f.name == 'max_deck_speed_mps':
                if not _finite(value) or isinstance(value, bool) or value < 0.0:
                    raise ValueError(f'PlannerParams.max_deck_speed_mps must be finite and '
                                     f'>= 0, got {value!r}')
            elif f.name == 'deck_yaw_offset_rad':
                if not _finite(value) or isinstance(value, bool):
                    raise ValueError(f'PlannerParams.deck_yaw_offset_rad must be finite, '
                                     f'got {value!r}')
            elif (isinstance(value, bool) or not isinstance(value, (int, float))
                  or not math.isfinite(value) or value <= 0.0):
                raise ValueError(f'PlannerParams.{f.name} must be a finite number > 0, '
                                 f'got {value!r}')
        if self.acceptance_hysteresis < 1.0:
            raise ValueError('PlannerParams.acceptance_hysteresis must be >= 1')
        if not (self.gear_height_m < self.final_approach_height_m < self.approach_height_m
                <= self.search_height_m <= self.wide_search_height_m):
            raise ValueError('PlannerParams heights must satisfy gear_height_m < '
                             'final_approach_height_m < approach_height_m <= search_height_m '
                             '<= wide_search_height_m')
        if max(self.landed_press_m, self.moving_landed_press_m) >= self.final_press_m:
            raise ValueError('PlannerParams.landed_press_m and moving_landed_press_m must be < '
                             'final_press_m (the '
                             'reference must be able to press that far below contact)')
        if (max(self.final_leash_m, self.commit_leash_m)
                >= min(self.landed_press_m, self.moving_landed_press_m)):
            raise ValueError('PlannerParams.final_leash_m and commit_leash_m must be < '
                             'landed_press_m and moving_landed_press_m')
        if self.max_xy_dist_m < self.acceptance_radius_m:
            raise ValueError('PlannerParams.max_xy_dist_m must be >= acceptance_radius_m')
        if not (self.gear_height_m + self.commit_clearance_m < self.final_approach_height_m):
            raise ValueError('PlannerParams.commit_clearance_m must put the hold below the '
                             'final-approach height')
        if self.predictor_min_calibration < 1:
            raise ValueError('PlannerParams.predictor_min_calibration must be >= 1')


class _Path:
    """Straight-line setpoint motion with a jerk-limited 1-D profile along the segment."""

    __slots__ = ('_gen', '_len', '_start', '_u')

    def __init__(self, limits: ReferenceLimits) -> None:
        self._gen = ReferenceGenerator(limits)
        self._start = (0.0, 0.0)
        self._u = (0.0, 0.0)
        self._len = 0.0

    def start(self, p0: tuple[float, float], p1: tuple[float, float],
              v0: tuple[float, float] = (0.0, 0.0)) -> None:
        dx, dy = p1[0] - p0[0], p1[1] - p0[1]
        n = math.hypot(dx, dy)
        self._start = p0
        self._len = n
        self._u = (dx / n, dy / n) if n > 1e-9 else (0.0, 0.0)
        # keep the along-track speed continuous (cross-track component is dropped)
        self._gen.reset(0.0, max(0.0, v0[0] * self._u[0] + v0[1] * self._u[1]), 0.0)

    def step(self, speed_mps: float, dt_s: float) -> tuple[tuple[float, float],
                                                          tuple[float, float]]:
        s, v, _ = self._gen.step(self._len, speed_mps, dt_s)
        u = self._u
        return ((self._start[0] + u[0] * s, self._start[1] + u[1] * s), (u[0] * v, u[1] * v))

    @property
    def done(self) -> bool:
        return self._gen.z_m >= self._len - 1e-6 and abs(self._gen.z_dot_mps) < 1e-6


def _wrap(a: float) -> float:
    """Angle wrapped to (-π, π]."""
    return math.atan2(math.sin(a), math.cos(a))


def _finite(*values: float) -> bool:
    """True if every value is a finite number (False for non-numbers).

    One ``isfinite`` on the sum: a NaN or inf anywhere makes the sum non-finite. Caveat:
    finite values whose sum overflows (beyond ~1.8e308) are reported non-finite too; no
    planner input (times, metres, m/s, radians) comes anywhere near that.
    """
    try:
        return math.isfinite(sum(values))
    except TypeError:
        return False


@dataclass
class _Latch:
    """Bookkeeping of the current mode (timers, latched targets), renewed by every switch."""

    t_mode: float = 0.0
    entry_pending: bool = True
    hold_height_m: float | None = None
    hold_xy: tuple[float, float] | None = None
    t_in_radius: float | None = None
    t_arrived: float | None = None
    t_landed_cond: float | None = None
    t_invalid: float | None = None
    over_deck: bool = False      # FALLBACK entered over the tracked deck: keep following it
    follow_track: bool = False   # HOLD over the predicted track (a moving deck)
    go_around: bool = False      # ALIGN after a go-around: climb back before descending
    t_excursion: float | None = None   # debounce: since when the timer's condition is off
    committed: bool = False      # FINAL: the descent is committed (else holding)
    windowed: bool = False       # ... into a predicted window (the looser commit leash)
    t_check: float = -math.inf   # FINAL: last find_window
    t_ready: float = math.nan    # FINAL: since when the prediction has been ready (NaN: not)


class _Tick:
    """What one step read from its inputs, handed to the mode handlers."""

    __slots__ = ('apron', 'closing', 'dt_s', 'lost_for', 'rel', 't_s', 'target_ok', 'veh_ok',
                 'vehicle', 'vert_ok')

    def __init__(self, t_s: float, dt_s: float, vehicle: VehicleState, apron: ApronState,
                 veh_ok: bool, target_ok: bool, rel: tuple[float, float], vert_ok: bool,
                 closing: float, lost_for: float) -> None:
        self.t_s = t_s
        self.dt_s = dt_s
        self.vehicle = vehicle
        self.apron = apron
        self.veh_ok = veh_ok
        self.target_ok = target_ok        # tracked, finite, inside the area gate
        self.rel = rel                    # camera offset of the target ((0, 0) if not ok)
        self.vert_ok = vert_ok
        self.closing = closing            # closing speed to the surface below (m/s)
        self.lost_for = lost_for          # since the target was last ok (s)


class LandingPlanner:
    """The landing procedure of section 3.3 as a deterministic, stepped state machine."""

    def __init__(self, params: PlannerParams | None = None) -> None:
        self.params = params or PlannerParams()
        p = self.params
        self.mode = Mode.IDLE
        self.reason = 'initial'
        self.rebases = 0
        self.rejected: dict[str, int] = {'nan': 0, 'out_of_order': 0, 'bad_dt': 0}
        self._state: _State = _STATES[Mode.IDLE]
        self._search = SearchPattern(p.max_searches, p.search_radius_m, p.search_hold_s)
        self._at_rest = _TouchdownRule(p.final_speed_mps, p.commit_plan_speed_mps,
                                       p.landed_press_m, p.landed_hold_s,
                                       p.landed_height_tol_m)
        self._firm = _TouchdownRule(p.moving_final_speed_mps, p.moving_commit_plan_speed_mps,
                                    p.moving_landed_press_m, p.moving_landed_hold_s,
                                    p.moving_landed_height_tol_m)
        self._limits = ReferenceLimits(p.vertical_accel_mps2, p.vertical_jerk_mps3)
        self._wide_limits = ReferenceLimits(p.wide_search_accel_mps2, p.vertical_jerk_mps3)
        self._zref = ReferenceGenerator(self._limits)
        self._zref_ok = False
        self._leash_taken_m = 0.0   # what the leash took back in the landed band (_leash)
        self._leash_h: float | None = None   # the height the leash holds to (low-passed h)
        self._vframe = VERTICAL_RELATIVE
        self._world_floor_m = 0.0
        self._path = _Path(ReferenceLimits(p.approach_accel_mps2, p.approach_jerk_mps3))
        self._path_active = False
        self._path_rel = False      # the path is flown relative to the predicted deck
        self._sp: tuple[float, float] | None = None
        self._ff = (0.0, 0.0)
        self._yaw: float | None = None
        self._t_started = math.nan
        self._t_last: float | None = None
        self._t_target_ok = -math.inf
        self._ambiguous = False     # target σ above max_target_sigma_m (README "False blobs")
        self._rel: tuple[float, float] | None = None   # last tracked camera offset
        self._last_target: tuple[float, float] | None = None
        self._pos: tuple[float, float, float] | None = None
        self._vel: tuple[float, float, float] = (0.0, 0.0, 0.0)
        self._height: float | None = None
        self._surface = 0.0
        self._epoch: int | None = None
        self._l = _Latch()
        self._last_out: PlannerOutput | None = None
        # issue 13: the deck as a moving target, its vertical prediction, the go-arounds
        self._track = DeckTrack(p.landing_area_m, DeckTrackParams(
            velocity_filter_s=p.deck_velocity_filter_s, max_prediction_s=p.track_timeout_s,
            confirm_s=p.deck_confirm_s))
        self._tp: TrackPoint = self._track.at(0.0)
        heave = ChannelParams(warmup_updates=p.predictor_warmup_updates,
                              min_calibration=p.predictor_min_calibration)
        self.predictor = DeckPredictor(DeckPredictorParams(heave=heave,
                                                           tilt=tilt_channel_params()))
        self.tilt_coupling = TiltCoupling()
        self._commit = CommitParams()
        self._monitor = PredictionMonitor(MonitorParams())
        self.go_arounds = 0
        self._accel_ff = (0.0, 0.0)
        self.track_source = self._tp.source

    @property
    def searches(self) -> int:
        """Search attempts since the last ``start_landing`` (Step 11)."""
        return self._search.attempts

    # --- services (std_srvs/Trigger semantics) ------------------------------------------
    # A service call comes between steps: the entry actions of the mode it switches to run at
    # the start of the next step, on that step's inputs (entry_now=False).
    def start_landing(self, t_s: float) -> tuple[bool, str]:
        """Step 1: start the procedure (from IDLE, TAKEOFF or HOLD)."""
        if self.mode in _LANDING_MODES:
            return False, f'already landing (mode {self.mode.name})'
        if self.mode is Mode.LANDED:
            return False, 'landed: take off first'
        self._search.reset()
        self.go_arounds = 0
        self._t_started = t_s       # the area gate grows from here until a fix
        self._yaw = None            # latch the current heading at the next step
        self._switch_to(Mode.APPROACH, t_s, 'start_landing requested (Step 1)', entry_now=False)
        return True, 'landing started'

    def abort(self, t_s: float) -> tuple[bool, str]:
        """Climb to the approach height and hold position; a later start is allowed."""
        if self.mode in (Mode.IDLE, Mode.LANDED):
            return False, f'nothing to abort (mode {self.mode.name})'
        if self.mode is Mode.HOLD:
            return True, 'already holding'
        self._switch_to(Mode.HOLD, t_s, f'abort requested in {self.mode.name}', entry_now=False)
        return True, 'aborted: climbing to the approach height and holding'

    def takeoff(self, t_s: float) -> tuple[bool, str]:
        """Climb to the approach height over the current position, then HOLD."""
        if self.mode not in (Mode.IDLE, Mode.LANDED):
            return False, f'already airborne (mode {self.mode.name})'
        self._yaw = None
        self._switch_to(Mode.TAKEOFF, t_s, 'takeoff requested', entry_now=False)
        return True, 'taking off'

    # --- main step -----------------------------------------------------------------------
    def step(self, t_s: float, dt_s: float, vehicle: VehicleState,
             apron: ApronState) -> PlannerOutput:
        """Advance the state machine and the references by ``dt_s`` at time ``t_s``."""
        if not _finite(t_s):
            self.rejected['nan'] += 1
            return self._hold_output(t_s)
        if self._t_last is not None and t_s < self._t_last:
            self.rejected['out_of_order'] += 1
            return self._hold_output(t_s)
        if not (_finite(dt_s) and dt_s > 0.0):
            self.rejected['bad_dt'] += 1
            return self._hold_output(t_s)
        self._t_last = t_s
        p = self.params
        veh_ok = self._read_vehicle(vehicle)
        target_ok, rel = self._read_target(t_s, apron)
        vert_ok, closing = self._read_vertical(apron)
        self.track_source = self._track.update(t_s, apron, target_ok)
        self._tp = self._track.at(t_s)
        self._feed_predictor(t_s, apron, vert_ok, vehicle if veh_ok else None)
        self._accel_ff = (0.0, 0.0)

        if self._pos is None:   # nothing known about the vehicle yet
            return self._emit(t_s, self._placeholder_height(), 0.0, 0.0, True)
        if self._yaw is None and veh_ok:
            self._yaw = float(vehicle.yaw_rad)   # heading held from (re)start on
        if self._sp is None:
            self._sp = (self._pos[0], self._pos[1])
        if not self._zref_ok and self._height is not None:
            self._zref.reset(self._height)
            self._zref_ok = True
        if self._l.entry_pending:
            self._run_entry()

        tk = _Tick(t_s, dt_s, vehicle, apron, veh_ok, target_ok, rel, vert_ok, closing,
                   t_s - self._t_target_ok)
        paused = self._safe_mode(tk)
        if not paused:
            self._state.run(self, tk)          # transitions of the current mode

        # --- references of the (new) mode ---------------------------------------------------
        self._update_frame()
        state = self._state
        state.horizontal(self, tk)
        wide = self.mode is Mode.SEARCH and self._wide_search()
        if self.mode in _DECK_MODES:
            self._align_yaw(dt_s)
        elif wide and self._yaw is not None:
            self._yaw = _wrap(self._yaw + p.wide_search_yaw_rate_radps * dt_s)
        z_target, z_speed = self._stop_here() if paused else state.vertical(self, tk)
        if self._zref_ok:
            self._zref.limits = self._wide_limits if wide else self._limits
            self._zref.step(z_target, z_speed, dt_s)
            if vert_ok:
                self._leash(dt_s)
            else:
                self._leash_h = None
        thrust = self.mode is not Mode.LANDED
        if self.mode is Mode.IDLE and (vehicle.landed or (
                self._height is not None
                and self._height <= p.gear_height_m + p.landed_height_tol_m)):
            thrust = False
        z, zd, zdd = self._zref.state() if self._zref_ok else (
            self._placeholder_height(), 0.0, 0.0)
        return self._emit(t_s, z, zd, zdd, thrust)

    def _safe_mode(self, tk: _Tick) -> bool:
        """Invalid vehicle or vertical state for ``invalid_timeout_s``: FINAL (and DESCEND below
        the final-approach height) falls back to a slow descent where it is, the other airborne
        modes HOLD. True while the transitions and the vertical target are paused."""
        if tk.veh_ok and tk.vert_ok:
            self._l.t_invalid = None
            return False
        if self.mode not in _AIRBORNE_MODES or not self._zref_ok:
            return False
        p = self.params
        t_s = tk.t_s
        t_invalid = self._l.t_invalid
        if t_invalid is None:
            t_invalid = self._l.t_invalid = t_s
        if t_s - t_invalid >= p.invalid_timeout_s:
            what = 'vertical state' if not tk.vert_ok else 'vehicle state'
            low = self._height is not None and self._height <= p.final_approach_height_m
            if self.mode is Mode.FINAL or (self.mode is Mode.DESCEND and low):
                # "where it is" is the deck: the camera still sees it, so the vehicle stays
                # over it (a GPS hold drifts off the pad with the GPS error)
                self._switch_to(Mode.FALLBACK, t_s, f'{what} invalid in {self.mode.name}: '
                                'slow descent where it is (safe mode)', over_deck=tk.target_ok)
            elif self.mode not in (Mode.HOLD, Mode.FALLBACK, Mode.FINAL):
                self._switch_to(Mode.HOLD, t_s, f'{what} invalid for '
                                f'{t_s - t_invalid:.2f} s (safe mode)')
        return self.mode not in (Mode.FINAL, Mode.FALLBACK)

    # --- input handling ------------------------------------------------------------------
    def _read_vehicle(self, vehicle: VehicleState) -> bool:
        try:
            vp, vv = vehicle.position_m, vehicle.velocity_mps
            pos = (float(vp[0]), float(vp[1]), float(vp[2]))
            vel = (float(vv[0]), float(vv[1]), float(vv[2]))
            ok = _finite(*pos, *vel, vehicle.yaw_rad, vehicle.roll_rad, vehicle.pitch_rad)
        except (TypeError, ValueError, IndexError, AttributeError):
            ok = False
        if not ok:
            self.rejected['nan'] += 1
            return False
        self._pos, self._vel = pos, vel
        return True

    def _read_target(self, t_s: float, apron: ApronState) -> tuple[bool, tuple[float, float]]:
        self._rel = None
        if not apron.tracked:
            return False, (0.0, 0.0)
        ap, av, rp = apron.apron_position_m, apron.apron_velocity_mps, apron.rel_position_m
        if not _finite(ap[0], ap[1], av[0], av[1], rp[0], rp[1]):
            self.rejected['nan'] += 1
            return False, (0.0, 0.0)
        self._rel = (rp[0], rp[1])
        if math.hypot(*self._gate_offset(t_s, ap)) > self._gate_m(t_s):
            # like ArduPilot PLND_XY_DIST_MAX, measured from where the deck is predicted to
            # be (DeckTrack), not from a world-fixed area a moving deck can leave. Kept for a
            # followed track too: it also guards against a diverging estimate (sea_state_4
            # seed 100002 chased a track 3-5 m off without it); a FALLBACK right over the
            # gated beacon still follows it (_rel)
            return False, (0.0, 0.0)
        var = apron.rel_position_var_m2
        sig = self.params.max_target_sigma_m
        # a NaN variance reads as ambiguous (the comparison below is then False)
        self._ambiguous = not (var[0] + var[1] <= sig * sig)
        self._t_target_ok = t_s
        self._last_target = (ap[0], ap[1])
        return True, (rp[0], rp[1])

    def _gate_m(self, t_s: float) -> float:
        """The area gate: ``max_xy_dist_m``; in a wide search (the deck was not at the area
        and has never been seen) grown by how far a deck at ``max_deck_speed_mps`` can have
        gone since the landing started."""
        p = self.params
        if (self.mode is not Mode.SEARCH or not self._wide_search()
                or not math.isfinite(self._t_started)):
            return p.max_xy_dist_m
        return p.max_xy_dist_m + p.max_deck_speed_mps * max(0.0, t_s - self._t_started)

    def _gate_offset(self, t_s: float, ap: tuple[float, float]) -> tuple[float, float]:
        """The target minus where the deck is predicted to be (before this step's fix)."""
        q = self._track.at(t_s).position_m
        return ap[0] - q[0], ap[1] - q[1]

    def _feed_predictor(self, t_s: float, apron: ApronState, vert_ok: bool,
                        vehicle: VehicleState | None) -> None:
        """The deck's vertical motion (and tilt, with telemetry) into the predictor. The
        tilt comes from the ship's attitude whatever the position's source: the beacon fixes
        where the pad is, not how it leans. Holding over the pad (DESCEND, FINAL), the
        vehicle's tilt against the pad's teaches the tilt coupling (decision 17)."""
        v = apron.vertical
        if vert_ok:
            self.predictor.on_surface(t_s, v.surface_height_m, v.surface_epoch,
                                      v.last_rebase_m if _finite(v.last_rebase_m) else 0.0)
        if apron.deck_attitude_valid:
            r = apron.deck_rpy_rad
            if _finite(r[0], r[1], r[2]):
                n = pad_normal_xy(r[0], r[1], r[2])
                self.predictor.on_tilt(t_s, *n)
                if vehicle is not None and self.mode in (Mode.DESCEND, Mode.FINAL):
                    self.tilt_coupling.on_sample(t_s, n[0], n[1], *pad_normal_xy(
                        vehicle.roll_rad, vehicle.pitch_rad, vehicle.yaw_rad))

    def _deck_yaw_target(self) -> float | None:
        """The heading to hold over the deck: its heading + ``deck_yaw_offset_rad``."""
        h = self._tp.heading_rad
        return None if h is None else h + self.params.deck_yaw_offset_rad

    def _align_yaw(self, dt_s: float) -> None:
        """Yaw alignment (issue 13, part 3): turn the held heading toward the deck's at
        ``yaw_rate_max_radps``; without a deck heading the heading stays as latched."""
        target = self._deck_yaw_target()
        if target is None or self._yaw is None:
            return
        err = _wrap(target - self._yaw)
        lim = self.params.yaw_rate_max_radps * dt_s
        self._yaw = _wrap(self._yaw + max(-lim, min(lim, err)))

    def _yaw_aligned(self, vehicle_yaw: float) -> bool:
        """DESCEND only with the vehicle within ``yaw_tolerance_rad`` of the target heading
        (always true without a deck heading)."""
        target = self._deck_yaw_target()
        if target is None:
            return True
        return abs(_wrap(target - vehicle_yaw)) <= self.params.yaw_tolerance_rad

    def _debounced(self, ok: bool, t_s: float, dt_s: float,
                   start: float | None) -> float | None:
        """A timer started at ``start`` that survives excursions (``ok`` False, each sample
        lasting ``dt_s``) shorter than ``timer_debounce_s`` (issue 13, part 5); returns the
        new start (None = reset)."""
        latch = self._l
        if ok:
            latch.t_excursion = None
            return start if start is not None else t_s
        if start is None:
            return None
        if latch.t_excursion is None:
            latch.t_excursion = t_s
        if t_s + dt_s - latch.t_excursion >= self.params.timer_debounce_s - 1e-9:
            latch.t_excursion = None
            return None
        return start

    def _read_vertical(self, apron: ApronState) -> tuple[bool, float]:
        v = apron.vertical
        if not v.valid:
            return False, 0.0
        if not _finite(v.height_m, v.closing_speed_mps, v.surface_height_m):
            self.rejected['nan'] += 1
            return False, 0.0
        # surface re-base: the surface below jumped by last_rebase_m (e.g. the deck came
        # under the vehicle). Shift the relative reference by −jump so the vehicle keeps its
        # world altitude instead of climbing (paper Fig. 7c shows the naive climb).
        if self._epoch is None:
            self._epoch = v.surface_epoch
        elif v.surface_epoch != self._epoch:
            self._epoch = v.surface_epoch
            if self._zref_ok and self._vframe == VERTICAL_RELATIVE and _finite(v.last_rebase_m):
                self._zref.shift(-v.last_rebase_m)
                if self._leash_h is not None:
                    self._leash_h -= v.last_rebase_m
                if self._l.hold_height_m is not None and self.mode in (Mode.IDLE, Mode.ALIGN):
                    # latched "hold where you are" heights move with the datum too
                    self._l.hold_height_m -= v.last_rebase_m
            self.rebases += 1
        self._height = v.height_m
        self._surface = v.surface_height_m
        return True, v.closing_speed_mps

    # --- switching -----------------------------------------------------------------------
    def _switch_to(self, mode: Mode, t_s: float, reason: str, over_deck: bool = False,
                   entry_now: bool = True, follow_track: bool = False,
                   go_around: bool = False) -> None:
        """Enter ``mode`` for ``reason`` (logged in every output): new bookkeeping (the
        invalid-input timer carries over), then the mode's entry actions (``entry_now=False``
        for a service call: at the start of the next step)."""
        t = t_s if _finite(t_s) else (self._t_last or 0.0)
        self.mode = mode
        self._state = _STATES[mode]
        self.reason = reason
        self._l = _Latch(t_mode=t, t_invalid=self._l.t_invalid, over_deck=over_deck,
                         follow_track=follow_track, go_around=go_around)
        if entry_now:
            self._run_entry()

    def _run_entry(self) -> None:
        """Entry actions, in the new mode's vertical frame; they wait (``entry_pending``) for
        the first step that knows the vehicle position."""
        pos = self._pos
        if pos is None:
            return
        self._l.entry_pending = False
        self._update_frame()   # hold heights latched on entry are in the new mode's frame
        self._state.enter(self, (pos[0], pos[1]))

    def _search_or_fallback(self, t_s: float, why: str) -> None:
        """Step 11: search again unless the attempts are used up, then Step 14."""
        search = self._search
        if search.retry():
            self._switch_to(Mode.SEARCH, t_s, f'{why}: search attempt {search.attempts} '
                            f'of {search.max_attempts} (Steps 11-12)')
        elif self._deck_may_move() and not self._over_deck():
            # Step 14 "land where it is" would land on the sea beside a moving deck
            deck = ('a moving deck' if self._deck_moving()
                    else 'a deck seen too briefly to know it is at rest')
            self._switch_to(Mode.HOLD, t_s, f'{why}: {search.attempts} search attempts used '
                            f'on {deck}: holding over its predicted track at the '
                            'search height (Step 14 refused: no descent off the deck)',
                            follow_track=True)
        else:
            self._switch_to(Mode.FALLBACK, t_s, f'{why}: {search.attempts} search attempts '
                            'used, landing where it is (Step 14)', over_deck=self._over_deck())

    def _over_deck(self) -> bool:
        """A tracked, unambiguous beacon right below (camera offset within the re-align
        radius): a FALLBACK then follows it down instead of holding a GPS position."""
        p = self.params
        return (self._rel is not None and not self._ambiguous
                and math.hypot(*self._rel) <= p.acceptance_radius_m * p.acceptance_hysteresis)

    # --- touchdown timed to the deck (issue 13, part 4) -----------------------------------
    def _timing(self) -> bool:
        """FINAL holds and waits for a window (not on the deck-blind constant-rate profile)."""
        return self.params.timed_touchdown and self.params.descent_profile == 'deck_relative'

    def _commit_now(self, t_s: float, reason: str, arm: bool, windowed: bool) -> None:
        """Start the final descent; ``arm``: watch the prediction (go-around);
        ``windowed``: into a window (the commit leash, re-planned on the way down)."""
        self._l.committed = True
        self._l.windowed = windowed
        self.reason = reason
        if not (arm and self._monitor.arm(self.predictor)):
            self._monitor.disarm()

    def _try_commit(self, tk: _Tick) -> None:
        """FINAL hold: commit when a descent started now lands inside a predicted window.
        Bounded: without a ready prediction for ``commit_timeout_s``, or with one but no
        window for ``commit_search_s`` and then no best commit offered for 3 s more, descend
        as before (Step 10)."""
        p = self.params
        latch = self._l
        t = tk.t_s
        if not self.predictor.ready:
            latch.t_ready = math.nan
            if t - latch.t_mode >= p.commit_timeout_s:
                self._commit_now(t, f'no commit ready prediction within {t - latch.t_mode:.1f}'
                                 ' s of holding: final descent as before (Step 10)', False, False)
            return
        if math.isnan(latch.t_ready):
            latch.t_ready = t
        searched = t - latch.t_ready
        late = searched >= p.commit_search_s
        # past the search with no window: the best commit offered within one horizon more
        # (find_window's best_commit_s), then, bounded, as before
        if searched >= p.commit_search_s + _BEST_WAIT_S:
            self._commit_now(t, f'no commit window within {searched:.1f} s of a ready '
                             'prediction: final descent as before (Step 10)', False, False)
            return
        if t - latch.t_check < p.commit_check_s:
            return
        h = self._height
        if not (tk.vert_ok and tk.veh_ok) or h is None or not self._zref_ok:
            return
        hold = p.gear_height_m + p.commit_clearance_m
        if (abs(self._zref.z_m - hold) > 0.02
                or abs(self._zref.z_dot_mps) > self._touchdown().final_speed_mps + 0.01):
            return     # still settling onto the hold height
        latch.t_check = t
        w = self._window(t, tk.vehicle, h)
        if w.commit_now:
            self._commit_now(t, f'commit window open: contact in {w.now_contact_s - t:.1f} s '
                             f'at <= {w.now_speed_hi_mps:.2f} m/s (Step 10)', True, True)
        elif late and w.best_commit_s <= t + 0.5 * p.commit_check_s:
            tilt = ('' if not math.isfinite(w.best_tilt_hi_rad) else
                    f', tilt <= {math.degrees(w.best_tilt_hi_rad):.1f}°')
            self._commit_now(t, f'no window within {p.commit_search_s:.1f} s: the best '
                             f'commit offered (contact at <= {w.best_speed_hi_mps:.2f} m/s'
                             f'{tilt}, Step 10)', True, False)

    def _window(self, t_s: float, v: VehicleState, h: float) -> CommitWindow:
        """The commit window for the final descent flown from height ``h`` now."""
        p = self.params
        nx, ny = pad_normal_xy(v.roll_rad, v.pitch_rad, v.yaw_rad)
        gain, sig = (0.0, 0.0), (0.0, 0.0)
        model = self.tilt_coupling.model()
        if model is not None:       # the vehicle's tilt at contact follows the pad's
            gain, (nx, ny), sig = model
        plan = DescentPlan(height_m=max(h - p.gear_height_m, 0.01),
                           closing_speed_mps=self._touchdown().plan_speed_mps,
                           follow_lag_s=p.commit_follow_lag_s,
                           vehicle_vz_mps=float(v.velocity_mps[2]),
                           vehicle_normal_x=nx, vehicle_normal_y=ny,
                           normal_gain_x=gain[0], normal_gain_y=gain[1],
                           normal_sigma_x=sig[0], normal_sigma_y=sig[1])
        return find_window(t_s, self.predictor.snapshot(), plan, self._commit)

    def _recheck_commit(self, tk: _Tick) -> None:
        """A windowed descent that fell behind its plan (the vehicle descends slower than the
        plan's closing speed) can carry the contact into a reversal: every
        ``commit_check_s`` the descent is re-planned from where it is; when continuing now is
        no longer inside a window it stops and holds again (FINAL hold), above the landed
        band only."""
        p = self.params
        latch = self._l
        h = self._height
        if (not latch.windowed or h is None or not (tk.vert_ok and tk.veh_ok)
                or h - p.gear_height_m <= p.landed_height_tol_m
                or tk.t_s - latch.t_check < p.commit_check_s or not self.predictor.ready):
            return
        latch.t_check = tk.t_s
        w = self._window(tk.t_s, tk.vehicle, h)
        if (w.commit_now or not math.isfinite(w.now_speed_hi_mps)
                or w.now_speed_hi_mps <= self._commit.max_normal_speed_mps + 0.03):
            return     # (hysteresis against chattering; no contact found: the monitor's)
        latch.committed = latch.windowed = False
        self._monitor.disarm()
        self.reason = (f'the committed descent left its window (contact now at <= '
                       f'{w.now_speed_hi_mps:.2f} m/s): holding again (Step 10)')

    def _watch_commit(self, tk: _Tick) -> None:
        """Committed: the deck broke the prediction → go around (climb over the pad, keep
        tracking, retry), at most ``max_go_arounds`` times and not in the landed band."""
        mon = self._monitor
        if not mon.armed:
            return
        broken = mon.update(tk.t_s, self.predictor)
        if not broken:
            self._recheck_commit(tk)
            if not self._l.committed:
                return
        if mon.expired and not broken:
            mon.disarm()
            return
        if not broken:
            return
        mon_reason, worst = mon.reason, mon.worst_sigma
        mon.disarm()
        self._go_around(tk.t_s, f'deck broke the prediction ({mon_reason}, {worst:.1f} sigma)',
                        'climb over the pad, keep tracking, retry')

    def _blind_go_around(self, tk: _Tick) -> bool:
        """Committed, the beacon lost over a moving deck and no telemetry: the pad's place
        is only a constant-velocity prediction, wrong by the deck's unmodelled acceleration
        and the last estimate's velocity error (`fault_telemetry_loss` seed 100002: 0.5 m/s,
        first contact 2 m off the pad, an edge strike). Above the landed band go around
        (climb over the predicted pad, look again), at most ``max_go_arounds`` times; a
        deck at rest, telemetry, or the landed band: go on blind (PX4 PLD_FAPPR_ALT)."""
        if (self._tp.source != DECK_SOURCE_PREDICTION
                or tk.lost_for < self.params.timer_debounce_s or not self._deck_moving()):
            return False
        if not self._go_around(tk.t_s, f'target lost for {tk.lost_for:.1f} s in the '
                               'committed descent over a moving deck, only a prediction of it',
                               'climb over the predicted pad, look again'):
            return False
        self._monitor.disarm()
        return True

    def _go_around(self, t_s: float, why: str, how: str) -> bool:
        """→ ALIGN as a go-around, unless ``max_go_arounds`` are used or the vehicle is in
        the landed band (the contact is closer than any climb); True if it went around."""
        p = self.params
        h = self._height
        if (self.go_arounds >= p.max_go_arounds or h is None
                or h - p.gear_height_m <= p.landed_height_tol_m):
            return False
        self.go_arounds += 1
        self._switch_to(Mode.ALIGN, t_s, f'{why}: go around {self.go_arounds} of '
                        f'{p.max_go_arounds} ({how})', go_around=True)
        return True

    def _deck_moving(self) -> bool:
        """The deck is predicted moving, or was once tracked faster than a drifting barge."""
        return self._tp.moving or self._track.max_speed_mps > _MOVING_MPS

    def _deck_may_move(self) -> bool:
        """Moving, or seen too briefly to tell (no fix's velocity ever confirmed:
        `paper_translating` seed 100227 saw its 0.5 m/s deck for 1 s in a search and, taken
        for a deck at rest, landed beside it after the searches)."""
        tr = self._track
        return self._deck_moving() or (tr.has_fix and not tr.confirmed)

    def _wide_search(self) -> bool:
        """Search wide: the deck has never been seen (no fix) and may have moved off."""
        return not self._track.has_fix

    def _touchdown(self) -> _TouchdownRule:
        """Step 10's speed and Step 15's rule: the firm set when the deck's RMS speed over
        the last seconds of fixes is that of a moving deck (translating, or swaying on a
        rolling hull), not a drifting barge (README "Firm touchdown")."""
        return self._firm if self._track.rms_speed_mps > _MOVING_MPS else self._at_rest

    def _check_landed(self, tk: _Tick) -> None:
        """FINAL, FALLBACK: Step 15 → Step 16."""
        if self._landed(tk.t_s, tk.vert_ok, tk.closing, tk.vehicle, tk.veh_ok):
            self._switch_to(Mode.LANDED, tk.t_s, 'landed (Step 15 → Step 16)')

    def _landed(self, t_s: float, vert_ok: bool, closing: float, vehicle: VehicleState,
                veh_ok: bool) -> bool:
        """Step 15: the autopilot says so, or resting at gear height for a while.

        Resting means: at gear height (within the tolerance), not moving, *and* the height
        reference has run ``landed_press_m`` below the measured height — the controller asks
        for lower and the vehicle does not move. Without the last clause a centimetre of
        height-estimate bias declared LANDED while still hovering just above the deck; the
        motors were cut and the vehicle dropped onto it (touchdown p95 0.46 m/s on `paper`).
        """
        p = self.params
        h = self._height if self._height is not None else math.nan   # NaN: never resting
        datum = self._surface if self._vframe == VERTICAL_WORLD_RATE else 0.0
        rule = self._touchdown()
        pressing = self._zref_ok and self._zref.z_m - datum <= h - rule.press_m
        cond = (veh_ok and vehicle.landed) or (
            vert_ok and pressing and h - p.gear_height_m <= rule.height_tol_m
            and abs(closing) <= p.landed_speed_tol_mps)
        if not cond:
            self._l.t_landed_cond = None
            return False
        if veh_ok and vehicle.landed:
            return True
        if self._l.t_landed_cond is None:
            self._l.t_landed_cond = t_s
        return t_s - self._l.t_landed_cond >= rule.hold_s

    # --- references (shared by the mode handlers) ----------------------------------------
    def _wanted_frame(self) -> str:
        if self.params.descent_profile == 'constant_rate' and self._state.world_ramp:
            return VERTICAL_WORLD_RATE
        return VERTICAL_RELATIVE

    def _update_frame(self) -> None:
        """Convert the reference between height-above-surface and world altitude.

        z_world = h + z_s, so the shift keeps ż_d and z̈_d (no kick, only a datum change).
        """
        want = self._wanted_frame()
        if want == self._vframe:
            return
        if self._zref_ok:
            self._zref.shift(self._surface if want == VERTICAL_WORLD_RATE else -self._surface)
        if want == VERTICAL_WORLD_RATE:
            # deck-blind floor well below any heave trough; contact happens long before it
            self._world_floor_m = (self._surface + self.params.gear_height_m
                                   - self.params.final_press_m - 3.0)
        self._vframe = want

    def _leash(self, dt_s: float) -> None:
        """Final descent: the reference never runs more than ``final_leash_m`` below h
        (above the landed band: h low-passed over ``leash_filter_s``, or the leash ratchets
        z_d up to the noise of the height estimate; README "Touchdown speed").

        The altitude law turns a height error into descent speed: on the DOB's sliding
        surface (14) σ = 0 means ė_z ≈ −Λ e_z, i.e. Λ = 10.5 (m/s) per metre, so a reference
        1 cm below the vehicle asks for 0.1 m/s *on top of* ż_d. Without a leash, z_d keeps
        running down at the final speed whenever the vehicle lags it (the deck fell away
        after a reversal, the relative-speed estimate was off, a gust) and the vehicle then
        catches up at contact (README, "Touchdown speed"). With it, below the final-approach
        height the relative descent is set by ż_d (a rate reference) and e_z ≥ −final_leash_m
        bounds the catch-up to Λ·final_leash_m ≈ 0.05 m/s. The shift keeps ż_d and z̈_d (no
        kick of (17)), and ż_d stays −final_speed, so the vehicle keeps descending to contact.

        The leash lets go once, inside the landed height band, it has taken back
        landed_press_m − final_leash_m (the vehicle was asked for that much travel and did
        not make it: resting, or the deck receding). From there the reference runs on as
        before, so ``_landed`` and its "reference pressing landed_press_m below h" test are
        unchanged: the leash can only delay LANDED (by about landed_press_m / final_speed),
        never declare it. Only with a valid height this step: a stale one must not pin the
        reference.
        """
        p = self.params
        h = self._height
        if (h is None or self._vframe != VERTICAL_RELATIVE
                or self.mode not in (Mode.FINAL, Mode.FALLBACK) or h > p.final_approach_height_m):
            self._leash_taken_m = 0.0
            self._leash_h = None
            return
        hl = self._leash_h
        hl = h if hl is None else hl + (h - hl) * dt_s / (p.leash_filter_s + dt_s)
        self._leash_h = hl
        # a descent committed into a window (no reversal predicted before the contact, the
        # catch-up case) runs on a looser leash: with 5 mm the vehicle follows ż_d at ~0.03
        # instead of 0.08 m/s and lands seconds after the window it was committed into
        leash = p.commit_leash_m if (self._l.windowed and self.mode is Mode.FINAL) \
            else p.final_leash_m
        in_band = h - p.gear_height_m <= p.landed_height_tol_m
        if not in_band:
            self._leash_taken_m = 0.0
        elif self._leash_taken_m >= self._touchdown().press_m - leash:
            return      # let go: the reference presses on toward its target
        # above the landed band the smaller of h and its low-pass: a noise spike up cannot lift
        # z_d, and a deck coming up (h falling faster than the filter) is seen at once. In the
        # band the raw height: what the leash takes back there is travel the
        # vehicle was asked for and did not make, not the filter catching up (it lets go)
        low = (h if in_band else min(h, hl)) - leash
        if self._zref.z_m < low:
            if in_band:
                self._leash_taken_m += low - self._zref.z_m
            self._zref.shift(low - self._zref.z_m)

    def _held_height(self) -> float:
        """The height latched on entry (ALIGN, HOLD, TAKEOFF); the braking stop point if none
        is latched (entry actions wait for the first vehicle position)."""
        h = self._l.hold_height_m
        return h if h is not None else self._stop_here()[0]

    def _stop_here(self) -> tuple[float, float]:
        """Target 'stop where the braking reference comes to rest' (evaluated only if used)."""
        return (self._zref.stopping_point() if self._zref_ok else 0.0,
                self.params.vertical_speed_mps)

    def _world_ramp(self) -> tuple[float, float]:
        """Deck-blind ramp toward a floor below the surface at a constant world rate."""
        return self._world_floor_m, self.params.constant_rate_mps

    def _stop_z(self) -> float:
        """Entry actions: where the reference would come to rest (approach height if none)."""
        return self._zref.stopping_point() if self._zref_ok else self.params.approach_height_m

    def _hold_position(self) -> None:
        """Horizontal: the position latched on entry, no feed-forward."""
        if self._l.hold_xy is not None:
            self._sp = self._l.hold_xy
        self._ff = (0.0, 0.0)

    def _fly_path(self, speed_mps: float, dt_s: float) -> bool:
        """Horizontal: along the active path (False, position held, when none is active).

        A path started ``relative`` is flown in the frame of the predicted deck: setpoint =
        predicted pad + path, feed-forward = deck velocity + path rate (and the deck's
        acceleration): an intercept with velocity matching, not a chase of where it was.
        """
        if not self._path_active:
            self._hold_position()
            return False
        sp, ff = self._path.step(speed_mps, dt_s)
        if self._path_rel:
            o = self._tp
            sp = (sp[0] + o.position_m[0], sp[1] + o.position_m[1])
            ff = (ff[0] + o.velocity_mps[0], ff[1] + o.velocity_mps[1])
            self._accel_ff = o.accel_mps2
        self._sp, self._ff = sp, ff
        return True

    def _track_deck(self, apron: ApronState, seen: bool, dt_s: float) -> None:
        """Horizontal: slew toward the target, moving with the deck and closing the gap at
        ``align_speed_mps``, its velocity and acceleration fed forward; not seen: move on
        with the predicted deck (FINAL continues blind; a deck at rest: the last setpoint)."""
        if seen:
            ax, ay = apron.apron_position_m
            fx, fy = apron.apron_velocity_mps
            acc = apron.apron_accel_mps2
            if _finite(acc[0], acc[1]):
                self._accel_ff = (float(acc[0]), float(acc[1]))
        else:
            o = self._tp
            if o.source == DECK_SOURCE_NONE:
                self._ff = (0.0, 0.0)
                return
            (ax, ay), (fx, fy) = o.position_m, o.velocity_mps
            self._accel_ff = o.accel_mps2
            if o.source == DECK_SOURCE_PREDICTION:
                # a prediction moves the setpoint with the deck, it does not pull it
                sx, sy = self._sp if self._sp is not None else (ax, ay)
                self._sp = (sx + fx * dt_s, sy + fy * dt_s)
                self._ff = (fx, fy)
                return
        sx, sy = self._sp if self._sp is not None else (ax, ay)   # (set by step())
        px, py = sx + fx * dt_s, sy + fy * dt_s
        ex, ey = ax - px, ay - py
        n = math.hypot(ex, ey)
        lim = self.params.align_speed_mps * dt_s
        if n > lim:
            ex, ey = ex * lim / n, ey * lim / n
        self._sp = (px + ex, py + ey)
        self._ff = (fx, fy)

    def _start_path(self, goal: tuple[float, float], relative: bool = False) -> None:
        """A straight path to ``goal`` from the setpoint; ``relative``: in the frame of the
        predicted deck (goal relative to the pad)."""
        start = self._sp
        if start is None:   # (step() sets the setpoint before any entry action runs)
            start = (self._pos[0], self._pos[1]) if self._pos is not None else goal
        v0 = self._ff
        if relative:
            o = self._tp
            start = (start[0] - o.position_m[0], start[1] - o.position_m[1])
            v0 = (v0[0] - o.velocity_mps[0], v0[1] - o.velocity_mps[1])
        self._path.start(start, (float(goal[0]), float(goal[1])), v0)
        self._path_active = True
        self._path_rel = relative

    # --- output --------------------------------------------------------------------------
    def _placeholder_height(self) -> float:
        if self._pos is not None and _finite(self._pos[2]):
            return self._pos[2]
        return self.params.approach_height_m

    def _emit(self, t_s: float, z: float, zd: float, zdd: float,
              thrust: bool) -> PlannerOutput:
        sp = self._sp if self._sp is not None else tuple(self.params.landing_area_m)
        if self._pos is None and self._sp is None:
            thrust = self.mode is not Mode.LANDED and self.mode is not Mode.IDLE
        out = PlannerOutput(
            t_s=t_s, mode=self.mode, setpoint_m=(float(sp[0]), float(sp[1])),
            velocity_ff_mps=self._ff, yaw_rad=self._yaw_out(),
            z_d_m=z, z_d_dot_mps=zd, z_d_ddot_mps2=zdd, thrust_enabled=thrust,
            searches=self.searches, reason=self.reason, vertical_mode=self._vframe,
            accel_ff_mps2=self._accel_ff)
        self._last_out = out
        return out

    def _yaw_out(self) -> float:
        if self._yaw is not None:
            return self._yaw
        if self._last_out is not None:
            return self._last_out.yaw_rad
        return 0.0

    def _hold_output(self, t_s: float) -> PlannerOutput:
        """Answer to a rejected call: the last output (or a neutral one), state unchanged."""
        if self._last_out is not None:
            return self._last_out
        t = t_s if _finite(t_s) else 0.0
        sp = self.params.landing_area_m
        return PlannerOutput(
            t_s=t, mode=self.mode, setpoint_m=(float(sp[0]), float(sp[1])),
            velocity_ff_mps=(0.0, 0.0), yaw_rad=0.0, z_d_m=self._placeholder_height(),
            z_d_dot_mps=0.0, z_d_ddot_mps2=0.0,
            thrust_enabled=self.mode not in (Mode.IDLE, Mode.LANDED),
            searches=self.searches, reason=self.reason, vertical_mode=self._vframe)


# --- one handler per mode ------------------------------------------------------------------
# step() calls, in this order: run() of the current mode (its guarded transitions; skipped
# while the inputs are invalid), then horizontal() and vertical() of the mode it is in after
# them. _switch_to() calls enter().


class _State:
    """A mode of the machine: entry actions, transitions, horizontal and vertical reference."""

    def __init__(self, world_ramp: bool = False) -> None:
        # the constant_rate profile flies this mode on a world-altitude ramp (DESCEND, FINAL)
        self.world_ramp = world_ramp

    def enter(self, pl: LandingPlanner, here: tuple[float, float]) -> None:
        """Entry actions (``here``: the vehicle's horizontal position)."""

    def run(self, pl: LandingPlanner, tk: _Tick) -> None:
        """Guarded transitions out of this mode."""

    def horizontal(self, pl: LandingPlanner, tk: _Tick) -> None:
        """Setpoint and feed-forward; by default the position latched on entry."""
        pl._hold_position()

    def vertical(self, pl: LandingPlanner, tk: _Tick) -> tuple[float, float]:
        """(target, speed) of the vertical reference; by default the height latched on entry."""
        return pl._held_height(), pl.params.vertical_speed_mps


class _Idle(_State):
    """IDLE: before a start; holds where it is, thrust off on the ground (step())."""

    def enter(self, pl: LandingPlanner, here: tuple[float, float]) -> None:
        pl._l.hold_xy = here
        pl._l.hold_height_m = pl._height

    def vertical(self, pl: LandingPlanner, tk: _Tick) -> tuple[float, float]:
        speed = pl.params.vertical_speed_mps
        if not pl._zref_ok:
            # no valid height yet: nothing to hold. Latching the uninitialised reference
            # (0 m) here made the vehicle sink to the ground when OFFBOARD engaged.
            return pl._placeholder_height(), speed
        latch = pl._l
        if latch.hold_height_m is None:
            latch.hold_height_m = pl._zref.z_m
        return latch.hold_height_m, speed


class _Takeoff(_State):
    """TAKEOFF: climb over the current position to the approach height, then HOLD."""

    def enter(self, pl: LandingPlanner, here: tuple[float, float]) -> None:
        pl._l.hold_xy = here
        pl._l.hold_height_m = pl.params.approach_height_m
        pl._path_active = False
        if pl._height is not None and pl._zref_ok:
            pl._zref.reset(pl._height)

    def run(self, pl: LandingPlanner, tk: _Tick) -> None:
        target = pl.params.approach_height_m
        h = pl._height
        if (pl._zref_ok and h is not None and abs(pl._zref.z_m - target) < 1e-3
                and abs(h - target) < 0.15):
            pl._switch_to(Mode.HOLD, tk.t_s, 'takeoff complete')


class _Approach(_State):
    """APPROACH (Step 2): the straight line to the landing area at the approach height."""

    def enter(self, pl: LandingPlanner, here: tuple[float, float]) -> None:
        pl._start_path((0.0, 0.0), relative=True)   # to the predicted deck (the area at rest)

    def run(self, pl: LandingPlanner, tk: _Tick) -> None:
        if tk.target_ok:
            pl._switch_to(Mode.ALIGN, tk.t_s, 'target visible (Step 3 → Step 4)')
            return
        p = pl.params
        latch = pl._l
        lx, ly = pl._tp.position_m
        pos = pl._pos
        arrived = (pl._path.done and pos is not None
                   and math.hypot(pos[0] - lx, pos[1] - ly) <= p.arrival_radius_m)
        # debounced: one noisy position sample outside the radius does not restart it
        latch.t_arrived = pl._debounced(arrived, tk.t_s, tk.dt_s, latch.t_arrived)
        if (arrived and latch.t_arrived is not None
                and tk.t_s - latch.t_arrived >= p.arrival_wait_s):
            pl._search_or_fallback(tk.t_s, 'no target at the landing area (Step 3)')

    def horizontal(self, pl: LandingPlanner, tk: _Tick) -> None:
        pl._fly_path(pl.params.approach_speed_mps, tk.dt_s)

    def vertical(self, pl: LandingPlanner, tk: _Tick) -> tuple[float, float]:
        return pl.params.approach_height_m, pl.params.vertical_speed_mps


class _Align(_State):
    """ALIGN (Steps 3-5): over the deck at the entry height until inside the radius."""

    def enter(self, pl: LandingPlanner, here: tuple[float, float]) -> None:
        p = pl.params
        # from a wide search: down to the search height (the acceptance radius is the
        # paper's for 2-3.5 m; at 8 m the estimate's noise alone keeps the vehicle out of it)
        pl._l.hold_height_m = min(max(pl._stop_z(), p.final_approach_height_m),
                                  p.search_height_m)
        pl._path_active = False

    def run(self, pl: LandingPlanner, tk: _Tick) -> None:
        p = pl.params
        if tk.lost_for > p.target_lost_timeout_s:
            pl._search_or_fallback(tk.t_s, f'target lost for {tk.lost_for:.1f} s in ALIGN')
            return
        latch = pl._l
        dist = math.hypot(tk.rel[0], tk.rel[1])
        close = tk.target_ok and dist <= p.acceptance_radius_m and not pl._ambiguous
        # debounced (issue 13, part 5): a single noisy sample does not restart the hold
        latch.t_in_radius = pl._debounced(close, tk.t_s, tk.dt_s, latch.t_in_radius)
        if (close and latch.t_in_radius is not None
                and tk.t_s - latch.t_in_radius >= p.acceptance_hold_s):
            if not (tk.veh_ok and pl._yaw_aligned(tk.vehicle.yaw_rad)):
                return    # yaw alignment: turning to the deck's heading first
            h, hold = pl._height, latch.hold_height_m
            if latch.go_around and h is not None and hold is not None and h < hold - 0.05:
                return    # a go-around climbs back to the hover height over the pad first
            pl._switch_to(Mode.DESCEND, tk.t_s, f'horizontally close ({dist:.2f} m) for '
                          f'{p.acceptance_hold_s:.1f} s (Step 5 → Step 6)')

    def horizontal(self, pl: LandingPlanner, tk: _Tick) -> None:
        pl._track_deck(tk.apron, tk.target_ok, tk.dt_s)


class _Descend(_State):
    """DESCEND (Steps 6-7, "8", 9): descend over the deck to the final-approach height."""

    def run(self, pl: LandingPlanner, tk: _Tick) -> None:
        p = pl.params
        h = pl._height
        dist = math.hypot(tk.rel[0], tk.rel[1])
        if tk.vert_ok and h is not None and h <= p.final_approach_height_m:
            pl._switch_to(Mode.FINAL, tk.t_s, f'vertically close (h = {h:.2f} m, '
                          'Step 9 → Step 10)')
        elif tk.lost_for > p.target_lost_timeout_s:
            pl._search_or_fallback(tk.t_s, f'target lost for {tk.lost_for:.1f} s in DESCEND '
                                   '(Step 7)')
        elif tk.target_ok and dist > p.acceptance_radius_m * p.acceptance_hysteresis:
            pl._switch_to(Mode.ALIGN, tk.t_s, f'drifted {dist:.2f} m off the target: pause '
                          'the descent and re-align (Step 5 → Step 4)')
        elif tk.target_ok and pl._ambiguous:
            pl._switch_to(Mode.ALIGN, tk.t_s, 'target ambiguous (σ > '
                          f'{p.max_target_sigma_m:.2f} m, e.g. a false blob beside it): '
                          'pause the descent and re-align')

    def horizontal(self, pl: LandingPlanner, tk: _Tick) -> None:
        pl._track_deck(tk.apron, tk.target_ok, tk.dt_s)

    def vertical(self, pl: LandingPlanner, tk: _Tick) -> tuple[float, float]:
        if pl._vframe == VERTICAL_WORLD_RATE:
            return pl._world_ramp()
        if not tk.target_ok:
            return pl._stop_here()   # momentarily not seen: hold height, timer runs on
        p = pl.params
        margin = min(0.2, 0.5 * (p.final_approach_height_m - p.gear_height_m))
        return p.final_approach_height_m - margin, p.descent_speed_mps


class _Final(_State):
    """FINAL (Steps 9-10): the final descent relative to the deck, leashed, blind if need be.

    Timed (issue 13, part 4): first hold ``commit_clearance_m`` of gear clearance over the
    pad, commit into a predicted window (``find_window``), watch the prediction
    (``PredictionMonitor``) and go around (→ ALIGN) when the deck breaks it.
    """

    def enter(self, pl: LandingPlanner, here: tuple[float, float]) -> None:
        pl._l.committed = not pl._timing()
        pl._monitor.disarm()

    def run(self, pl: LandingPlanner, tk: _Tick) -> None:
        pl._check_landed(tk)
        if pl.mode is not Mode.FINAL:
            return
        if pl._l.committed:
            if not pl._blind_go_around(tk):
                pl._watch_commit(tk)
        elif tk.lost_for > _HOLD_LOST_FACTOR * pl.params.target_lost_timeout_s:
            # the hold waits for a window and may wait seconds: blind, the estimate drifts
            # with the wind until the vehicle leaves the pad (gusty seed 100020: 4 s blind at
            # 12 cm clearance, then off the apron's edge). Only a committed descent goes on
            # blind (PX4 PLD_FAPPR_ALT); a hold first climbs to the final-approach height
            # (vertical()), then looks for the deck again, as DESCEND does
            pl._search_or_fallback(tk.t_s, f'target lost for {tk.lost_for:.1f} s in the '
                                   'FINAL hold (Step 7)')
        else:
            pl._try_commit(tk)

    def horizontal(self, pl: LandingPlanner, tk: _Tick) -> None:
        pl._track_deck(tk.apron, tk.target_ok, tk.dt_s)

    def vertical(self, pl: LandingPlanner, tk: _Tick) -> tuple[float, float]:
        if pl._vframe == VERTICAL_WORLD_RATE:
            return pl._world_ramp()
        p = pl.params
        if not pl._l.committed:
            if tk.lost_for > p.target_lost_timeout_s:
                # lost in the hold: up to where the camera's footprint is wider (run())
                return p.final_approach_height_m, p.vertical_speed_mps
            return p.gear_height_m + p.commit_clearance_m, pl._touchdown().final_speed_mps
        return p.gear_height_m - p.final_press_m, pl._touchdown().final_speed_mps


class _Search(_State):
    """SEARCH (Steps 11-13): at the search height, fly the pattern until the target shows."""

    def enter(self, pl: LandingPlanner, here: tuple[float, float]) -> None:
        # around the predicted track: the pattern is flown in the predicted deck's frame
        pl._start_path(pl._search.begin((0.0, 0.0)), relative=True)

    def run(self, pl: LandingPlanner, tk: _Tick) -> None:
        if tk.target_ok:
            pl._switch_to(Mode.ALIGN, tk.t_s, 'target re-acquired during search (Step 13 → '
                          'Step 4)')
        elif tk.t_s - pl._l.t_mode >= pl.params.search_timeout_s:
            pl._search_or_fallback(tk.t_s, f'search attempt {pl.searches} timed out '
                                   '(Step 13)')

    def horizontal(self, pl: LandingPlanner, tk: _Tick) -> None:
        if pl._fly_path(pl.params.search_speed_mps, tk.dt_s) and pl._path.done:
            goal = pl._search.next_goal(tk.t_s)
            if goal is not None:
                pl._start_path(goal, relative=True)

    def vertical(self, pl: LandingPlanner, tk: _Tick) -> tuple[float, float]:
        p = pl.params
        if pl._wide_search():
            return p.wide_search_height_m, p.wide_search_climb_mps
        return p.search_height_m, p.vertical_speed_mps


class _Fallback(_State):
    """FALLBACK (Step 14, safe mode): land where it is, relative to the surface below."""

    def enter(self, pl: LandingPlanner, here: tuple[float, float]) -> None:
        pl._l.hold_xy = here
        pl._path_active = False

    def run(self, pl: LandingPlanner, tk: _Tick) -> None:
        pl._check_landed(tk)

    def horizontal(self, pl: LandingPlanner, tk: _Tick) -> None:
        if pl._l.over_deck:   # follow the deck, even a beacon outside the area gate
            pl._track_deck(tk.apron, tk.target_ok or pl._rel is not None, tk.dt_s)
        else:
            pl._hold_position()

    def vertical(self, pl: LandingPlanner, tk: _Tick) -> tuple[float, float]:
        p = pl.params
        fast = pl._zref.z_m > p.final_approach_height_m
        speed = p.fallback_speed_mps if fast else pl._touchdown().final_speed_mps
        return p.gear_height_m - p.final_press_m, speed


class _Hold(_State):
    """HOLD (abort, invalid inputs, takeoff complete): hover at the approach height or above;
    after the searches on a moving deck: over the predicted track, at the search height."""

    def enter(self, pl: LandingPlanner, here: tuple[float, float]) -> None:
        pl._l.hold_xy = here
        base = (pl.params.search_height_m if pl._l.follow_track
                else pl.params.approach_height_m)
        pl._l.hold_height_m = max(pl._stop_z(), base)
        pl._path_active = False

    def run(self, pl: LandingPlanner, tk: _Tick) -> None:
        # the searches were used up, not the landing: a deck that comes back into view is
        # aligned on again (a later loss in ALIGN returns here, the search budget spent)
        if pl._l.follow_track and tk.target_ok:
            pl._switch_to(Mode.ALIGN, tk.t_s, 'target re-acquired while holding over the '
                          "deck's predicted track (Step 4)")

    def horizontal(self, pl: LandingPlanner, tk: _Tick) -> None:
        if pl._l.follow_track:
            o = pl._tp
            pl._sp, pl._ff, pl._accel_ff = o.position_m, o.velocity_mps, o.accel_mps2
        else:
            pl._hold_position()


class _Landed(_State):
    """LANDED (Steps 15-16): on the deck, thrust off; the reference brakes to rest."""

    def enter(self, pl: LandingPlanner, here: tuple[float, float]) -> None:
        pl._l.hold_xy = here
        pl._path_active = False

    def vertical(self, pl: LandingPlanner, tk: _Tick) -> tuple[float, float]:
        return pl._stop_here()


_STATES: dict[Mode, _State] = {
    Mode.IDLE: _Idle(), Mode.TAKEOFF: _Takeoff(), Mode.APPROACH: _Approach(),
    Mode.ALIGN: _Align(), Mode.DESCEND: _Descend(world_ramp=True),
    Mode.FINAL: _Final(world_ramp=True), Mode.SEARCH: _Search(), Mode.FALLBACK: _Fallback(),
    Mode.HOLD: _Hold(), Mode.LANDED: _Landed(),
}
