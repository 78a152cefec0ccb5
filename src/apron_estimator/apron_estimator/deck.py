"""The deck as a moving target (pure): the beacon track fused with the ship's telemetry.

Sources, best first (``ApronState.source``): the tracked beacon (the estimator's apron position
and velocity, paper (27)-(35)); the ship's telemetry (``deck/odom``: coarse GNSS, delayed), moved
onto the beacon's frame by an offset learnt while both are available — the ship's GNSS error
plus the vehicle's own local-position bias — and carried to now with its velocity and
acceleration; a constant-velocity prediction from the last estimate; nothing. The deck's
acceleration comes from the beacon track's own filter while it is tracked (``beacon_accel``,
:class:`apron_estimator.horizontal.DeckAccelKF`), else from the telemetry's velocity; its
attitude and yaw rate only from telemetry. Design: apron_estimator
README, "Moving deck".
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
import math

from deckland_common.contract import (
    DECK_SOURCE_BEACON,
    DECK_SOURCE_NONE,
    DECK_SOURCE_PREDICTION,
    DECK_SOURCE_TELEMETRY,
    ApronState,
)
from deckland_common.frames import mat_vec, quaternion_to_euler, rot_body_to_world

from deckland_common import validate as chk

Vec2 = tuple[float, float]
Vec3 = tuple[float, float, float]


@dataclass(frozen=True)
class DeckFusionParams:
    """Deck fusion parameters (times in s, distances in m)."""

    telemetry_timeout_s: float = 1.5      # a telemetry sample older than this is not used
    attitude_timeout_s: float = 1.0       # deck attitude valid while this fresh
    attitude_extrapolation_s: float = 0.5  # roll / pitch / heading carried forward this long
    max_extrapolation_s: float = 2.0      # telemetry carried forward at most this long
    offset_tau_s: float = 5.0             # averaging time of the learnt GNSS offset
    offset_gate_m: float = 3.0            # a residual this far from the learnt offset: refused
    offset_max_rel_m: float = 0.3         # learn only with the beacon this close below
    beacon_history_s: float = 2.0         # beacon estimates kept to meet delayed telemetry
    prediction_timeout_s: float = 20.0    # constant-velocity prediction at most this long
    accel_tau_s: float = 1.0              # low-pass of the telemetry's deck acceleration
    max_accel_mps2: float = 5.0           # clamp of the acceleration estimate
    # while tracked, publish the beacon filter's deck acceleration (DeckAccelKF) rather than
    # the telemetry's (README "Moving deck", D6)
    beacon_accel: bool = True

    def __post_init__(self) -> None:
        o = 'DeckFusionParams'
        for name in ('telemetry_timeout_s', 'attitude_timeout_s', 'attitude_extrapolation_s',
                     'max_extrapolation_s',
                     'offset_tau_s', 'offset_gate_m', 'offset_max_rel_m', 'beacon_history_s',
                     'prediction_timeout_s', 'accel_tau_s', 'max_accel_mps2'):
            chk.positive(f'{o}.{name}', getattr(self, name))
        chk.require(isinstance(self.beacon_accel, bool), f'{o}.beacon_accel', 'must be a bool',
                    self.beacon_accel)


def telemetry_from_odometry(q_wxyz: tuple[float, float, float, float],
                            velocity_child_mps: Vec3, rates_child_radps: Vec3,
                            attitude_var_rad2: float, attitude_max_var_rad2: float = 1.0
                            ) -> tuple[Vec3, bool, Vec3, float, Vec3]:
    """``deck/odom`` (nav_msgs/Odometry, twist in the deck frame) → (velocity ENU, attitude
    valid, rpy, yaw rate, body rates): the attitude counts as known while its variance is
    below ``attitude_max_var_rad2``; ψ̇ = (ω_y sin φ + ω_z cos φ) / cos θ."""
    w, x, y, z = q_wxyz
    n = math.sqrt(w * w + x * x + y * y + z * z)
    valid = n > 0.0 and attitude_var_rad2 < attitude_max_var_rad2
    rpy = quaternion_to_euler(w / n, x / n, y / n, z / n) if n > 0.0 else (0.0, 0.0, 0.0)
    vel = mat_vec(rot_body_to_world(*rpy), velocity_child_mps)
    cp = math.cos(rpy[1])
    _, wq, wr = rates_child_radps
    yaw_rate = (wq * math.sin(rpy[0]) + wr * math.cos(rpy[0])) / cp if abs(cp) > 1e-6 else 0.0
    if not valid:
        return vel, False, (0.0, 0.0, 0.0), 0.0, (0.0, 0.0, 0.0)
    return vel, True, rpy, yaw_rate, rates_child_radps


class DeckFusion:
    """Fill the moving-deck fields of an :class:`ApronState` (see the module docstring).

    Feed :meth:`on_telemetry` with ``deck/odom`` samples (stamps in our clock, measurement
    time) and pass every published state through :meth:`fuse` (``t_s`` increasing).
    """

    def __init__(self, params: DeckFusionParams | None = None) -> None:
        self.params = params if params is not None else DeckFusionParams()
        self.rejected: dict[str, int] = {'non_finite': 0, 'out_of_order': 0, 'offset_gated': 0}
        self.offset_m: Vec2 = (0.0, 0.0)   # beacon frame − telemetry frame (learnt)
        self.offset_samples = 0
        # (t, x, y, vx, vy, usable for the offset) of the beacon-derived deck
        self._beacon: deque[tuple[float, float, float, float, float, bool]] = deque()
        self._tel: tuple[float, Vec3, Vec3] | None = None       # (t, position, velocity)
        self._tel_accel: Vec2 = (0.0, 0.0)
        self._v_ref: tuple[float, float, float] | None = None   # (t, vx, vy) of accel
        self._att: tuple[float, Vec3, Vec3] | None = None       # (t, rpy, Euler rates)
        self._pending: list[tuple[float, float, float]] = []    # telemetry (t, x, y) to meet
        self._last: tuple[float, Vec2, Vec2] | None = None      # last beacon/telemetry output

    # -- inputs ----------------------------------------------------------------------------
    def on_telemetry(self, t_s: float, position_m: Vec3, velocity_mps: Vec3,
                     attitude_valid: bool = False, rpy_rad: Vec3 = (0.0, 0.0, 0.0),
                     yaw_rate_radps: float = 0.0,
                     rates_flu_radps: Vec3 = (0.0, 0.0, 0.0)) -> bool:
        """One ``deck/odom`` sample at its measurement time ``t_s``; True if accepted.
        ``rates_flu_radps``: the deck's body rates (roll and pitch are carried to now with
        the Euler rates they give, the heading with ``yaw_rate_radps``)."""
        vals = (t_s, *position_m, *velocity_mps, *rpy_rad, yaw_rate_radps, *rates_flu_radps)
        if not all(math.isfinite(v) for v in vals):
            self.rejected['non_finite'] += 1
            return False
        if self._tel is not None and t_s <= self._tel[0]:
            self.rejected['out_of_order'] += 1
            return False
        ref = self._v_ref
        if ref is None:
            self._v_ref = (t_s, velocity_mps[0], velocity_mps[1])
        elif t_s - ref[0] >= 0.15 and (velocity_mps[0], velocity_mps[1]) != (ref[1], ref[2]):
            # acceleration from GNSS velocities of distinct fixes, low-passed
            dt = t_s - ref[0]
            a = min(1.0, dt / self.params.accel_tau_s)
            ax, ay = (velocity_mps[0] - ref[1]) / dt, (velocity_mps[1] - ref[2]) / dt
            ta = self._tel_accel
            self._tel_accel = (ta[0] + a * (ax - ta[0]), ta[1] + a * (ay - ta[1]))
            self._v_ref = (t_s, velocity_mps[0], velocity_mps[1])
        self._tel = (t_s, position_m, velocity_mps)
        if attitude_valid:
            roll, pitch = rpy_rad[0], rpy_rad[1]
            wp, wq, wr = rates_flu_radps
            cr, sr = math.cos(roll), math.sin(roll)
            # Z-Y-X Euler kinematics: φ̇ = p + (q sφ + r cφ) tan θ, θ̇ = q cφ − r sφ
            rates = (wp + (wq * sr + wr * cr) * math.tan(pitch), wq * cr - wr * sr,
                     yaw_rate_radps)
            self._att = (t_s, rpy_rad, rates)
        self._pending.append((t_s, position_m[0], position_m[1]))
        self._learn()
        return True

    def _beacon_at(self, t_s: float) -> Vec2 | None:
        """The beacon-derived deck position at ``t_s`` (linear between kept estimates)."""
        h = self._beacon
        if not h or t_s < h[0][0] or t_s > h[-1][0]:
            return None
        prev = h[0]
        for e in h:
            if e[0] >= t_s:
                if e[0] - prev[0] > 0.2 or not (e[5] and prev[5]):
                    return None              # a gap in the track, or not usable there
                w = 0.0 if e[0] == prev[0] else (t_s - prev[0]) / (e[0] - prev[0])
                return (prev[1] + w * (e[1] - prev[1]), prev[2] + w * (e[2] - prev[2]))
            prev = e
        return None

    def _learn(self) -> None:
        """Telemetry samples met by beacon estimates at their stamps update the offset."""
        if not self._pending:
            return
        p = self.params
        t_latest = self._beacon[-1][0] if self._beacon else -math.inf
        keep = []
        for t, x, y in self._pending:
            if t > t_latest:
                keep.append((t, x, y))       # the beacon estimate at t is still to come
                continue
            b = self._beacon_at(t)
            if b is None:
                continue
            rx, ry = b[0] - x, b[1] - y
            ox, oy = self.offset_m
            n = self.offset_samples
            if n >= 10 and math.hypot(rx - ox, ry - oy) > p.offset_gate_m:
                self.rejected['offset_gated'] += 1
                continue
            # running mean for the first samples, then an exponential average (τ)
            w = max(1.0 / (n + 1), 0.2 / p.offset_tau_s)
            self.offset_m = (ox + w * (rx - ox), oy + w * (ry - oy))
            self.offset_samples = n + 1
        self._pending = keep[-20:]

    # -- output ----------------------------------------------------------------------------
    def telemetry_at(self, t_s: float) -> tuple[Vec2, Vec2] | None:
        """Telemetry deck position (offset applied) and velocity at ``t_s``, or None."""
        tel = self._tel
        p = self.params
        if tel is None or t_s - tel[0] > p.telemetry_timeout_s:
            return None
        dt = min(max(0.0, t_s - tel[0]), p.max_extrapolation_s)
        (x, y, _), (vx, vy, _) = tel[1], tel[2]
        ax, ay = self._tel_accel
        ox, oy = self.offset_m
        return ((x + ox + vx * dt + 0.5 * ax * dt * dt, y + oy + vy * dt + 0.5 * ay * dt * dt),
                (vx + ax * dt, vy + ay * dt))

    def fuse(self, st: ApronState, beacon_accel_mps2: Vec2 | None = None) -> ApronState:
        """``st`` with source, apron position / velocity / acceleration and deck attitude.
        ``beacon_accel_mps2``: the beacon filter's deck acceleration (ENU; None while it is
        not known: ``HorizontalTracker.deck_accel``)."""
        p = self.params
        t = st.t_s
        h = self._beacon
        tel = self.telemetry_at(t)
        lim = p.max_accel_mps2
        if st.tracked:
            pos, vel = st.apron_position_m, st.apron_velocity_mps
            if p.beacon_accel and beacon_accel_mps2 is not None:
                acc = beacon_accel_mps2          # D6
            else:
                acc = self._tel_accel if tel is not None else (0.0, 0.0)
            # the camera offsets scale with the height above the surface the lidar sees: from
            # beside the deck (the sea or ground below) they are over-scaled (estimator README,
            # Known limitations); close above the beacon the error is that small fraction
            usable = math.hypot(*st.rel_position_m) <= p.offset_max_rel_m
            h.append((t, pos[0], pos[1], vel[0], vel[1], usable))
            while h and t - h[0][0] > p.beacon_history_s:
                h.popleft()
            self._learn()
            source = DECK_SOURCE_BEACON
        else:
            h.clear()
            if tel is not None:
                pos, vel = tel
                acc = self._tel_accel
                source = DECK_SOURCE_TELEMETRY
            elif self._last is not None and t - self._last[0] <= p.prediction_timeout_s:
                t0, p0, v0 = self._last
                dt = t - t0
                pos, vel, acc = (p0[0] + v0[0] * dt, p0[1] + v0[1] * dt), v0, (0.0, 0.0)
                source = DECK_SOURCE_PREDICTION
            else:
                pos, vel, acc = st.apron_position_m, st.apron_velocity_mps, (0.0, 0.0)
                source = DECK_SOURCE_NONE
        if source in (DECK_SOURCE_BEACON, DECK_SOURCE_TELEMETRY):
            self._last = (t, pos, vel)
        acc = (max(-lim, min(lim, acc[0])), max(-lim, min(lim, acc[1])))
        att = self._att
        att_valid = att is not None and t - att[0] <= p.attitude_timeout_s
        rpy: Vec3 = (0.0, 0.0, 0.0)
        yaw_rate = 0.0
        if att is not None and att_valid:
            dt = min(max(0.0, t - att[0]), p.attitude_extrapolation_s)
            r, pt, y = att[1]
            dr, dp, yaw_rate = att[2]
            rpy = (r + dr * dt, pt + dp * dt, math.remainder(y + yaw_rate * dt, 2.0 * math.pi))
        return ApronState(
            t_s=st.t_s, tracked=st.tracked, visible=st.visible,
            time_since_seen_s=st.time_since_seen_s, rel_position_m=st.rel_position_m,
            rel_velocity_mps=st.rel_velocity_mps, rel_position_var_m2=st.rel_position_var_m2,
            rel_position_body_m=st.rel_position_body_m,
            rel_velocity_body_mps=st.rel_velocity_body_mps,
            apron_position_m=(float(pos[0]), float(pos[1])),
            apron_velocity_mps=(float(vel[0]), float(vel[1])), vertical=st.vertical,
            camera_stamp_s=st.camera_stamp_s, source=source, apron_accel_mps2=acc,
            deck_attitude_valid=att_valid, deck_rpy_rad=rpy, deck_yaw_rate_radps=yaw_rate)
