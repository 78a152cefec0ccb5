"""The landing area as a moving target: where the pad is, how fast it goes, where it will be.

:class:`DeckTrack` keeps the planner's one estimate of the pad (position, velocity,
acceleration, heading, world ENU) from the sources in their order of preference (issue 13,
part 1): the tracked beacon, else the ship's telemetry, else a constant-velocity prediction
from the last estimate, else the operator's landing area (at rest). It predicts with the
reported velocity low-pass filtered (or, optionally, the displacement of the fixes over
``velocity_window_s``), so one noisy sample does not send the prediction off.

Pure: no rclpy, no wall clock; updated with the apron state's own stamps.
"""

from __future__ import annotations

from dataclasses import dataclass
import math

from deckland_common.contract import (
    DECK_SOURCE_BEACON,
    DECK_SOURCE_NONE,
    DECK_SOURCE_PREDICTION,
    DECK_SOURCE_TELEMETRY,
    ApronState,
)

from deckland_common import validate as chk

__all__ = ['DeckTrack', 'DeckTrackParams', 'TrackPoint']


@dataclass(frozen=True, slots=True)
class DeckTrackParams:
    """How the track predicts (SI units, validated at construction)."""

    velocity_filter_s: float = 0.5    # time constant of the reported velocity's filter
    velocity_window_s: float = 1.0    # ... or the displacement of the fixes over this
    displacement_velocity: bool = False   # predict with the displacement (see update)
    max_prediction_s: float = 60.0    # a prediction older than this is no track
    accel_horizon_s: float = 1.0      # a telemetry fix's acceleration is used this long
    #                                   after it (a beacon fix's only at the fix: planner
    #                                   README, "Tilt at contact", the deck acceleration)
    speed_window_s: float = 3.0       # averaging time of the RMS speed (rms_speed_mps)
    confirm_s: float = 2.0            # a beacon track's velocity is believed after this
    #                                   long of fixes without a gap (see update)

    def __post_init__(self) -> None:
        chk.positive('DeckTrackParams.velocity_filter_s', self.velocity_filter_s)
        chk.positive('DeckTrackParams.velocity_window_s', self.velocity_window_s)
        chk.positive('DeckTrackParams.max_prediction_s', self.max_prediction_s)
        chk.non_negative('DeckTrackParams.accel_horizon_s', self.accel_horizon_s)
        chk.positive('DeckTrackParams.speed_window_s', self.speed_window_s)
        chk.non_negative('DeckTrackParams.confirm_s', self.confirm_s)


class TrackPoint:
    """The pad at one time: position, velocity, acceleration (ENU), heading, its source."""

    __slots__ = ('accel_mps2', 'age_s', 'heading_rad', 'position_m', 'source', 'velocity_mps')

    def __init__(self, position_m: tuple[float, float], velocity_mps: tuple[float, float],
                 accel_mps2: tuple[float, float], heading_rad: float | None, source: str,
                 age_s: float) -> None:
        self.position_m = position_m
        self.velocity_mps = velocity_mps
        self.accel_mps2 = accel_mps2
        self.heading_rad = heading_rad    # None: the deck's heading is not known
        self.source = source              # DECK_SOURCE_*
        self.age_s = age_s                # since the last fix (0 for a fix this step)

    @property
    def moving(self) -> bool:
        """Faster than a drifting barge (0.2 m/s): a fixed-point landing is unsafe."""
        return math.hypot(*self.velocity_mps) > 0.2


def _ok(*values: float) -> bool:
    try:
        return math.isfinite(sum(values))
    except TypeError:
        return False


class DeckTrack:
    """The pad from the beacon, else telemetry, else a prediction, else the landing area."""

    __slots__ = ('_acc', '_acc_horizon_s', '_fix_s', '_heading', '_hist', '_ms', '_pos',
                 '_run_s', '_src', '_vel', '_vel_f', '_yaw_rate', 'area_m', 'confirmed',
                 'fixes', 'max_speed_mps', 'params')

    def __init__(self, area_m: tuple[float, float],
                 params: DeckTrackParams | None = None) -> None:
        self.params = params or DeckTrackParams()
        self.area_m = (float(area_m[0]), float(area_m[1]))
        self.fixes = 0
        self.max_speed_mps = 0.0     # fastest filtered velocity (confirmed or not) so far
        self.confirmed = False       # a fix's velocity was ever believed (confirm_s)
        self.reset()

    def reset(self) -> None:
        """Forget every fix: the landing area at rest again."""
        self._pos = self.area_m
        self._vel = (0.0, 0.0)       # the velocity predicted with (0 until confirmed)
        self._vel_f = (0.0, 0.0)     # the filtered reported velocity
        self._acc = (0.0, 0.0)
        self._run_s = -math.inf      # first fix of the current beacon run (confirm_s)
        self._acc_horizon_s = 0.0
        self._heading: float | None = None
        self._yaw_rate = 0.0
        self._fix_s = -math.inf
        self._src = DECK_SOURCE_NONE
        self._hist: list[tuple[float, float, float]] = []   # (t, x, y) of recent fixes
        self._ms = 0.0               # mean square of the filtered velocity (speed_window_s)

    @property
    def rms_speed_mps(self) -> float:
        """The deck's RMS horizontal speed over about ``speed_window_s`` of fixes: a
        translating or swaying deck, not an estimator's acquisition transient (which
        ``max_speed_mps`` keeps) nor the noise of a deck at rest."""
        return math.sqrt(self._ms)

    @property
    def has_fix(self) -> bool:
        return self._src != DECK_SOURCE_NONE

    def update(self, t_s: float, apron: ApronState, accepted: bool) -> str:
        """Take a fix from ``apron`` if it has one; returns the source used this step.

        ``accepted``: the planner accepted the tracked beacon (finite, inside its gate).
        Telemetry counts when ``apron.source`` says so; a prediction the estimator made is
        not a fix (the track predicts itself).

        A beacon track's velocity (and acceleration) is predicted with only after
        ``confirm_s`` of fixes without a gap longer than ``velocity_window_s``; before, the
        fixes are followed at rest. An acquisition's transient, and the scale error of a
        beacon first seen beside a raised deck (the camera height is then the lidar's, over
        the surface below: offsets ×2 at 1 m of freeboard), read as deck motion of the
        vehicle's own speed: `sea_state_4` seed 100036 chased 0.8 m/s of it off a deck at
        rest, lost the beacon and searched along the phantom track. Telemetry is
        believed at once, and so is a beacon run that continues a telemetry track (the
        estimator starts its filter from the telemetry's velocity).
        """
        if accepted:
            src = DECK_SOURCE_BEACON
        elif apron.source == DECK_SOURCE_TELEMETRY:
            src = DECK_SOURCE_TELEMETRY
        else:
            return DECK_SOURCE_PREDICTION if self.has_fix else DECK_SOURCE_NONE
        p, v, a = apron.apron_position_m, apron.apron_velocity_mps, apron.apron_accel_mps2
        if not (_ok(t_s, p[0], p[1], v[0], v[1]) and t_s >= self._fix_s):
            return DECK_SOURCE_PREDICTION if self.has_fix else DECK_SOURCE_NONE
        acc = (float(a[0]), float(a[1])) if _ok(a[0], a[1]) else (0.0, 0.0)
        prm = self.params
        gap = t_s - self._fix_s
        broken = gap > prm.velocity_window_s   # a gap: the old fixes say nothing now
        if src == DECK_SOURCE_TELEMETRY:
            self._run_s = -math.inf            # believed, and a beacon run following it
        elif broken:
            self._run_s = t_s                  # a new beacon run: not yet confirmed
        confirmed = t_s - self._run_s >= prm.confirm_s
        if self.has_fix and self._fix_s > -math.inf:
            # first-order filter on the velocity: k = dt / (τ + dt)
            k = gap / (prm.velocity_filter_s + gap) if gap > 0.0 else 0.0
            vf = self._vel_f
            vel = (vf[0] + k * (v[0] - vf[0]), vf[1] + k * (v[1] - vf[1]))
        else:
            vel = (float(v[0]), float(v[1]))
        self._vel_f = vel
        if not confirmed:
            vel, acc = (0.0, 0.0), (0.0, 0.0)
        self.confirmed = self.confirmed or confirmed
        if self.has_fix and self._fix_s > -math.inf and gap > 0.0:
            km = gap / (prm.speed_window_s + gap)
            self._ms += km * (vel[0] * vel[0] + vel[1] * vel[1] - self._ms)
        pos = (float(p[0]), float(p[1]))
        hist = self._hist
        if hist and broken:
            hist.clear()
        hist.append((t_s, pos[0], pos[1]))
        w = prm.velocity_window_s
        while len(hist) > 2 and t_s - hist[1][0] >= w:
            del hist[0]
        span = t_s - hist[0][0]
        if span >= 0.5 * w and prm.displacement_velocity and confirmed:
            # the displacement over the window (not the default: after an acquisition the
            # positions carry the estimator's transient too; ship_ss3 seed 100002 predicted
            # 5.5 m/s from them, 3.7 from the filtered velocity, for 2.5 m/s)
            vel = ((pos[0] - hist[0][1]) / span, (pos[1] - hist[0][2]) / span)
        self._pos, self._vel, self._acc = pos, vel, acc
        # the ship's own (INS/GNSS) acceleration is carried on; the beacon filter's is a
        # short-horizon estimate of a sway (σ 0.15-0.6 m/s²): carried for a second it became
        # a lasting velocity error, and a static deck lost behind an occlusion was searched
        # for metres away (fault_beacon_occlusion seed 100002)
        self._acc_horizon_s = (prm.accel_horizon_s if src == DECK_SOURCE_TELEMETRY
                               else 0.0)
        # the evidence that the deck moves counts unconfirmed too: it only makes the planner
        # more careful (no "land where it is" beside it, no blind descent onto it)
        self.max_speed_mps = max(self.max_speed_mps, math.hypot(*self._vel_f))
        if apron.deck_attitude_valid and _ok(apron.deck_rpy_rad[2], apron.deck_yaw_rate_radps):
            self._heading = float(apron.deck_rpy_rad[2])
            self._yaw_rate = float(apron.deck_yaw_rate_radps)
        self._fix_s = t_s
        self._src = src
        self.fixes += 1
        return src

    def at(self, t_s: float) -> TrackPoint:
        """The pad at ``t_s``: the last fix moved on at constant velocity (and, for
        ``accel_horizon_s`` after a telemetry fix, acceleration); the landing area at rest
        before any fix or once the prediction is older than ``max_prediction_s``."""
        if not self.has_fix:
            return TrackPoint(self.area_m, (0.0, 0.0), (0.0, 0.0), None, DECK_SOURCE_NONE,
                              math.inf)
        age = max(0.0, t_s - self._fix_s)
        if age > self.params.max_prediction_s:
            self.reset()
            return self.at(t_s)
        horizon = self._acc_horizon_s
        ta = min(age, horizon)
        ax, ay = self._acc
        vx, vy = self._vel
        x = self._pos[0] + vx * age + 0.5 * ax * ta * ta + ax * ta * (age - ta)
        y = self._pos[1] + vy * age + 0.5 * ay * ta * ta + ay * ta * (age - ta)
        acc = self._acc if age <= horizon else (0.0, 0.0)
        heading = None
        if self._heading is not None:
            h = self._heading + self._yaw_rate * age
            heading = math.atan2(math.sin(h), math.cos(h))
        src = self._src if age == 0.0 else DECK_SOURCE_PREDICTION
        return TrackPoint((x, y), (vx + ax * ta, vy + ay * ta), acc, heading, src, age)
