"""Landing planner: the paper's landing procedure (section 3.3) as an explicit state machine.

The paper lists Steps 1-16 but has no Step 8 and its loop 5 → 6 → 7 → 5 never reaches Step 9.
This module defines the intended flow with named states and guarded transitions (README,
"State machine"): APPROACH (Step 2) → ALIGN (Steps 3-5) → DESCEND (Steps 6-7) → FINAL (Steps
9-10) → LANDED (Steps 15-16), with SEARCH (Steps 11-13), FALLBACK (Step 14) and HOLD (abort /
invalid input) around them; Step 8 is read as "target lost for longer than the timeout → Step
11".

Outputs are what the controllers need: a horizontal setpoint with velocity feed-forward for
the position loop, and a smooth vertical reference (z_d, ż_d, z̈_d) for the altitude law (16),
produced by :class:`~landing_planner.reference.ReferenceGenerator` so that ż_d never steps
(which would kick the term (17)). In the paper's ``deck_relative`` profile z_d is a height above
the surface below (e_z of (7) is taken against the measured height, so the DOB rejects the
heave); the ``constant_rate`` baseline flies DESCEND/FINAL on a world-altitude ramp instead
(``PlannerOutput.vertical_mode``).

Pure: no rclpy, no wall clock; stepped with explicit ``t_s`` / ``dt_s``.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
import math
from typing import TYPE_CHECKING

from landing_planner.reference import ReferenceGenerator, ReferenceLimits
from landing_planner.types import (
    VERTICAL_RELATIVE,
    VERTICAL_WORLD_RATE,
    Mode,
    PlannerOutput,
    VehicleState,
)

if TYPE_CHECKING:  # pragma: no cover - typing only
    from apron_estimator.types import ApronState

__all__ = ['LandingPlanner', 'Mode', 'PlannerOutput', 'PlannerParams', 'VehicleState']

DESCENT_PROFILES = ('deck_relative', 'constant_rate')
_LANDING_MODES = (Mode.APPROACH, Mode.ALIGN, Mode.DESCEND, Mode.FINAL, Mode.SEARCH,
                  Mode.FALLBACK)
_AIRBORNE_MODES = (*_LANDING_MODES, Mode.TAKEOFF, Mode.HOLD)


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
            elif f.name == 'max_searches':
                if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                    raise ValueError(f'PlannerParams.max_searches must be an int >= 0, '
                                     f'got {value!r}')
            elif (isinstance(value, bool) or not isinstance(value, (int, float))
                  or not math.isfinite(value) or value <= 0.0):
                raise ValueError(f'PlannerParams.{f.name} must be a finite number > 0, '
                                 f'got {value!r}')
        if self.acceptance_hysteresis < 1.0:
            raise ValueError('PlannerParams.acceptance_hysteresis must be >= 1')
        if not (self.gear_height_m < self.final_approach_height_m < self.approach_height_m
                <= self.search_height_m):
            raise ValueError('PlannerParams heights must satisfy gear_height_m < '
                             'final_approach_height_m < approach_height_m <= search_height_m')
        if self.landed_press_m >= self.final_press_m:
            raise ValueError('PlannerParams.landed_press_m must be < final_press_m (the '
                             'reference must be able to press that far below contact)')
        if self.final_leash_m >= self.landed_press_m:
            raise ValueError('PlannerParams.final_leash_m must be < landed_press_m')
        if self.max_xy_dist_m < self.acceptance_radius_m:
            raise ValueError('PlannerParams.max_xy_dist_m must be >= acceptance_radius_m')


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
    """Mutable bookkeeping of the state machine (timers, latched targets)."""

    t_mode: float = 0.0
    entry_pending: bool = True
    hold_height_m: float | None = None
    hold_xy: tuple[float, float] | None = None
    t_in_radius: float | None = None
    t_arrived: float | None = None
    t_landed_cond: float | None = None
    t_invalid: float | None = None
    over_deck: bool = False      # FALLBACK entered over the tracked deck: keep following it
    waypoints: list[tuple[float, float]] = field(default_factory=list)
    wp_index: int = 0
    t_wp_reached: float | None = None


class LandingPlanner:
    """The landing procedure of section 3.3 as a deterministic, stepped state machine."""

    def __init__(self, params: PlannerParams | None = None) -> None:
        self.params = params or PlannerParams()
        p = self.params
        self.mode = Mode.IDLE
        self.reason = 'initial'
        self.searches = 0
        self.rebases = 0
        self.rejected: dict[str, int] = {'nan': 0, 'out_of_order': 0, 'bad_dt': 0}
        self._zref = ReferenceGenerator(ReferenceLimits(p.vertical_accel_mps2,
                                                        p.vertical_jerk_mps3))
        self._zref_ok = False
        self._leash_taken_m = 0.0   # what the leash took back in the landed band (_leash)
        self._vframe = VERTICAL_RELATIVE
        self._world_floor_m = 0.0
        self._path = _Path(ReferenceLimits(p.approach_accel_mps2, p.approach_jerk_mps3))
        self._path_active = False
        self._sp: tuple[float, float] | None = None
        self._ff = (0.0, 0.0)
        self._yaw: float | None = None
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

    # --- services (std_srvs/Trigger semantics) ------------------------------------------
    def start_landing(self, t_s: float) -> tuple[bool, str]:
        """Step 1: start the procedure (from IDLE, TAKEOFF or HOLD)."""
        if self.mode in _LANDING_MODES:
            return False, f'already landing (mode {self.mode.name})'
        if self.mode is Mode.LANDED:
            return False, 'landed: take off first'
        self.searches = 0
        self._yaw = None            # latch the current heading at the next step
        self._enter(Mode.APPROACH, t_s, 'start_landing requested (Step 1)')
        return True, 'landing started'

    def abort(self, t_s: float) -> tuple[bool, str]:
        """Climb to the approach height and hold position; a later start is allowed."""
        if self.mode in (Mode.IDLE, Mode.LANDED):
            return False, f'nothing to abort (mode {self.mode.name})'
        if self.mode is Mode.HOLD:
            return True, 'already holding'
        self._enter(Mode.HOLD, t_s, f'abort requested in {self.mode.name}')
        return True, 'aborted: climbing to the approach height and holding'

    def takeoff(self, t_s: float) -> tuple[bool, str]:
        """Climb to the approach height over the current position, then HOLD."""
        if self.mode not in (Mode.IDLE, Mode.LANDED):
            return False, f'already airborne (mode {self.mode.name})'
        self._yaw = None
        self._enter(Mode.TAKEOFF, t_s, 'takeoff requested')
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
        lost_for = t_s - self._t_target_ok
        inputs_ok = veh_ok and vert_ok

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
            self._on_entry(t_s)

        # --- safe mode on invalid inputs (after a grace period) -------------------------
        paused = False
        if inputs_ok:
            self._l.t_invalid = None
        elif self.mode in _AIRBORNE_MODES and self._zref_ok:
            if self._l.t_invalid is None:
                self._l.t_invalid = t_s
            if t_s - self._l.t_invalid >= p.invalid_timeout_s:
                what = 'vertical state' if not vert_ok else 'vehicle state'
                low = self._height is not None and self._height <= p.final_approach_height_m
                if self.mode is Mode.FINAL or (self.mode is Mode.DESCEND and low):
                    self._enter(Mode.FALLBACK, t_s, f'{what} invalid in {self.mode.name}: '
                                'slow descent where it is (safe mode)')
                    # "where it is" is the deck: the camera still sees it, so the vehicle
                    # stays over it (a GPS hold drifts off the pad with the GPS error)
                    self._l.over_deck = target_ok
                    self._on_entry(t_s)
                elif self.mode not in (Mode.HOLD, Mode.FALLBACK, Mode.FINAL):
                    self._enter(Mode.HOLD, t_s, f'{what} invalid for '
                                f'{t_s - self._l.t_invalid:.2f} s (safe mode)')
                    self._on_entry(t_s)
            paused = self.mode not in (Mode.FINAL, Mode.FALLBACK)

        # --- transitions ------------------------------------------------------------------
        if not paused:
            self._transitions(t_s, target_ok, rel, lost_for, vert_ok, closing, vehicle, veh_ok)

        # --- references -------------------------------------------------------------------
        self._update_frame()
        self._update_horizontal(t_s, dt_s, target_ok, apron)
        z_target, z_speed = self._vertical_target(target_ok, paused)
        if self._zref_ok:
            self._zref.step(z_target, z_speed, dt_s)
            if vert_ok:
                self._leash()
        thrust = self.mode is not Mode.LANDED
        if self.mode is Mode.IDLE and (vehicle.landed or (
                self._height is not None
                and self._height <= p.gear_height_m + p.landed_height_tol_m)):
            thrust = False
        z, zd, zdd = self._zref.state() if self._zref_ok else (
            self._placeholder_height(), 0.0, 0.0)
        return self._emit(t_s, z, zd, zdd, thrust)

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
        lx, ly = self.params.landing_area_m
        if math.hypot(ap[0] - lx, ap[1] - ly) > self.params.max_xy_dist_m:
            # like ArduPilot PLND_XY_DIST_MAX. Kept for a followed track too: it also guards
            # against a diverging estimate (sea_state_4 seed 100002 chased a track 3-5 m off
            # without it); a FALLBACK right over the gated beacon still follows it (_rel)
            return False, (0.0, 0.0)
        var = apron.rel_position_var_m2
        sig = self.params.max_target_sigma_m
        # a NaN variance reads as ambiguous (the comparison below is then False)
        self._ambiguous = not (var[0] + var[1] <= sig * sig)
        self._t_target_ok = t_s
        self._last_target = (ap[0], ap[1])
        return True, (rp[0], rp[1])

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
                if self._l.hold_height_m is not None and self.mode in (Mode.IDLE, Mode.ALIGN):
                    # latched "hold where you are" heights move with the datum too
                    self._l.hold_height_m -= v.last_rebase_m
            self.rebases += 1
        self._height = v.height_m
        self._surface = v.surface_height_m
        return True, v.closing_speed_mps

    # --- state machine -------------------------------------------------------------------
    def _enter(self, mode: Mode, t_s: float, reason: str) -> None:
        t = t_s if _finite(t_s) else (self._t_last or 0.0)
        self.mode = mode
        self.reason = reason
        latch = _Latch(t_mode=t, t_invalid=self._l.t_invalid)
        self._l = latch

    def _search_or_fallback(self, t_s: float, why: str) -> None:
        """Step 11: search again unless the attempts are used up, then Step 14."""
        if self.searches < self.params.max_searches:
            self.searches += 1
            self._enter(Mode.SEARCH, t_s, f'{why}: search attempt {self.searches} '
                        f'of {self.params.max_searches} (Steps 11-12)')
        else:
            self._enter(Mode.FALLBACK, t_s, f'{why}: {self.searches} search attempts used, '
                        'landing where it is (Step 14)')
            self._l.over_deck = self._over_deck()
        self._on_entry(t_s)

    def _over_deck(self) -> bool:
        """A tracked, unambiguous beacon right below (camera offset within the re-align
        radius): a FALLBACK then follows it down instead of holding a GPS position."""
        p = self.params
        return (self._rel is not None and not self._ambiguous
                and math.hypot(*self._rel) <= p.acceptance_radius_m * p.acceptance_hysteresis)

    def _on_entry(self, t_s: float) -> None:
        """Entry actions; run lazily once the vehicle position is known."""
        if self._pos is None:
            return
        p = self.params
        latch = self._l
        latch.entry_pending = False
        mode = self.mode
        self._update_frame()   # hold heights below are in the new mode's vertical frame
        here = (self._pos[0], self._pos[1])
        stop_z = self._zref.stopping_point() if self._zref_ok else p.approach_height_m
        if mode is Mode.APPROACH:
            self._start_path(p.landing_area_m)
        elif mode is Mode.ALIGN:
            latch.hold_height_m = max(stop_z, p.final_approach_height_m)
            self._path_active = False
        elif mode is Mode.SEARCH:
            lx, ly = p.landing_area_m
            c = self._last_target or (lx, ly)
            r = p.search_radius_m
            latch.waypoints = [c, (c[0] + r, c[1] + r), (c[0] - r, c[1] + r),
                               (c[0] - r, c[1] - r), (c[0] + r, c[1] - r), c]
            latch.wp_index = 0
            self._start_path(c)
        elif mode in (Mode.HOLD, Mode.TAKEOFF, Mode.FALLBACK):
            latch.hold_xy = here
            latch.hold_height_m = max(stop_z, p.approach_height_m)
            self._path_active = False
            if mode is Mode.TAKEOFF:
                latch.hold_height_m = p.approach_height_m
                if self._height is not None and self._zref_ok:
                    self._zref.reset(self._height)
        elif mode is Mode.LANDED:
            latch.hold_xy = here
            self._path_active = False
        elif mode is Mode.IDLE:
            latch.hold_xy = here
            latch.hold_height_m = self._height

    def _start_path(self, goal: tuple[float, float]) -> None:
        start = self._sp
        if start is None:   # (step() sets the setpoint before any entry action runs)
            start = (self._pos[0], self._pos[1]) if self._pos is not None else goal
        self._path.start(start, (float(goal[0]), float(goal[1])), self._ff)
        self._path_active = True

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
        pressing = self._zref_ok and self._zref.z_m - datum <= h - p.landed_press_m
        cond = (veh_ok and vehicle.landed) or (
            vert_ok and pressing and h - p.gear_height_m <= p.landed_height_tol_m
            and abs(closing) <= p.landed_speed_tol_mps)
        if not cond:
            self._l.t_landed_cond = None
            return False
        if veh_ok and vehicle.landed:
            return True
        if self._l.t_landed_cond is None:
            self._l.t_landed_cond = t_s
        return t_s - self._l.t_landed_cond >= p.landed_hold_s

    def _transitions(self, t_s: float, target_ok: bool, rel: tuple[float, float],
                     lost_for: float, vert_ok: bool, closing: float, vehicle: VehicleState,
                     veh_ok: bool) -> None:
        p = self.params
        mode = self.mode
        latch = self._l
        dist = math.hypot(rel[0], rel[1])
        if mode is Mode.APPROACH:
            if target_ok:
                self._enter(Mode.ALIGN, t_s, 'target visible (Step 3 → Step 4)')
                self._on_entry(t_s)
                return
            lx, ly = p.landing_area_m
            pos = self._pos
            arrived = (self._path.done and pos is not None
                       and math.hypot(pos[0] - lx, pos[1] - ly) <= p.arrival_radius_m)
            if not arrived:
                latch.t_arrived = None
            elif latch.t_arrived is None:
                latch.t_arrived = t_s
            elif t_s - latch.t_arrived >= p.arrival_wait_s:
                self._search_or_fallback(t_s, 'no target at the landing area (Step 3)')
        elif mode is Mode.ALIGN:
            if lost_for > p.target_lost_timeout_s:
                self._search_or_fallback(t_s, f'target lost for {lost_for:.1f} s in ALIGN')
                return
            if target_ok and dist <= p.acceptance_radius_m and not self._ambiguous:
                if latch.t_in_radius is None:
                    latch.t_in_radius = t_s
                if t_s - latch.t_in_radius >= p.acceptance_hold_s:
                    self._enter(Mode.DESCEND, t_s, f'horizontally close ({dist:.2f} m) for '
                                f'{p.acceptance_hold_s:.1f} s (Step 5 → Step 6)')
                    self._on_entry(t_s)
            else:
                latch.t_in_radius = None
        elif mode is Mode.DESCEND:
            if vert_ok and self._height is not None and self._height <= p.final_approach_height_m:
                self._enter(Mode.FINAL, t_s, f'vertically close (h = {self._height:.2f} m, '
                            'Step 9 → Step 10)')
                self._on_entry(t_s)
            elif lost_for > p.target_lost_timeout_s:
                self._search_or_fallback(t_s, f'target lost for {lost_for:.1f} s in DESCEND '
                                         '(Step 7)')
            elif target_ok and dist > p.acceptance_radius_m * p.acceptance_hysteresis:
                self._enter(Mode.ALIGN, t_s, f'drifted {dist:.2f} m off the target: pause '
                            'the descent and re-align (Step 5 → Step 4)')
                self._on_entry(t_s)
            elif target_ok and self._ambiguous:
                self._enter(Mode.ALIGN, t_s, 'target ambiguous (σ > '
                            f'{p.max_target_sigma_m:.2f} m, e.g. a false blob beside it): '
                            'pause the descent and re-align')
                self._on_entry(t_s)
        elif mode in (Mode.FINAL, Mode.FALLBACK):
            if self._landed(t_s, vert_ok, closing, vehicle, veh_ok):
                self._enter(Mode.LANDED, t_s, 'landed (Step 15 → Step 16)')
                self._on_entry(t_s)
        elif mode is Mode.SEARCH:
            if target_ok:
                self._enter(Mode.ALIGN, t_s, 'target re-acquired during search (Step 13 → '
                            'Step 4)')
                self._on_entry(t_s)
            elif t_s - latch.t_mode >= p.search_timeout_s:
                self._search_or_fallback(t_s, f'search attempt {self.searches} timed out '
                                         '(Step 13)')
        elif mode is Mode.TAKEOFF and (
                self._zref_ok and self._height is not None
                and abs(self._zref.z_m - p.approach_height_m) < 1e-3
                and abs(self._height - p.approach_height_m) < 0.15):
            self._enter(Mode.HOLD, t_s, 'takeoff complete')
            self._on_entry(t_s)

    # --- references ----------------------------------------------------------------------
    def _wanted_frame(self) -> str:
        if (self.params.descent_profile == 'constant_rate'
                and self.mode in (Mode.DESCEND, Mode.FINAL)):
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

    def _vertical_target(self, target_ok: bool, paused: bool) -> tuple[float, float]:
        p = self.params
        mode = self.mode
        latch = self._l
        if paused:
            return self._stop_here()
        contact = p.gear_height_m - p.final_press_m
        if self._vframe == VERTICAL_WORLD_RATE:
            # deck-blind ramp toward a floor below the surface at a constant world rate
            return self._world_floor_m, p.constant_rate_mps
        if mode is Mode.APPROACH:
            return p.approach_height_m, p.vertical_speed_mps
        if mode is Mode.ALIGN:
            return self._held_height(), p.vertical_speed_mps
        if mode is Mode.DESCEND:
            if not target_ok:
                return self._stop_here()   # momentarily not seen: hold height, timer runs on
            margin = min(0.2, 0.5 * (p.final_approach_height_m - p.gear_height_m))
            return p.final_approach_height_m - margin, p.descent_speed_mps
        if mode is Mode.FINAL:
            return contact, p.final_speed_mps
        if mode is Mode.FALLBACK:
            fast = self._zref.z_m > p.final_approach_height_m
            return contact, p.fallback_speed_mps if fast else p.final_speed_mps
        if mode is Mode.SEARCH:
            return p.search_height_m, p.vertical_speed_mps
        if mode in (Mode.HOLD, Mode.TAKEOFF):
            return self._held_height(), p.vertical_speed_mps
        if mode is Mode.IDLE:
            if not self._zref_ok:
                # no valid height yet: nothing to hold. Latching the uninitialised reference
                # (0 m) here made the vehicle sink to the ground when OFFBOARD engaged.
                return self._placeholder_height(), p.vertical_speed_mps
            if latch.hold_height_m is None:
                latch.hold_height_m = self._zref.z_m
            return latch.hold_height_m, p.vertical_speed_mps
        # LANDED: come to rest where the reference is
        return self._stop_here()

    def _leash(self) -> None:
        """Final descent: the reference never runs more than ``final_leash_m`` below h.

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
            return
        in_band = h - p.gear_height_m <= p.landed_height_tol_m
        if not in_band:
            self._leash_taken_m = 0.0
        elif self._leash_taken_m >= p.landed_press_m - p.final_leash_m:
            return      # let go: the reference presses on toward its target
        low = h - p.final_leash_m
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

    def _update_horizontal(self, t_s: float, dt_s: float, target_ok: bool,
                           apron: ApronState) -> None:
        p = self.params
        mode = self.mode
        latch = self._l
        if mode in (Mode.ALIGN, Mode.DESCEND, Mode.FINAL) or (
                mode is Mode.FALLBACK and latch.over_deck):
            if target_ok or (mode is Mode.FALLBACK and self._rel is not None):
                ax, ay = apron.apron_position_m
                fx, fy = apron.apron_velocity_mps
                # slew toward the target: move with the deck, close the gap at align_speed
                sx, sy = self._sp if self._sp is not None else (ax, ay)   # (set by step())
                px, py = sx + fx * dt_s, sy + fy * dt_s
                ex, ey = ax - px, ay - py
                n = math.hypot(ex, ey)
                lim = p.align_speed_mps * dt_s
                if n > lim:
                    ex, ey = ex * lim / n, ey * lim / n
                self._sp = (px + ex, py + ey)
                self._ff = (fx, fy)
            else:   # hold the last setpoint (FINAL continues blind)
                self._ff = (0.0, 0.0)
            return
        if mode in (Mode.APPROACH, Mode.SEARCH) and self._path_active:
            speed = p.approach_speed_mps if mode is Mode.APPROACH else p.search_speed_mps
            self._sp, self._ff = self._path.step(speed, dt_s)
            if mode is Mode.SEARCH and self._path.done:
                self._next_waypoint(t_s)
            return
        if latch.hold_xy is not None:
            self._sp = latch.hold_xy
        self._ff = (0.0, 0.0)

    def _next_waypoint(self, t_s: float) -> None:
        """Search pattern: hover at the centre for search_hold_s, then fly the square."""
        latch = self._l
        if latch.wp_index == 0:
            if latch.t_wp_reached is None:
                latch.t_wp_reached = t_s
            if t_s - latch.t_wp_reached < self.params.search_hold_s:
                return
        latch.t_wp_reached = None
        latch.wp_index = (latch.wp_index + 1) % len(latch.waypoints)
        self._start_path(latch.waypoints[latch.wp_index])

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
            searches=self.searches, reason=self.reason, vertical_mode=self._vframe)
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
