"""The apron estimator node's loop core (pure): inputs gated and fed, ``apron/state`` out.

Everything between the node's subscriptions and its publication, on plain numbers: stamps
judged against the node clock ``now`` (stale / future), implausible readings refused (an
orientation without estimate or off-unit, a non-finite or > 16 g specific force, a malformed
block list), odometry and velocity of one stamp paired, and the state published or withheld
(no fresh attitude or position, a clock that did not advance). The ROS node, the in-process
runner and the golden replay all feed this object; the algorithm is
:class:`~apron_estimator.estimator.ApronEstimator`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
import math

from deckland_common.checks import InputGuard, finite
from deckland_common.contract import ApronState, PixyBlock
from deckland_common.frames import quaternion_to_euler

from apron_estimator.deck import DeckFusion, DeckFusionParams
from apron_estimator.estimator import ApronEstimator
from apron_estimator.inputs import (
    LocalPosition,
    LocalPositionPairer,
    blocks_from_cloud,
    lidar_range,
    world_accel_from_specific_force,
)
from deckland_common import validate as chk

#: Largest plausible IMU specific force per axis (m/s²): 16 g, the full scale of the Pixhawk
#: IMUs. A larger (finite) reading cannot come from the sensor; fed to the core it wrecks the
#: horizontal filter's acceleration integrals for good (test/system/test_fuzz_nodes.py).
MAX_SPECIFIC_FORCE_MPS2 = 16.0 * 9.80665

#: Variance (m², m²/s², rad²) published for a quantity that is not known.
UNKNOWN_VAR = 1.0e4

REJECTED = ('stale_stamp', 'future_stamp', 'malformed_cloud', 'no_orientation',
            'bad_quaternion', 'non_finite', 'out_of_order', 'implausible')
WITHHELD = ('no_attitude', 'no_position', 'non_finite_output', 'clock_not_advancing')
TRIGGERS = ('imu', 'camera', 'imu_thinned', 'loop')

Vec3 = tuple[float, float, float]


class EstimatorLoop(InputGuard):
    """The estimator node between its inputs and ``apron/state``.

    Args:
        estimator: the core it feeds.
        input_timeout_s: inputs older (or newer) than this vs ``now`` are rejected; no state
            is published while the attitude or the local position is this stale.
        gravity_mps2: g removed from the rotated specific force.
        position_pair_tolerance_s: largest stamp difference of a position + velocity pair.
        imu_min_spacing_s: :meth:`publish_on_imu` publishes unless the previous IMU-triggered
            publication is less than this old (the node: 0.5 / rate_hz).

    Every ``on_*`` method returns True when the input was accepted.
    """

    def __init__(self, estimator: ApronEstimator, input_timeout_s: float = 0.5,
                 gravity_mps2: float = 9.81, position_pair_tolerance_s: float = 0.005,
                 imu_min_spacing_s: float = 0.005,
                 deck: DeckFusionParams | None = None) -> None:
        chk.positive('EstimatorLoop.input_timeout_s', input_timeout_s)
        chk.positive('EstimatorLoop.gravity_mps2', gravity_mps2)
        chk.non_negative('EstimatorLoop.imu_min_spacing_s', imu_min_spacing_s)
        super().__init__(REJECTED, WITHHELD)
        self.estimator = estimator
        #: the moving deck: beacon, ship telemetry (deck/odom), prediction (apron_estimator.deck)
        self.deck = DeckFusion(deck)
        self._t_deck = -math.inf
        self.pairer = LocalPositionPairer(position_pair_tolerance_s)
        self.timeout_s = float(input_timeout_s)
        self.gravity_mps2 = float(gravity_mps2)
        self.imu_min_spacing_s = float(imu_min_spacing_s)
        # last accepted stamp per input stream (-inf = never): see last_stamp
        self._t_imu = self._t_odom = self._t_velocity = -math.inf
        self._t_range = self._t_camera = -math.inf
        #: publications by trigger; IMU ticks not publishing (closer than imu_min_spacing_s)
        self.triggers: dict[str, int] = dict.fromkeys(TRIGGERS, 0)
        self.published = 0
        self.last_state: ApronState | None = None
        self.t_position_s = -math.inf      # stamp of the last local position fed
        self._t_published = -math.inf      # t_s of the last published state
        self._t_imu_published = -math.inf  # now of the last IMU-triggered publication

    @property
    def last_stamp(self) -> dict[str, float | None]:
        """The last accepted stamp per input stream (None = never)."""
        stamps = (('imu', self._t_imu), ('odom', self._t_odom), ('velocity', self._t_velocity),
                  ('range', self._t_range), ('camera', self._t_camera))
        return {k: (t if t > -math.inf else None) for k, t in stamps}

    def _fresh(self, now_s: float, t_s: float, what: str) -> bool:
        if now_s - t_s > self.timeout_s:
            self.reject('stale_stamp', what)
            return False
        if t_s - now_s > self.timeout_s:
            self.reject('future_stamp', what)
            return False
        return True

    # --- inputs ------------------------------------------------------------------------------

    def on_imu(self, now_s: float, t_s: float, q: tuple[float, float, float, float],
               specific_force_flu: Sequence[float], has_orientation: bool = True) -> bool:
        """``vehicle/imu``: orientation (w, x, y, z) → attitude, specific force → ENU accel.

        True when the attitude was accepted (a rejected acceleration is counted apart).
        ``has_orientation`` False is REP-145's "no orientation estimate" (covariance −1).
        """
        if not self._fresh(now_s, t_s, 'vehicle/imu'):
            return False
        if not has_orientation:
            self.reject('no_orientation', 'vehicle/imu')
            return False
        qn = self.unit_quaternion(q, 'vehicle/imu orientation')
        if qn is None:
            return False
        roll, pitch, yaw = quaternion_to_euler(qn[0], qn[1], qn[2], qn[3])
        self.estimator.on_attitude(t_s, roll, pitch, yaw)
        self._t_imu = t_s
        acc = world_accel_from_specific_force(qn, specific_force_flu, self.gravity_mps2)
        if acc is None:
            self.reject('non_finite', 'vehicle/imu linear_acceleration')
        elif max(abs(c) for c in specific_force_flu) > MAX_SPECIFIC_FORCE_MPS2:
            self.reject('implausible', 'vehicle/imu linear_acceleration (beyond 16 g)')
        else:
            self.estimator.on_accel(t_s, acc)
        return True

    def on_attitude(self, now_s: float, t_s: float, roll_rad: float, pitch_rad: float,
                    yaw_rad: float) -> bool:
        """Attitude already as Z-Y-X Euler angles (the in-process runner)."""
        if not self._fresh(now_s, t_s, 'attitude'):
            return False
        self.estimator.on_attitude(t_s, roll_rad, pitch_rad, yaw_rad)
        self._t_imu = t_s
        return True

    def on_accel(self, now_s: float, t_s: float, accel_world_mps2: Vec3) -> bool:
        """Vehicle acceleration already in ENU, gravity removed (the in-process runner)."""
        if not self._fresh(now_s, t_s, 'acceleration'):
            return False
        self.estimator.on_accel(t_s, accel_world_mps2)
        return True

    def on_position(self, now_s: float, t_s: float, position_m: Vec3) -> bool:
        """``vehicle/odom`` position; fed with the velocity of the same stamp."""
        if not self._fresh(now_s, t_s, 'vehicle/odom'):
            return False
        self._t_odom = t_s
        self._feed_pair(self.pairer.on_position(t_s, position_m), t_s, 'vehicle/odom')
        return True

    def on_velocity(self, now_s: float, t_s: float, velocity_mps: Vec3) -> bool:
        """``vehicle/velocity`` (ENU); fed with the position of the same stamp."""
        if not self._fresh(now_s, t_s, 'vehicle/velocity'):
            return False
        self._t_velocity = t_s
        self._feed_pair(self.pairer.on_velocity(t_s, velocity_mps), t_s, 'vehicle/velocity')
        return True

    def _feed_pair(self, pair: LocalPosition | None, t_s: float, what: str) -> None:
        if pair is not None:
            self.t_position_s = pair.t_s
            self.estimator.on_local_position(pair.t_s, pair.position_m, pair.velocity_mps)
        elif t_s < self.pairer.last_t_s:
            self.reject('out_of_order', what)

    def on_local_position(self, now_s: float, t_s: float, position_m: Vec3,
                          velocity_mps: Vec3) -> bool:
        """Position and velocity already paired (the in-process runner)."""
        if not self._fresh(now_s, t_s, 'local position'):
            return False
        self.t_position_s = t_s
        self.estimator.on_local_position(t_s, position_m, velocity_mps)
        return True

    def on_range(self, now_s: float, t_s: float, range_m: float, min_range_m: float,
                 max_range_m: float) -> bool:
        """``vehicle/range`` (REP-117: ±inf or outside the limits = no return)."""
        return self.on_lidar(now_s, t_s, lidar_range(range_m, min_range_m, max_range_m),
                             'vehicle/range')

    def on_lidar(self, now_s: float, t_s: float, range_m: float | None,
                 what: str = 'lidar') -> bool:
        """Lidar range, None = no return."""
        if not self._fresh(now_s, t_s, what):
            return False
        self._t_range = t_s
        self.estimator.on_lidar(t_s, range_m)
        return True

    def on_blocks(self, now_s: float, t_s: float, xs: Sequence[float], ys: Sequence[float],
                  channels: Mapping[str, Sequence[float]]) -> bool:
        """``pixy/blocks``: points (x_px, y_px) and the channels of docs/interfaces.md."""
        if not self._fresh(now_s, t_s, 'pixy/blocks'):
            return False
        blocks = blocks_from_cloud(xs, ys, channels)
        if blocks is None:
            self.reject('malformed_cloud', 'pixy/blocks (channels inconsistent with points)')
            return False
        self._t_camera = t_s
        self._camera(t_s, blocks)
        return True

    def on_camera(self, now_s: float, t_s: float, blocks: Sequence[PixyBlock]) -> bool:
        """One camera frame as blocks, ``t_s`` = its exposure stamp (the in-process runner)."""
        if not self._fresh(now_s, t_s, 'camera frame'):
            return False
        self._t_camera = t_s
        self._camera(t_s, blocks)
        return True

    def _camera(self, t_s: float, blocks: Sequence[PixyBlock]) -> None:
        """A frame to the estimator, with the deck velocity a new track assumes: the ship's
        telemetry when fresh, else at rest (apron_estimator README, D7)."""
        tel = self.deck.telemetry_at(t_s)
        self.estimator.on_camera(t_s, blocks, tel[1] if tel is not None else (0.0, 0.0))

    def on_deck_odom(self, now_s: float, t_s: float, position_m: Vec3, velocity_mps: Vec3,
                     attitude_valid: bool = False, rpy_rad: Vec3 = (0.0, 0.0, 0.0),
                     yaw_rate_radps: float = 0.0,
                     rates_flu_radps: Vec3 = (0.0, 0.0, 0.0)) -> bool:
        """``deck/odom``: the ship's telemetry, ENU, stamped at its measurement time (older
        than the input timeout is normal for telemetry: the deck fusion judges its age)."""
        if t_s - now_s > self.timeout_s:
            self.reject('future_stamp', 'deck/odom')
            return False
        if not self.deck.on_telemetry(t_s, position_m, velocity_mps, attitude_valid, rpy_rad,
                                      yaw_rate_radps, rates_flu_radps):
            self.reject('non_finite' if not finite(t_s) or t_s > self._t_deck
                        else 'out_of_order', 'deck/odom')
            return False
        self._t_deck = t_s
        return True

    # --- output ------------------------------------------------------------------------------

    def withhold_reason(self, now_s: float) -> str:
        """Why no state may be published at ``now_s`` ('' = it may)."""
        if now_s - self._t_imu > self.timeout_s:   # -inf: never
            return 'no_attitude'
        t_pos = self.t_position_s
        if not finite(t_pos) or now_s - t_pos > self.timeout_s:
            return 'no_position'
        return ''

    def publish(self, now_s: float, trigger: str = 'loop') -> ApronState | None:
        """``state(now_s)`` to publish (counted under ``trigger``), or None (withheld);
        ``t_s`` strictly increases."""
        reason = self.withhold_reason(now_s)
        if not reason and now_s <= self._t_published:
            reason = 'clock_not_advancing'   # downstream rejects repeated or older t_s
        st: ApronState | None = None
        if not reason:
            st = self.deck.fuse(self.estimator.state(now_s), self.estimator.deck_accel(now_s))
            if st.has_nan():  # defensive: the core never does this
                reason = 'non_finite_output'
        if reason or st is None:
            self.withhold(reason)
            return None
        self.withheld_reason = ''
        self.last_state = st
        self._t_published = now_s
        self.published += 1
        self.triggers[trigger] += 1
        return st

    def publish_on_imu(self, now_s: float) -> ApronState | None:
        """The event-driven clock: an accepted IMU message publishes, thinned to
        ``imu_min_spacing_s``."""
        if now_s - self._t_imu_published < self.imu_min_spacing_s:
            self.triggers['imu_thinned'] += 1
            return None
        st = self.publish(now_s, 'imu')
        if st is not None:
            self._t_imu_published = now_s
        return st

    # --- derived outputs and diagnostics -------------------------------------------------------

    def rel_velocity_var(self, now_s: float) -> tuple[float, float]:
        """Relative-velocity variances predicted to ``now_s``: c + q·dt of (31)-(32)."""
        h = self.estimator.horizontal
        kf = h.kf
        t_filter = h.t_filter
        dt = max(0.0, now_s - t_filter) if t_filter is not None else 0.0
        q = h.params.accel_psd_m2ps3
        return kf.cx + q * dt, kf.cy + q * dt

    def odom_variances(self, st: ApronState, now_s: float
                       ) -> tuple[float, float, float, float, float, float]:
        """``apron/odom`` variances (x, y, z, vx, vy, vz): the track's, the surface's
        (altitude + lidar), :data:`UNKNOWN_VAR` for what is not known."""
        vp = self.estimator.params.vertical
        if st.tracked:
            var_x, var_y = st.rel_position_var_m2
            var_vx, var_vy = self.rel_velocity_var(now_s)
        else:
            var_x = var_y = var_vx = var_vy = UNKNOWN_VAR
        if st.vertical.valid:
            var_z = vp.sigma_altitude_m ** 2 + vp.sigma_lidar_m ** 2
            var_vz = vp.sigma_vz_mps ** 2
        else:
            var_z = var_vz = UNKNOWN_VAR
        return var_x, var_y, var_z, var_vx, var_vy, var_vz

    def diagnostic_values(self, now_s: float) -> dict[str, str]:
        """Counters, input ages and the last state, as diagnostics key/values."""
        values = {'published': str(self.published)}
        for name, t in self.last_stamp.items():
            values[f'age_{name}_s'] = 'inf' if t is None else f'{now_s - t:.3f}'
        values['age_deck_s'] = f'{now_s - self._t_deck:.3f}' if finite(self._t_deck) else 'inf'
        values.update({f'rejected_{k}': str(v) for k, v in self.rejected.items()})
        values.update({f'withheld_{k}': str(v) for k, v in self.withheld.items()})
        values.update({f'trigger_{k}': str(v) for k, v in self.triggers.items()})
        values.update({f'core_rejected_{k}': str(v)
                       for k, v in self.estimator.rejected.items()})
        values.update({f'deck_rejected_{k}': str(v) for k, v in self.deck.rejected.items()})
        st = self.last_state
        if st is not None:
            values.update(tracked=str(st.tracked), visible=str(st.visible),
                          time_since_seen_s=f'{st.time_since_seen_s:.3f}',
                          vertical_valid=str(st.vertical.valid),
                          height_m=f'{st.vertical.height_m:.3f}',
                          surface_epoch=str(st.vertical.surface_epoch),
                          deck_source=st.source)
        return values
