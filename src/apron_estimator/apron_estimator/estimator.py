"""ApronEstimator: camera model + horizontal KF + vertical filter (pure; docs/interfaces.md).

Data flow: ``on_camera(t, blocks)`` looks up the attitude at the exposure stamp ``t`` (linear
interpolation in a ~0.5 s history), the height above the deck at ``t`` (vertical filter,
falling back to the last tilt-corrected lidar height; the raw lidar range in ``paper_exact``
mode), turns every block into a beacon-minus-vehicle offset in ENU with the camera model
(27)-(30), and hands the candidates to the horizontal tracker (31)-(34) at stamp ``t``.
``state(t)`` predicts both filters to ``t`` without changing them and fills every
:class:`ApronState` field: the heading-frame (FLU) offsets use our form of (35),
``rel_FLU = Rz(ψ)ᵀ rel_ENU``.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field
import math

from deckland_common.contract import ApronState, PixyBlock
from deckland_common.frames import wrap_pi

from apron_estimator.camera import CameraModel, CameraParams
from apron_estimator.horizontal import HorizontalParams, HorizontalTracker
from apron_estimator.vertical import VerticalFilter, VerticalParams
from deckland_common import validate as chk

_isfinite = math.isfinite


#: Decision 12d: below this camera height above the beacon's surface the level correction
#: is not applied (the lidar height is used, as the paper does)
_MIN_CAMERA_HEIGHT_M = 0.3


@dataclass(frozen=True)
class EstimatorParams:
    """All estimator parameters; sub-dataclasses validate themselves."""

    camera: CameraParams = field(default_factory=CameraParams)
    horizontal: HorizontalParams = field(default_factory=HorizontalParams)
    vertical: VerticalParams = field(default_factory=VerticalParams)
    beacon_signature: int = 0           # Pixy signature of the beacon; 0 = any
    attitude_history_s: float = 0.5
    max_attitude_gap_s: float = 0.1     # no attitude sample this close to a stamp → no fix
    height_fallback_timeout_s: float = 1.0  # raw lidar height usable this long w/o filter
    visible_timeout_s: float = 0.2      # ``visible`` also needs a frame this recent
    max_position_extrapolation_s: float = 0.5

    def __post_init__(self) -> None:
        o = 'EstimatorParams'
        for name, cls in (('camera', CameraParams), ('horizontal', HorizontalParams),
                          ('vertical', VerticalParams)):
            if not isinstance(getattr(self, name), cls):
                raise ValueError(f'{o}.{name} must be a {cls.__name__}')
        chk.integer_at_least(f'{o}.beacon_signature', self.beacon_signature, 0)
        chk.positive(f'{o}.attitude_history_s', self.attitude_history_s)
        chk.positive(f'{o}.max_attitude_gap_s', self.max_attitude_gap_s)
        chk.positive(f'{o}.height_fallback_timeout_s', self.height_fallback_timeout_s)
        chk.positive(f'{o}.visible_timeout_s', self.visible_timeout_s)
        chk.non_negative(f'{o}.max_position_extrapolation_s', self.max_position_extrapolation_s)


class ApronEstimator:
    """Apron (beacon) state from Pixy blocks, attitude, local position, acceleration, lidar."""

    def __init__(self, params: EstimatorParams | None = None) -> None:
        self.params = params if params is not None else EstimatorParams()
        self.camera = CameraModel(self.params.camera)
        self.horizontal = HorizontalTracker(self.params.horizontal)
        self.vertical = VerticalFilter(self.params.vertical)
        self._own: dict[str, int] = {'nan': 0, 'out_of_order': 0, 'no_attitude': 0,
                                     'no_height': 0, 'signature': 0, 'off_deck': 0,
                                     'malformed': 0}
        self._att: deque[tuple[float, float, float, float]] = deque()
        self._pos: tuple[float, tuple[float, float, float], tuple[float, float, float]] | None
        self._pos = None
        self._t_camera = -math.inf
        self._lidar_spot = (0.0, 0.0)
        self._delta_m = 0.0     # the camera height's level correction used last (_camera_delta)
        self._top_level_m = 0.0   # the deck's surface level (_camera_delta)
        self._low_level_m = 0.0   # the lowest surface level seen

    @property
    def rejected(self) -> dict[str, int]:
        """Rejection counters: own keys, plus ``horizontal.*`` and ``vertical.*``."""
        out = dict(self._own)
        for k, v in self.horizontal.rejected.items():
            out['horizontal.' + k] = v
        for k, v in self.vertical.rejected.items():
            out['vertical.' + k] = v
        return out

    # -- inputs ----------------------------------------------------------------------------
    def on_attitude(self, t_s: float, roll_rad: float, pitch_rad: float,
                    yaw_rad: float) -> None:
        if not _isfinite(t_s + roll_rad + pitch_rad + yaw_rad):   # overflow: on_local_position
            self._own['nan'] += 1
            return
        att = self._att
        if att and t_s <= att[-1][0]:
            self._own['out_of_order'] += 1
            return
        att.append((t_s, roll_rad, pitch_rad, yaw_rad))
        horizon = t_s - self.params.attitude_history_s
        while len(att) > 2 and att[1][0] < horizon:
            att.popleft()

    def attitude_at(self, t_s: float) -> tuple[float, float, float] | None:
        """(roll, pitch, yaw) at t_s, linear between samples (yaw wrapped); None if no sample
        within ``max_attitude_gap_s``."""
        att = self._att
        if not att:
            return None
        gap = self.params.max_attitude_gap_s
        last = att[-1]
        if t_s >= last[0]:
            return (last[1], last[2], last[3]) if t_s - last[0] <= gap else None
        for i in range(len(att) - 2, -1, -1):
            a = att[i]
            if a[0] <= t_s:
                b = att[i + 1]
                span = b[0] - a[0]
                if min(t_s - a[0], b[0] - t_s) > gap:
                    return None
                w = (t_s - a[0]) / span
                return (a[1] + w * (b[1] - a[1]), a[2] + w * (b[2] - a[2]),
                        wrap_pi(a[3] + w * wrap_pi(b[3] - a[3])))
        first = att[0]
        return (first[1], first[2], first[3]) if first[0] - t_s <= gap else None

    def on_local_position(self, t_s: float, position_m: Sequence[float],
                          velocity_mps: Sequence[float]) -> None:
        """Vehicle local position / velocity, world ENU (GPS / EKF)."""
        try:
            px, py, pz = position_m
            vx, vy, vz = velocity_mps
            px, py, pz = float(px), float(py), float(pz)
            vx, vy, vz = float(vx), float(vy), float(vz)
        except (TypeError, ValueError):
            self._own['nan'] += 1
            return
        # a NaN/inf anywhere makes the sum non-finite (finite values near 1e308 could overflow
        # and be rejected too; positions, speeds and stamps are nowhere near that)
        if not _isfinite(t_s + px + py + pz + vx + vy + vz):
            self._own['nan'] += 1
            return
        if self._pos is not None and t_s <= self._pos[0]:
            self._own['out_of_order'] += 1
            return
        self._pos = (t_s, (px, py, pz), (vx, vy, vz))
        self.vertical.on_altitude(t_s, pz, vz)

    def on_accel(self, t_s: float, accel_world_mps2: Sequence[float]) -> None:
        """Vehicle acceleration, ENU, gravity removed."""
        try:
            ax, ay, az = accel_world_mps2
            ax, ay, az = float(ax), float(ay), float(az)
        except (TypeError, ValueError):
            self._own['nan'] += 1
            return
        self.horizontal.on_accel(t_s, ax, ay)
        self.vertical.on_accel(t_s, az)

    def on_lidar(self, t_s: float, range_m: float | None) -> None:
        """Downward lidar range (None = no return); tilt from the attitude at t_s."""
        att = self.attitude_at(t_s) if _isfinite(t_s) else None
        roll, pitch = (att[0], att[1]) if att is not None else (0.0, 0.0)
        vf = self.vertical
        epoch = vf.surface_epoch
        vf.on_lidar(t_s, range_m, roll, pitch)
        r = vf.last_range_m
        if att is not None and r is not None and vf.t_last_range == t_s:
            # where the lidar hits, horizontally from the body origin (ENU): range · (−R e3)
            # — a tilted vehicle samples the surface up to h·tan(tilt) away from below it
            cr, sr = math.cos(roll), math.sin(roll)
            sp = math.sin(pitch)
            cy, sy = math.cos(att[2]), math.sin(att[2])
            self._lidar_spot = (-r * (cy * sp * cr + sy * sr), -r * (sy * sp * cr - cy * sr))
        if vf.surface_epoch != epoch:
            # The camera offsets scale with the camera height (29)-(30): a re-base changes it
            # from c_before to c_after and every offset measured from now on by their ratio.
            # c = h − δ: with the beacon's surface level known, δ moves with the level and
            # c does not change (ratio 1); unknown (δ = 0), h_after / h_before (12b)
            h_after = vf.x[0] - vf.x[2]
            h_before = h_after + vf.last_rebase_m
            self._top_level_m = max(self._top_level_m, vf.surface_level_m)
            self._low_level_m = min(self._low_level_m, vf.surface_level_m)
            d_after = self._camera_delta(h_after)
            c_after, c_before = h_after - d_after, h_before - self._delta_m
            if c_after > 0.05 and c_before > 0.05:
                self.horizontal.rescale(c_after / c_before)
            self._delta_m = d_after

    def on_camera(self, t_s: float, blocks: Sequence[PixyBlock],
                  deck_velocity_mps: tuple[float, float] = (0.0, 0.0)) -> None:
        """One Pixy frame; ``t_s`` is its exposure stamp (may be in the past).
        ``deck_velocity_mps``: the deck's velocity (ENU) a track started by this frame assumes
        — the ship's telemetry when the owner has it, else at rest (README, D7)."""
        if not _isfinite(t_s):
            self._own['nan'] += 1
            return
        if t_s <= self._t_camera:
            self._own['out_of_order'] += 1
            return
        att = self.attitude_at(t_s)
        if att is None:
            self._own['no_attitude'] += 1
            return
        height = self._height_at(t_s)
        if height is None:
            self._own['no_height'] += 1
            return
        if not self.params.camera.paper_exact:
            # the height above the *beacon's* surface (README, decision 12d)
            delta = self._camera_delta(height)
            if delta != self._delta_m and height - self._delta_m > 0.05:
                # the basis changed (the track's level learnt or switched): rescale
                self.horizontal.rescale((height - delta) / (height - self._delta_m))
            self._delta_m = delta
            height -= delta
        self._t_camera = t_s
        sig = self.params.beacon_signature
        scored = []
        for b in blocks:
            try:
                bsig, x, y, w, h = b.signature, b.x_px, b.y_px, b.width_px, b.height_px
                finite = _isfinite(x) and _isfinite(y) and _isfinite(w) and _isfinite(h)
            except (AttributeError, TypeError):
                self._own['malformed'] += 1
                continue
            if sig and bsig != sig:
                self._own['signature'] += 1
                continue
            if not finite:
                self._own['nan'] += 1
                continue
            scored.append((-(w * h), x, y))
        scored.sort()
        roll, pitch, yaw = att
        candidates = []
        rel = self.camera.relative_position
        for _, x, y in scored:
            c = rel(x, y, height, roll, pitch, yaw)
            if c is None:
                self._own['off_deck'] += 1
            else:
                candidates.append(c)
        # the level of the surface under the vehicle (the sum of the surface steps the
        # vertical filter has re-based on): resolves false blobs. Not the absolute surface
        # height: samples over two hypotheses are taken seconds apart, and the deck heaves
        # (and the altitude drifts) by more than a deck's rise in between (README)
        vf = self.vertical
        surface = None
        if vf.initialised and self._recent_lidar(t_s):
            surface = vf.surface_level_m
        hz = self.horizontal
        top = None if self.params.camera.paper_exact else self._top_level_m
        prior = self._relative_velocity_prior(deck_velocity_mps)
        if hz.update(t_s, candidates, height, surface, self._lidar_spot, top, prior) and (
                surface is not None and hz.mode == 'tracking'):
            # the lidar spot on the tracked beacon: the surface under it is the beacon's
            x, y = hz.kf.px, hz.kf.py
            sx, sy = self._lidar_spot
            r = hz.params.verify_radius_m
            if ((x - sx) * (x - sx) + (y - sy) * (y - sy) <= r * r
                    and surface - self._low_level_m > self._top_level_m - surface):
                self._top_level_m = surface

    def _relative_velocity_prior(self, deck_velocity_mps: tuple[float, float]
                                 ) -> tuple[float, float]:
        """Beacon minus vehicle velocity for a new track: the deck's prior minus the
        vehicle's last velocity (README, D7); the deck's prior alone without a velocity."""
        dvx, dvy = deck_velocity_mps
        if not (_isfinite(dvx) and _isfinite(dvy)):
            dvx = dvy = 0.0
        if self._pos is None:
            return dvx, dvy
        vel = self._pos[2]
        return dvx - vel[0], dvy - vel[1]

    def _camera_delta(self, height_m: float) -> float:
        """δ = level of the beacon's surface − level of the surface under the vehicle (the
        vertical filter's re-base steps, decision 13): the camera height above the beacon
        is h − δ. The beacon's level: the highest surface seen (a beacon sits on the deck),
        moved to the level seen with the lidar spot on the tracked beacon when that is
        nearer the highest than the lowest (the levels drift with a heave between re-bases;
        a glint on the ground does not move it). 0 (the lidar height) when h − δ would be
        below ``_MIN_CAMERA_HEIGHT_M``: beside the deck at its own height there is no
        usable geometry, over the deck a drifted level must not shrink the final approach's
        offsets (README, decision 12d)."""
        if self.params.camera.paper_exact:
            return 0.0
        d = self._top_level_m - self.vertical.surface_level_m
        return d if height_m - d >= _MIN_CAMERA_HEIGHT_M else 0.0

    def _height_at(self, t_s: float) -> float | None:
        vf = self.vertical
        if self.params.camera.paper_exact:
            # the paper's z in (29)-(30) is the raw LidarLite range
            if vf.last_range_m is not None and self._recent_lidar(t_s):
                return vf.last_range_m
            return None
        if vf.valid_at(t_s):
            h = vf.height_at(t_s)
            if h > 0.0:
                return h
        if vf.last_h_m is not None and self._recent_lidar(t_s):
            return vf.last_h_m
        return None

    def _recent_lidar(self, t_s: float) -> bool:
        t = self.vertical.t_last_range
        return t is not None and abs(t_s - t) <= self.params.height_fallback_timeout_s

    # -- output ----------------------------------------------------------------------------
    def deck_accel(self, t_s: float) -> tuple[float, float] | None:
        """The deck's acceleration (ENU) from the beacon track's filter, None while unknown
        (``HorizontalTracker.deck_accel``)."""
        return self.horizontal.deck_accel(t_s)

    def state(self, t_s: float) -> ApronState:
        """Everything predicted to t_s; the filters are not changed."""
        if not _isfinite(t_s):
            self._own['nan'] += 1
            return ApronState.untracked(0.0)
        x, y, vx, vy, var_x, var_y, tracked, since = self.horizontal.state(t_s)
        vertical = self.vertical.state(t_s)
        visible = (self.horizontal.visible and t_s - self._t_camera
                   <= self.params.visible_timeout_s)
        yaw = self._att[-1][3] if self._att else 0.0
        c, s = math.cos(yaw), math.sin(yaw)
        if self._pos is not None:
            tp, pos, vel = self._pos
            dt = min(max(0.0, t_s - tp), self.params.max_position_extrapolation_s)
            vpx, vpy = pos[0] + vel[0] * dt, pos[1] + vel[1] * dt
            vvx, vvy = vel[0], vel[1]
        else:
            vpx = vpy = vvx = vvy = 0.0
        return ApronState(
            t_s=t_s, tracked=tracked, visible=visible, time_since_seen_s=since,
            rel_position_m=(x, y), rel_velocity_mps=(vx, vy),
            rel_position_var_m2=(var_x, var_y),
            rel_position_body_m=(c * x + s * y, -s * x + c * y),
            rel_velocity_body_mps=(c * vx + s * vy, -s * vx + c * vy),
            apron_position_m=(vpx + x, vpy + y), apron_velocity_mps=(vvx + vx, vvy + vy),
            vertical=vertical, camera_stamp_s=self._t_camera)
