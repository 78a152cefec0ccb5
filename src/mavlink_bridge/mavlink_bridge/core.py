"""Decision logic of the MAVLink bridge (pure, time-driven, no sockets, no rclpy).

The node feeds every event with its receive time ``t_s`` and sends what :class:`BridgeCore`
returns: link state, input freshness and the data-aware setpoint stream, the OFFBOARD /
GUIDED_NOGPS entry (only while the autopilot's safety-relevant parameters are known and safe,
re-checked at every send), ArduPilot's stop action (LAND: its GUIDED_NOGPS never lands by
itself), arm/mode requests with the retries PX4 v1.16 and ArduCopter 4.5 need, telemetry
requests driven by their ACKs and trims, STATUSTEXT, and :class:`LinkMonitor` (TIMESYNC).
The decisions and their measurements are in the package README. Bad input is counted in
``rejected`` and never changes the state.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field, replace
import math

from deckland_common.frames import quaternion_to_euler

from mavlink_bridge.conversions import (
    MAV_MODE_FLAG_SAFETY_ARMED,
    MAV_PARAM_TYPE_REAL32,
    PX4_OFFBOARD_LOSS_ACTIONS,
    ThrustCalibration,
    do_set_mode_params,
    euler_enu_to_quat_ned,
    landed_from_extended_sys_state,
    mode_name,
    param_value_from_wire,
    quat_enu_flu_to_ned_frd,
    quat_normalize,
)
from mavlink_bridge.monitors import HoverThrustEstimator, SetpointStats

MAV_CMD_DO_SET_MODE = 176
MAV_CMD_COMPONENT_ARM_DISARM = 400
MAV_CMD_NAV_TAKEOFF = 22
MAV_CMD_SET_MESSAGE_INTERVAL = 511
MAV_RESULT_ACCEPTED = 0
MAV_RESULT_TEMPORARILY_REJECTED = 1
MAV_RESULT_DENIED = 2
MAV_RESULT_UNSUPPORTED = 3
MAV_RESULT_FAILED = 4
MAV_RESULT_IN_PROGRESS = 5
MAV_AUTOPILOT_INVALID = 8
MAV_TYPE_GCS = 6
MAV_TYPE_ONBOARD_CONTROLLER = 18

MSG_ID = {'HEARTBEAT': 0, 'SCALED_IMU': 26, 'ATTITUDE': 30, 'LOCAL_POSITION_NED': 32,
          'ATTITUDE_TARGET': 83, 'HIGHRES_IMU': 105, 'DISTANCE_SENSOR': 132,
          'EXTENDED_SYS_STATE': 245}
#: messages that are never trimmed: protocol traffic (answers, parameters, time sync, the
#: autopilot's reasons — STATUSTEXT and PX4's EVENT / CURRENT_EVENT_SEQUENCE), not streams
KEEP_MSG_IDS = frozenset({0, 22, 77, 111, 253, 410, 411, 413})
#: the PX4 parameters the bridge reads before OFFBOARD (see :meth:`BridgeCore.px4_config_problem`)
PX4_PARAMS = ('COM_OBL_RC_ACT', 'COM_OF_LOSS_T', 'MPC_THR_HOVER')
#: the ArduCopter 4.5 parameters the bridge reads (:meth:`BridgeCore.ardupilot_config_problem`
#: needs the first four; the others are reported in diagnostics)
ARDUPILOT_PARAMS = ('GUID_OPTIONS', 'ATC_ANGLE_BOOST', 'GUID_TIMEOUT', 'MOT_THST_HOVER',
                    'MOT_THST_EXPO', 'FS_GCS_ENABLE', 'SYSID_MYGCS')
#: ArduCopter GUID_OPTIONS bit 3 (value 8): SET_ATTITUDE_TARGET.thrust is thrust, not climb rate.
GUID_OPTIONS_THRUST_BIT = 8
#: ``ardupilot_stop_action`` → the ArduCopter mode the bridge commands ('' = none)
ARDUPILOT_STOP_MODES = {'land': 'LAND', 'loiter': 'LOITER', 'none': ''}
#: a SET_MESSAGE_INTERVAL not acknowledged within this is forgotten (its ACK was lost)
_INTERVAL_ACK_TIMEOUT_S = 2.0


@dataclass(frozen=True, slots=True)
class BridgeParams:
    """Bridge timing and autopilot choice (validated at construction)."""

    autopilot: str = 'px4'                 # 'px4' | 'ardupilot'
    input_timeout_s: float = 0.2           # max age of thrust and attitude commands
    link_timeout_s: float = 3.0            # autopilot HEARTBEAT age that means link lost
    max_stream_rate_hz: float = 250.0      # long-term SET_ATTITUDE_TARGET cap (bucket refill)
    stream_burst: int = 3                  # setpoints allowed back to back (bucket depth)
    fresh_period_s: float = 0.02           # source stamp this much newer: always sent (50 Hz)
    offboard_warmup_s: float = 0.2         # streaming time before the mode request
    max_stream_gap_s: float = 0.5          # larger gaps restart the warm-up (2 Hz minimum)
    heartbeat_period_s: float = 1.0
    command_retry_s: float = 0.5
    command_timeout_s: float = 5.0
    interval_refresh_s: float = 10.0       # re-send SET_MESSAGE_INTERVAL (autopilot reboots)
    attitude_rate_hz: float = 100.0
    local_position_rate_hz: float = 50.0
    distance_sensor_rate_hz: float = 50.0
    imu_rate_hz: float = 100.0
    extended_sys_state_rate_hz: float = 5.0
    attitude_target_rate_hz: float = 10.0  # PX4 ATTITUDE_TARGET (hover-thrust measurement)
    use_highres_imu: bool = True           # HIGHRES_IMU, else SCALED_IMU
    target_component: int = 1              # autopilot component id (MAV_COMP_ID_AUTOPILOT1)
    system_id: int = 1                     # our own system id (ArduPilot SYSID_MYGCS check)
    #: PX4 COM_OBL_RC_ACT values (by name) OFFBOARD may be entered with: what PX4 does when the
    #: setpoints stop (PX4_OFFBOARD_LOSS_ACTIONS); unknown counts as unsafe
    offboard_loss_actions: tuple[str, ...] = ('land', 'hold')
    max_offboard_loss_timeout_s: float = 2.0   # PX4 COM_OF_LOSS_T above this: refuse OFFBOARD
    #: 'autopilot': PX4's own hover (ATTITUDE_TARGET in its hover, else MPC_THR_HOVER);
    #: 'parameter': thrust.hover_thrust_norm as configured
    hover_thrust_source: str = 'autopilot'
    hover_window_s: float = 4.0            # steady-hover window of the measurement
    trim_telemetry: bool = True            # SET_MESSAGE_INTERVAL -1 for unused streams
    param_retry_s: float = 2.0             # PARAM_REQUEST_READ repeated until answered ...
    param_max_requests: int = 5            # ... at most this often per parameter and link
    #: ArduPilot: what the bridge commands when its setpoints stop while ArduPilot flies them
    #: (ARDUPILOT_STOP_MODES: 'land' = LAND, 'loiter' = LOITER, 'none' = GUIDED_NOGPS's own
    #: timeout: level and hold altitude, indefinitely)
    ardupilot_stop_action: str = 'land'
    stop_after_s: float = 0.3              # ArduPilot: stream gap that triggers the stop action
    disarm_timeout_s: float = 15.0         # ArduPilot: a refused (FAILED) disarm retried so long
    disarm_retry_s: float = 1.0            # ... this often
    statustext_repeat_s: float = 5.0       # the same STATUSTEXT within this is not logged again
    link_monitor: LinkMonitorParams = field(default_factory=lambda: LinkMonitorParams())
    thrust: ThrustCalibration = field(default_factory=ThrustCalibration)

    def __post_init__(self) -> None:
        if self.autopilot not in ('px4', 'ardupilot'):
            raise ValueError(f"BridgeParams.autopilot = {self.autopilot!r}: must be 'px4' or "
                             "'ardupilot'")
        for name in ('input_timeout_s', 'link_timeout_s', 'max_stream_rate_hz', 'fresh_period_s',
                     'max_stream_gap_s', 'heartbeat_period_s',
                     'command_retry_s', 'command_timeout_s', 'interval_refresh_s',
                     'attitude_rate_hz', 'local_position_rate_hz', 'distance_sensor_rate_hz',
                     'imu_rate_hz', 'extended_sys_state_rate_hz', 'attitude_target_rate_hz',
                     'max_offboard_loss_timeout_s', 'hover_window_s', 'param_retry_s',
                     'stop_after_s', 'disarm_timeout_s', 'disarm_retry_s',
                     'statustext_repeat_s'):
            v = getattr(self, name)
            if not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0.0:
                raise ValueError(f'BridgeParams.{name} = {v!r}: must be a finite number > 0')
        w = self.offboard_warmup_s
        if isinstance(w, bool) or not isinstance(w, int | float) or not math.isfinite(w) \
                or not 0.0 <= w < self.command_timeout_s:
            raise ValueError(f'BridgeParams.offboard_warmup_s = {w!r}: must be in [0, '
                             f'command_timeout_s = {self.command_timeout_s!r}) (PX4 v1.16 '
                             'needs one setpoint younger than COM_OF_LOSS_T)')
        acts = self.offboard_loss_actions
        if not isinstance(acts, tuple) or not all(
                a in PX4_OFFBOARD_LOSS_ACTIONS.values() for a in acts):
            raise ValueError(f'BridgeParams.offboard_loss_actions = {acts!r}: must be a tuple '
                             f'of {sorted(PX4_OFFBOARD_LOSS_ACTIONS.values())}')
        if self.ardupilot_stop_action not in ARDUPILOT_STOP_MODES:
            raise ValueError(f'BridgeParams.ardupilot_stop_action = '
                             f'{self.ardupilot_stop_action!r}: must be one of '
                             f'{sorted(ARDUPILOT_STOP_MODES)}')
        n = self.param_max_requests
        if isinstance(n, bool) or not isinstance(n, int) or not 1 <= n <= 1000:
            raise ValueError(f'BridgeParams.param_max_requests = {n!r}: must be an integer in '
                             '[1, 1000]')
        if not isinstance(self.use_highres_imu, bool):
            raise ValueError(f'BridgeParams.use_highres_imu = {self.use_highres_imu!r}: must '
                             'be a bool')
        if self.hover_thrust_source not in ('autopilot', 'parameter'):
            raise ValueError(f'BridgeParams.hover_thrust_source = {self.hover_thrust_source!r}:'
                             " must be 'autopilot' or 'parameter'")
        if isinstance(self.stream_burst, bool) or not isinstance(self.stream_burst, int) or \
                not 1 <= self.stream_burst <= 100:
            raise ValueError(f'BridgeParams.stream_burst = {self.stream_burst!r}: must be an '
                             'integer in [1, 100]')
        if self.fresh_period_s > self.max_stream_gap_s:
            raise ValueError(f'BridgeParams.fresh_period_s = {self.fresh_period_s!r}: must be '
                             f'<= max_stream_gap_s ({self.max_stream_gap_s!r})')
        if self.max_stream_gap_s > 0.5:
            raise ValueError(f'BridgeParams.max_stream_gap_s = {self.max_stream_gap_s!r}: '
                             'must be <= 0.5 s (PX4 needs > 2 Hz)')
        if not 1 <= self.system_id <= 255:
            raise ValueError(f'BridgeParams.system_id = {self.system_id!r}: must be in '
                             '[1, 255]')
        if not 0 <= self.target_component <= 255:
            raise ValueError(f'BridgeParams.target_component = {self.target_component!r}: '
                             'must be in [0, 255]')
        if not isinstance(self.thrust, ThrustCalibration):
            raise ValueError('BridgeParams.thrust must be a ThrustCalibration')
        if not isinstance(self.link_monitor, LinkMonitorParams):
            raise ValueError('BridgeParams.link_monitor must be a LinkMonitorParams')

    @property
    def offboard_mode(self) -> str:
        """Mode name the bridge requests: OFFBOARD (PX4) or GUIDED_NOGPS (ArduPilot)."""
        return 'OFFBOARD' if self.autopilot == 'px4' else 'GUIDED_NOGPS'


@dataclass(frozen=True, slots=True)
class AttitudeSetpoint:
    """One SET_ATTITUDE_TARGET to send (NED/FRD quaternion, normalised thrust)."""

    t_s: float
    q_ned_frd: tuple[float, float, float, float]
    thrust_norm: float
    thrust_n: float
    roll_rad: float       # ENU/FLU, for logging
    pitch_rad: float
    yaw_rad: float
    type_mask: int = 7    # ignore body rates; use attitude and thrust


@dataclass(frozen=True, slots=True)
class Outgoing:
    """Something the node must send: a HEARTBEAT, a COMMAND_LONG or a PARAM_REQUEST_READ."""

    kind: str               # 'heartbeat' | 'command' | 'param_request' | 'timesync'
    #                         ('timesync': a TIMESYNC request, tc1 = 0, ts1 = params[0] s → ns)
    command: int = 0
    params: tuple[float, ...] = (0.0,) * 7
    param_id: str = ''
    note: str = ''


_HEARTBEAT = Outgoing('heartbeat')


class StreamLimiter:
    """Data-aware cap of the SET_ATTITUDE_TARGET rate (pure; times in seconds).

    A token bucket in receive time ``t_s``: it holds at most ``burst`` tokens, refilled at
    ``rate_hz``; sending costs one token. So a command goes out the moment it arrives as long as
    the *long-term* rate stays below ``rate_hz`` — two triggers that arrive together (the IMU
    tick and a camera frame of the same instant, each producing a new state and a new thrust)
    both pass, while a flood is held to ``rate_hz`` (the link budget). ``burst = 1`` is a plain
    minimum interval of ``1 / rate_hz``.

    Data-aware exception: a command whose *source stamp* is at least ``fresh_period_s`` newer
    than that of the last command sent is never dropped (the bucket is then emptied, not
    overdrawn): rate limiting may thin redundant commands, never starve new data.
    """

    __slots__ = ('_burst', '_fresh', '_last_sent_stamp', '_rate', '_t_s', '_tokens')

    def __init__(self, rate_hz: float, burst: int, fresh_period_s: float) -> None:
        self._rate = float(rate_hz)
        self._burst = float(burst)
        self._fresh = float(fresh_period_s)
        self.reset()

    def reset(self) -> None:
        self._tokens = self._burst
        self._t_s = -math.inf
        self._last_sent_stamp = -math.inf

    def allow(self, t_s: float, stamp_s: float) -> bool:
        """True when a command received at ``t_s`` with source stamp ``stamp_s`` may be sent
        now (and it is then accounted as sent). Inputs must be finite (the core checks)."""
        dt = t_s - self._t_s
        if dt > 0.0:  # a receive time going backwards refills nothing
            tokens = self._tokens + dt * self._rate
            self._tokens = tokens if tokens < self._burst else self._burst
            self._t_s = t_s
        # 1e-9: float rounding of tokens and of stamps (ROS stamps are integer ns)
        if self._tokens >= 1.0 - 1e-9:
            self._tokens = max(self._tokens - 1.0, 0.0)
        elif stamp_s - self._last_sent_stamp >= self._fresh - 1e-9:
            self._tokens = 0.0
        else:
            return False
        self._last_sent_stamp = stamp_s
        return True


@dataclass(frozen=True, slots=True)
class LinkMonitorParams:
    """MAVLink link-latency monitor (TIMESYNC round trips), validated at construction."""

    period_s: float = 0.1          # TIMESYNC request period (MAVROS/PX4 use 10 Hz)
    max_latency_s: float = 0.06    # one-way latency (RTT / 2) above which the link is degraded
    window: int = 4                # estimate = minimum of the last `window` one-way samples
    confirm_s: float = 0.2         # the estimate must stay above the limit this long
    max_outstanding: int = 64      # unanswered requests remembered (older ones are forgotten)

    def __post_init__(self) -> None:
        for name in ('period_s', 'max_latency_s'):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v) \
                    or v <= 0.0:
                raise ValueError(f'LinkMonitorParams.{name} = {v!r}: must be a finite number '
                                 '> 0')
        v = self.confirm_s
        if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v) \
                or v < 0.0:
            raise ValueError(f'LinkMonitorParams.confirm_s = {v!r}: must be a finite number '
                             '>= 0')
        for name, hi in (('window', 100), ('max_outstanding', 10000)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or not 1 <= v <= hi:
                raise ValueError(f'LinkMonitorParams.{name} = {v!r}: must be an integer in '
                                 f'[1, {hi}]')


class LinkMonitor:
    """Link latency from MAVLink TIMESYNC round trips; decides when to stop commanding.

    Beyond the paper: its loops (horizontal PID, DOB altitude law (16)-(19)) assume the
    commanded attitude and thrust act at once; the inner loops have time constants of
    ~0.1 s, so an actuation delay of that order destroys their phase margin
    (docs/failsafe.md, "Latency"). The companion therefore measures the link the way MAVROS
    does: every ``period_s`` it sends TIMESYNC(tc1 = 0, ts1 = its send time); the autopilot
    echoes ts1 in its reply, so ``rtt = t_received - ts1`` needs no clock agreement.

    * one-way sample = rtt / 2 (a symmetric link; the loop delay the link adds is the whole
      rtt: telemetry one way, the command back);
    * estimate :attr:`latency_s` = the minimum of the last ``window`` samples (queueing and
      polling jitter only ever *add* delay, so the minimum is the robust floor);
    * :attr:`degraded` once the estimate has stayed above ``max_latency_s`` for
      ``confirm_s`` (checked at each reply). It latches: a link that was too slow is not
      trusted again until :meth:`reset` (the operator's explicit offboard request), because
      re-engaging a loop that integrated against a vehicle it did not control gave hard
      touchdowns (docs/failsafe.md, "No automatic re-engagement").

    Lost requests are simply never answered (no sample): packet loss is not latency.
    Replies must match a request still remembered (``max_outstanding``) and arrive in time
    order; anything else is counted in :attr:`rejected` and changes nothing.
    """

    __slots__ = ('_exceed_since', '_last_rx_s', '_next_s', '_outstanding', '_samples', 'counters',
                 'degraded', 'degraded_since_s', 'params', 'reason', 'rejected', 'rtt_s')

    def __init__(self, params: LinkMonitorParams | None = None) -> None:
        self.params = params or LinkMonitorParams()
        self.rejected: dict[str, int] = {'nan': 0, 'out_of_order': 0, 'unknown_request': 0,
                                         'negative_rtt': 0}
        self.counters: dict[str, int] = {'requests': 0, 'replies': 0, 'exceeded': 0}
        self.reset()

    def reset(self) -> None:
        """Forget the samples and clear :attr:`degraded` (counters are kept)."""
        self._outstanding: list[float] = []
        self._samples: list[float] = []
        self._next_s = -math.inf
        self._last_rx_s = -math.inf
        self._exceed_since: float | None = None
        self.rtt_s = math.nan
        self.degraded = False
        self.degraded_since_s = math.nan
        self.reason = ''

    @property
    def latency_s(self) -> float:
        """One-way latency estimate (s): min of the last ``window`` rtt/2; NaN before any."""
        return min(self._samples) if self._samples else math.nan

    def poll(self, t_s: float) -> bool:
        """True when a TIMESYNC request is due at ``t_s``; the caller then sends one with
        ``ts1 = t_s`` (it is remembered as outstanding)."""
        if t_s < self._next_s - 1e-9:   # the common case first (NaN fails both tests)
            return False
        if not math.isfinite(t_s):
            self.rejected['nan'] += 1
            return False
        # on the fixed schedule (no drift from the caller's tick); re-anchored after a gap
        period = self.params.period_s
        nxt = self._next_s + period
        self._next_s = nxt if nxt > t_s else t_s + period
        out = self._outstanding
        out.append(t_s)
        if len(out) > self.params.max_outstanding:
            del out[0]
        self.counters['requests'] += 1
        return True

    def on_timesync(self, t_sent_s: float, t_received_s: float) -> bool:
        """A TIMESYNC reply echoing ``t_sent_s`` (our ts1) received at ``t_received_s``.

        Returns True when it was accepted as a sample. Updates :attr:`degraded`.
        """
        if not (math.isfinite(t_sent_s) and math.isfinite(t_received_s)):
            self.rejected['nan'] += 1
            return False
        if t_received_s < self._last_rx_s:
            self.rejected['out_of_order'] += 1
            return False
        rtt = t_received_s - t_sent_s
        if rtt < 0.0:
            self.rejected['negative_rtt'] += 1
            return False
        out = self._outstanding
        for i in range(len(out) - 1, -1, -1):
            if abs(out[i] - t_sent_s) <= 1e-6:   # ts1 travels as integer ns
                del out[i]
                break
        else:
            self.rejected['unknown_request'] += 1
            return False
        self._last_rx_s = t_received_s
        self.counters['replies'] += 1
        self.rtt_s = rtt
        p = self.params
        s = self._samples
        s.append(0.5 * rtt)
        if len(s) > p.window:
            del s[0]
        if self.degraded:
            return True
        est = min(s)
        if len(s) < p.window or est <= p.max_latency_s:
            self._exceed_since = None
            return True
        if self._exceed_since is None:
            self._exceed_since = t_received_s
            self.counters['exceeded'] += 1
        if t_received_s - self._exceed_since >= p.confirm_s:
            self.degraded = True
            self.degraded_since_s = t_received_s
            self.reason = (f'link latency {est * 1e3:.0f} ms > {p.max_latency_s * 1e3:.0f} ms '
                           f'for {t_received_s - self._exceed_since:.2f} s: commanding stopped '
                           '(autopilot failsafe)')
        return True


class _Request:
    """A pending arm/mode request, retried until the HEARTBEAT confirms it or it times out.

    ``acks`` counts the COMMAND_ACKs since the last send (PX4 answers a DO_SET_MODE twice:
    the MAVLink receiver's ACCEPTED at once, then the commander's verdict); ``accepted`` is
    set by an accepting verdict (no more sends, the HEARTBEAT confirms); ``deferred`` is set
    when PX4 refused a disarm as TEMPORARILY_REJECTED (in the air): it is sent again only
    once the land detector says landed; ``refusals`` counts ArduPilot's FAILED answers to a
    disarm (retried while its land detector catches up); ``reason`` says why a stop request
    was made."""

    __slots__ = ('accepted', 'acks', 'deferred', 'from_mode', 'last_sent_s', 'reason',
                 'refusals', 'sends', 'start_s', 'value')

    def __init__(self, t_s: float, value: object, reason: str = '', from_mode: str = '') -> None:
        self.start_s = t_s
        self.last_sent_s = -math.inf
        self.value = value
        self.acks = 0
        self.sends = 0
        self.accepted = False
        self.deferred = False
        self.refusals = 0
        self.reason = reason
        self.from_mode = from_mode


class BridgeCore:
    """Time-driven bridge logic. All methods take the receive/now time ``t_s``.

    Inputs: :meth:`on_heartbeat`, :meth:`on_command_ack`, :meth:`on_param_value`,
    :meth:`on_extended_sys_state`, :meth:`on_message`, :meth:`on_attitude_target`,
    :meth:`on_statustext`, :meth:`on_attitude_command`, :meth:`on_thrust_command`,
    :meth:`on_enabled`, :meth:`request_arm`, :meth:`request_offboard`.
    Outputs: :meth:`on_thrust_command` returns the :class:`AttitudeSetpoint` to send (or None);
    :meth:`step` returns the :class:`Outgoing` messages due now; :meth:`stream_diagnostics`
    the setpoint rate and gaps.
    """

    def __init__(self, params: BridgeParams | None = None) -> None:
        self.params = params or BridgeParams()
        self.rejected: dict[str, int] = {'nan': 0, 'out_of_order': 0, 'bad_quaternion': 0,
                                         'other_system': 0, 'bad_data': 0}
        self.counters: dict[str, int] = {'setpoints_sent': 0, 'rate_limited': 0,
                                         'stale_attitude': 0, 'disabled': 0, 'no_link': 0,
                                         'not_guided_nogps': 0,
                                         'heartbeats_rx': 0, 'commands_sent': 0,
                                         'link_degraded': 0, 'trim_requests': 0,
                                         'disarm_deferred': 0, 'disarm_refused': 0,
                                         'interval_refused': 0, 'imu_fallback': 0,
                                         'param_requests': 0, 'stop_actions': 0,
                                         'statustext_rx': 0, 'statustext_repeats': 0}
        self.link_monitor = LinkMonitor(self.params.link_monitor)
        self.setpoint_stats = SetpointStats()
        self.hover = HoverThrustEstimator(window_s=self.params.hover_window_s)
        self.reset()

    def reset(self) -> None:
        """Forget the link, the inputs and any pending request (counters are kept)."""
        # link
        self.target_system: int | None = None
        self.target_component: int = self.params.target_component
        self._last_hb_s = -math.inf
        self._link_was_up = False
        self.custom_mode = 0
        self.base_mode = 0
        self.mode = 'UNKNOWN'
        self.armed = False
        self.landed: bool | None = None
        self.autopilot_params: dict[str, float] = {}
        self._reset_connection()
        #: the autopilot's last STATUSTEXT messages, (t_s, severity, text), newest last
        self.statustexts: deque[tuple[float, int, str]] = deque(maxlen=8)
        self._statustext_seen: dict[str, float] = {}
        self._statustext_parts: dict[int, list[str]] = {}
        # inputs
        self._thrust_stamp = -math.inf
        self._att_stamp = -math.inf
        self._att_rx_s = -math.inf
        self._att_q_ned = (1.0, 0.0, 0.0, 0.0)
        self._att_euler = (0.0, 0.0, 0.0)
        self.enabled = True
        # stream (the calibration in use: chosen at each OFFBOARD request, see hover_source)
        self._limiter = StreamLimiter(self.params.max_stream_rate_hz, self.params.stream_burst,
                                      self.params.fresh_period_s)
        self._last_sent_s = -math.inf
        self._stream_start_s = math.inf
        self.thrust: ThrustCalibration = self.params.thrust
        self.hover_source = 'parameter'
        self.hover.reset()
        # periodic
        self._last_hb_tx_s = -math.inf
        self._last_interval_s = -math.inf
        self._last_param_req_s = -math.inf
        self._seen_ids: set[int] = set()
        self._trimmed: dict[int, int] = {}      # message id → trim requests sent
        self._last_trim_s = -math.inf
        self._offboard: _Request | None = None
        self._arm: _Request | None = None
        #: ArduPilot: the stop action's mode request (LAND / LOITER), retried until it shows
        self._stop: _Request | None = None
        self.last_result = ''
        self.link_monitor.reset()

    def _reset_connection(self) -> None:
        """Per-connection knowledge: what the autopilot refused and which parameters were
        asked (a reconnection may be a rebooted or another autopilot)."""
        p = self.params
        #: the IMU message the bridge streams: HIGHRES_IMU, or SCALED_IMU when that is
        #: configured (use_highres_imu False) or the autopilot refused HIGHRES_IMU
        self.imu_msg = 'HIGHRES_IMU' if p.use_highres_imu else 'SCALED_IMU'
        self._refused_ids: set[int] = set()
        self._interval_fifo: deque[tuple[float, int]] = deque()
        self._imu_request_due = False
        self._param_requests: dict[str, int] = {}

    # --- link ----------------------------------------------------------------------------

    def link_up(self, t_s: float) -> bool:
        """True while the autopilot HEARTBEAT is younger than ``link_timeout_s``."""
        return t_s - self._last_hb_s <= self.params.link_timeout_s

    def on_heartbeat(self, t_s: float, system_id: int, component_id: int, mav_type: int,
                     autopilot: int, base_mode: int, custom_mode: int) -> bool:
        """An incoming HEARTBEAT; returns True when it came from the autopilot we follow."""
        if autopilot == MAV_AUTOPILOT_INVALID or mav_type in (MAV_TYPE_GCS,
                                                              MAV_TYPE_ONBOARD_CONTROLLER):
            return False  # a GCS or another companion, not the flight controller
        if self.target_system is None:
            self.target_system = system_id
            self.target_component = component_id
        elif system_id != self.target_system or component_id != self.target_component:
            self.rejected['other_system'] += 1
            return False
        if not math.isfinite(t_s) or t_s < self._last_hb_s:
            self.rejected['out_of_order' if math.isfinite(t_s) else 'nan'] += 1
            return False
        if not self.link_up(t_s):
            # (re)connected, perhaps to a rebooted autopilot: ask for telemetry again, read
            # its parameters afresh, trim its streams again
            self._last_interval_s = -math.inf
            self._last_param_req_s = -math.inf
            self.autopilot_params = {}
            self._seen_ids = set()
            self._trimmed = {}
            self._reset_connection()
            self.hover.reset()
        self._last_hb_s = t_s
        self.counters['heartbeats_rx'] += 1
        self.base_mode = base_mode
        self.custom_mode = custom_mode
        was_armed = self.armed
        self.armed = bool(base_mode & MAV_MODE_FLAG_SAFETY_ARMED)
        self.mode = mode_name(self.params.autopilot, custom_mode)
        if was_armed and not self.armed and self.params.autopilot == 'ardupilot':
            # ArduPilot saves its learned MOT_THST_HOVER (MOT_HOVER_LEARN = 2) at disarm:
            # read it afresh for the next flight
            self.autopilot_params.pop('MOT_THST_HOVER', None)
            self._param_requests.pop('MOT_THST_HOVER', None)
            self._last_param_req_s = -math.inf
        return True

    def on_command_ack(self, t_s: float, command: int, result: int) -> None:
        """COMMAND_ACK, as PX4 v1.16 and ArduCopter 4.5 send them.

        DO_SET_MODE is answered twice by PX4: first the MAVLink receiver's ACCEPTED (the
        command was forwarded), then the commander's verdict; the first ACK after a send is
        therefore not a verdict on PX4 (on ArduPilot it is). An accepting verdict ends the
        re-sends (the HEARTBEAT, 1 Hz on PX4, confirms); TEMPORARILY_REJECTED is retried; a
        final refusal (DENIED, FAILED, UNSUPPORTED, …) cancels the request. A disarm refused
        as TEMPORARILY_REJECTED (PX4 in the air) is deferred until the land detector says
        landed instead of being repeated (each refusal is a critical message on every GCS);
        ArduPilot answers a disarm FAILED until its land detector confirms the landing: it is
        retried (:meth:`_step_arm`). SET_MESSAGE_INTERVAL answers are matched to the requests
        in the order they were sent (:meth:`_on_interval_ack`).
        """
        if command == MAV_CMD_SET_MESSAGE_INTERVAL:
            self._on_interval_ack(t_s, result)
        elif command == MAV_CMD_DO_SET_MODE and self._stop is not None:
            req = self._stop
            if result == MAV_RESULT_ACCEPTED:
                req.accepted = True
            elif result not in (MAV_RESULT_IN_PROGRESS, MAV_RESULT_TEMPORARILY_REJECTED):
                req.refusals += 1
                if req.value != 'LAND':
                    # LOITER needs a position estimate: LAND instead
                    self._stop = _Request(t_s, 'LAND', f'{req.reason}; {req.value} refused '
                                          f'(MAV_RESULT {result})', req.from_mode)
                    self.last_result = f'stop: {self._stop.reason}, commanding LAND'
        elif command == MAV_CMD_DO_SET_MODE and self._offboard is not None:
            req = self._offboard
            req.acks += 1
            if result == MAV_RESULT_IN_PROGRESS:
                return
            if self.params.autopilot == 'px4' and req.acks == 1 and \
                    result == MAV_RESULT_ACCEPTED:
                return  # PX4's MAVLink receiver: forwarded, not yet decided
            if result == MAV_RESULT_ACCEPTED:
                req.accepted = True
            elif result != MAV_RESULT_TEMPORARILY_REJECTED:
                self._offboard = None
                self.last_result = f'{self.params.offboard_mode} refused (MAV_RESULT {result})'
        elif command == MAV_CMD_COMPONENT_ARM_DISARM and self._arm is not None:
            req = self._arm
            if result in (MAV_RESULT_ACCEPTED, MAV_RESULT_IN_PROGRESS):
                req.accepted = result == MAV_RESULT_ACCEPTED
                return
            if not req.value and self.params.autopilot == 'ardupilot':
                # ArduCopter refuses a disarm (FAILED) until its land detector says landed
                # (in the air, or for the seconds after a touchdown): retried, not cancelled
                req.refusals += 1
                self.counters['disarm_refused'] += 1
                self.last_result = (f'disarm refused (MAV_RESULT {result}): ArduPilot has not '
                                    'confirmed the landing; retried every '
                                    f'{self.params.disarm_retry_s:g} s for '
                                    f'{self.params.disarm_timeout_s:g} s')
                return
            if result == MAV_RESULT_TEMPORARILY_REJECTED:
                if not req.value:
                    if not req.deferred:
                        self.counters['disarm_deferred'] += 1
                    req.deferred = True
                    self.last_result = ('disarm deferred: the autopilot is in the air '
                                        '(TEMPORARILY_REJECTED); re-sent once it says landed')
                return
            what = 'arm' if req.value else 'disarm'
            self._arm = None
            self.last_result = f'{what} refused (MAV_RESULT {result})'

    def _on_interval_ack(self, t_s: float, result: int) -> None:
        """The answer to the oldest SET_MESSAGE_INTERVAL still waiting for one (autopilots
        answer them in order; one whose ACK was lost is forgotten after 2 s). A refused stream
        is not asked for again on this connection; a refused HIGHRES_IMU — ArduCopter has no
        such message (DENIED, each request a "No ap_message for mavlink id (105)" broadcast to
        every link) — switches the IMU to SCALED_IMU, requested at once."""
        fifo = self._interval_fifo
        while fifo and t_s - fifo[0][0] > _INTERVAL_ACK_TIMEOUT_S:
            fifo.popleft()
        if not fifo:
            return
        _, msg_id = fifo.popleft()
        if result not in (MAV_RESULT_DENIED, MAV_RESULT_UNSUPPORTED, MAV_RESULT_FAILED):
            return
        if msg_id not in self._refused_ids:
            self._refused_ids.add(msg_id)
            self.counters['interval_refused'] += 1
        if msg_id == MSG_ID['HIGHRES_IMU'] and self.imu_msg == 'HIGHRES_IMU':
            self.imu_msg = 'SCALED_IMU'
            self._imu_request_due = True
            self.counters['imu_fallback'] += 1
            self.last_result = (f'HIGHRES_IMU refused (MAV_RESULT {result}): vehicle/imu from '
                                'SCALED_IMU')

    def on_param_value(self, name: str, value: float,
                       param_type: int = MAV_PARAM_TYPE_REAL32) -> None:
        """PARAM_VALUE: PX4's :data:`PX4_PARAMS`, ArduPilot's :data:`ARDUPILOT_PARAMS`. PX4
        sends integer parameters bytewise, ArduPilot as floats
        (:func:`~mavlink_bridge.conversions.param_value_from_wire`)."""
        if not isinstance(name, str):
            return
        v = param_value_from_wire(value, param_type, self.params.autopilot == 'px4')
        if math.isfinite(v):
            self.autopilot_params[name] = v

    def on_extended_sys_state(self, landed_state: int) -> None:
        """EXTENDED_SYS_STATE.landed_state → :attr:`landed` (None when undefined)."""
        self.landed = landed_from_extended_sys_state(landed_state)

    def on_message(self, msg_id: int) -> None:
        """Any message from the autopilot (its message id): the streams it sends, for
        :attr:`BridgeParams.trim_telemetry`."""
        self._seen_ids.add(msg_id)

    def on_attitude_target(self, t_s: float, thrust_norm: float, cos_tilt: float,
                           vz_mps: float) -> None:
        """ATTITUDE_TARGET.thrust with the current tilt (cos φ cos θ) and vertical speed: a
        hover-thrust sample while the autopilot flies by itself (armed, in the air, not in
        OFFBOARD / GUIDED_NOGPS, where it echoes our setpoints, the bridge not streaming and
        no request pending). PX4 and ArduPilot report their own collective there (ArduCopter
        in GUIDED after its take-off: 0.345 on the SITL quad, measured)."""
        if not (self.armed and self.landed is False and self.mode != self.params.offboard_mode
                and self._offboard is None and not self.streaming(t_s)):
            return
        self.hover.on_sample(t_s, thrust_norm, cos_tilt, vz_mps)

    def on_statustext(self, t_s: float, severity: int, text: str, text_id: int = 0,
                      chunk_seq: int = 0) -> str | None:
        """STATUSTEXT (ArduPilot's and PX4's reasons: "No such mode 13", "GCS Failsafe"…).

        Returns the complete text to log, or None: a MAVLink 2 text longer than 50 characters
        arrives in chunks with the same ``text_id`` (the last one shorter than 50), and the
        same text again within ``statustext_repeat_s`` is kept but not logged again (a
        repeated refusal must not flood the log). Every complete text is kept in
        :attr:`statustexts`."""
        if not isinstance(text, str) or not math.isfinite(t_s):
            self.rejected['bad_data'] += 1
            return None
        part = text.split('\x00', 1)[0]
        if text_id:
            parts = self._statustext_parts.setdefault(int(text_id), [])
            if chunk_seq != len(parts):
                parts.clear()           # a chunk was lost: start again from this one
            parts.append(part)
            if len(part) >= 50 and len(parts) < 6:
                return None             # more to come
            part = ''.join(parts)
            del self._statustext_parts[int(text_id)]
            if len(self._statustext_parts) > 8:
                self._statustext_parts.clear()
        self.counters['statustext_rx'] += 1
        self.statustexts.append((t_s, int(severity), part))
        last = self._statustext_seen.get(part)
        self._statustext_seen[part] = t_s
        if len(self._statustext_seen) > 64:
            self._statustext_seen = {k: v for k, v in self._statustext_seen.items()
                                     if t_s - v <= self.params.statustext_repeat_s}
        if last is not None and 0.0 <= t_s - last < self.params.statustext_repeat_s:
            self.counters['statustext_repeats'] += 1
            return None
        return part

    def count_bad_data(self, n: int = 1) -> None:
        """Garbage or truncated bytes seen by the transport."""
        self.rejected['bad_data'] += n

    # --- commands from ROS ---------------------------------------------------------------

    def on_enabled(self, t_s: float, enabled: bool) -> None:
        """``control/enabled``: False (landed) stops streaming and requests a disarm. On
        ArduPilot the bridge also commands LAND: ArduCopter refuses the disarm until its land
        detector confirms the landing, which it does in LAND (~1.5 s after touchdown,
        measured) but never in GUIDED_NOGPS on thrust (20 s of FAILED, measured); LAND then
        disarms by itself, the disarm request is retried meanwhile. Only while ArduCopter flies
        our setpoints (GUIDED_NOGPS): in its own modes it is the operator's."""
        if self.enabled and not enabled:
            self._offboard = None
            ardupilot = self.params.autopilot == 'ardupilot'
            if self.armed and ardupilot and not self.in_offboard():
                pass   # ArduCopter flies its own mode (an operator's GUIDED take-off, whose
                #        lift-off flickers the landed state): not ours to land or disarm
            elif self.armed:
                self._arm = _Request(t_s, False)
                if ardupilot and self.mode != 'LAND':
                    self._start_stop(t_s, 'LAND', 'control/enabled False (landed)')
        self.enabled = bool(enabled)

    def on_attitude_command(self, t_s: float, stamp_s: float,
                            q_enu_flu: tuple[float, float, float, float]) -> bool:
        """``control/attitude`` (FLU in ENU, (w, x, y, z)); returns False when rejected."""
        if not (math.isfinite(t_s) and math.isfinite(stamp_s)):
            self.rejected['nan'] += 1
            return False
        qn = quat_normalize(q_enu_flu)
        if qn is None:
            self.rejected['nan' if not all(map(math.isfinite, q_enu_flu))
                          else 'bad_quaternion'] += 1
            return False
        if not self._take_attitude_stamp(t_s, stamp_s):
            return False
        self._att_q_ned = quat_enu_flu_to_ned_frd(qn)
        self._att_euler = quaternion_to_euler(*qn)
        return True

    def _take_attitude_stamp(self, t_s: float, stamp_s: float) -> bool:
        """An attitude command stamped ``stamp_s`` is newer than the last (else counted
        ``out_of_order``, False); it becomes the last, received at ``t_s``."""
        if stamp_s < self._att_stamp:
            self.rejected['out_of_order'] += 1
            return False
        self._att_stamp = stamp_s
        self._att_rx_s = t_s
        return True

    def on_attitude_euler(self, t_s: float, stamp_s: float, roll_rad: float, pitch_rad: float,
                          yaw_rad: float) -> bool:
        """Same as :meth:`on_attitude_command` from ENU/FLU Z-Y-X Euler angles."""
        if not all(map(math.isfinite, (t_s, stamp_s, roll_rad, pitch_rad, yaw_rad))):
            self.rejected['nan'] += 1
            return False
        if not self._take_attitude_stamp(t_s, stamp_s):
            return False
        self._att_q_ned = euler_enu_to_quat_ned(roll_rad, pitch_rad, yaw_rad)
        self._att_euler = (roll_rad, pitch_rad, yaw_rad)
        return True

    def on_thrust_command(self, t_s: float, stamp_s: float,
                          thrust_n: float) -> AttitudeSetpoint | None:
        """``control/thrust`` (u_z of (16), N). Returns the setpoint to send now, or None.

        None when: the input is bad, the bridge is disabled, the link is down, the attitude
        command is older than ``input_timeout_s``, or the stream limiter refuses it
        (:class:`StreamLimiter`: only when commands arrive faster than ``max_stream_rate_hz``
        for longer than ``stream_burst`` commands *and* carry data less than
        ``fresh_period_s`` newer than the last one sent). The thrust is normalised with
        :attr:`thrust` (the calibration chosen at the last OFFBOARD request).
        """
        if not (math.isfinite(t_s) and math.isfinite(stamp_s) and math.isfinite(thrust_n)):
            self.rejected['nan'] += 1
            return None
        if stamp_s < self._thrust_stamp:
            self.rejected['out_of_order'] += 1
            return None
        self._thrust_stamp = stamp_s
        p = self.params
        if not self.enabled:
            self.counters['disabled'] += 1
            return None
        if not self.link_up(t_s):
            self.counters['no_link'] += 1
            return None
        if p.autopilot == 'ardupilot' and self.mode != p.offboard_mode and \
                self._offboard is None:
            # ArduCopter's GUIDED (and its other modes that take attitude targets) would fly
            # a SET_ATTITUDE_TARGET as an angle command, overriding its own position control
            # (an operator's take-off): only GUIDED_NOGPS, or its entry sequence, is ours
            self.counters['not_guided_nogps'] += 1
            return None
        if self.link_monitor.degraded:
            # the link is too slow to close the loops over: stop streaming, so that the
            # autopilot's offboard-loss failsafe takes over (LinkMonitor)
            self.counters['link_degraded'] += 1
            return None
        if t_s - self._att_rx_s > p.input_timeout_s:
            self.counters['stale_attitude'] += 1
            return None
        if not self._limiter.allow(t_s, stamp_s):
            self.counters['rate_limited'] += 1
            return None
        if t_s - self._last_sent_s > p.max_stream_gap_s:
            self._stream_start_s = t_s  # a new continuous stream starts here
        self._last_sent_s = t_s
        self.counters['setpoints_sent'] += 1
        self.setpoint_stats.on_sent(t_s)
        norm = self.thrust.to_norm(thrust_n)
        r, pt, y = self._att_euler
        return AttitudeSetpoint(t_s, self._att_q_ned, norm, thrust_n, r, pt, y)

    def on_timesync(self, t_s: float, tc1_ns: int, ts1_ns: int) -> bool:
        """A TIMESYNC from the autopilot received at ``t_s``. A reply (``tc1 != 0``) echoes
        our request's ``ts1`` (ns of our ``t_s``) and gives the round trip to
        :attr:`link_monitor`; requests from the autopilot (``tc1 == 0``) are not measured.
        Returns True when a round-trip sample was accepted. Logs the degradation once."""
        if not (isinstance(tc1_ns, int) and isinstance(ts1_ns, int)) or tc1_ns == 0:
            return False
        was = self.link_monitor.degraded
        ok = self.link_monitor.on_timesync(ts1_ns * 1e-9, t_s)
        if self.link_monitor.degraded and not was:
            self.last_result = self.link_monitor.reason
        return ok

    def streaming(self, t_s: float) -> bool:
        """True while setpoints flow (the last one is younger than ``max_stream_gap_s``)."""
        return t_s - self._last_sent_s <= self.params.max_stream_gap_s

    def stream_age_s(self, t_s: float) -> float:
        """How long the current continuous stream has lasted, up to its last setpoint (0 when
        not streaming)."""
        return self._last_sent_s - self._stream_start_s if self.streaming(t_s) else 0.0

    def in_offboard(self) -> bool:
        """The autopilot flies our setpoints: its mode is OFFBOARD / GUIDED_NOGPS *and* it is
        armed (PX4 reports OFFBOARD while disarmed after a failsafe landing)."""
        return self.armed and self.mode == self.params.offboard_mode

    def stream_diagnostics(self, t_s: float) -> tuple[float, float, str]:
        """``(rate_hz, max_gap_s, warning)`` of our own setpoints since the previous call
        (one diagnostics period). ``warning`` is set while the autopilot flies our setpoints
        and a gap exceeded half of PX4's ``COM_OF_LOSS_T`` (1 s assumed when unknown): one
        more such stall and PX4 takes its offboard-loss action."""
        rate, gap = self.setpoint_stats.window(t_s)
        if self.params.autopilot == 'px4':
            name, limit = 'COM_OF_LOSS_T', self.autopilot_params.get('COM_OF_LOSS_T', 1.0)
        else:
            name, limit = 'stop_after_s', self.params.stop_after_s
        warn = ''
        if self.in_offboard() and gap > 0.5 * limit:
            warn = (f'setpoint gap {gap * 1e3:.0f} ms > half of {name} '
                    f'({limit:.2f} s): close to the offboard-loss action')
        return rate, gap, warn

    # --- services ------------------------------------------------------------------------

    def request_arm(self, t_s: float, arm: bool) -> tuple[bool, str]:
        """``bridge/arm`` (SetBool). Returns (accepted, message); sending happens in step()."""
        if not self.link_up(t_s):
            return False, 'no autopilot heartbeat'
        if arm and not self.enabled:
            return False, 'control/enabled is False'
        if self.armed == bool(arm):
            return True, 'already ' + ('armed' if arm else 'disarmed')
        self._arm = _Request(t_s, bool(arm))
        return True, ('arm' if arm else 'disarm') + ' requested'

    def request_offboard(self, t_s: float) -> tuple[bool, str]:
        """``bridge/offboard`` (Trigger): request OFFBOARD / GUIDED_NOGPS while setpoints
        stream. Refused, with the reason, while the autopilot's configuration is unknown or
        unsafe (:meth:`px4_config_problem`, :meth:`ardupilot_config_problem`). Returns
        (accepted, message)."""
        p = self.params
        if not self.link_up(t_s):
            return False, 'no autopilot heartbeat'
        if not self.enabled:
            return False, 'control/enabled is False'
        problem = self.ardupilot_config_problem() or self.px4_config_problem()
        if problem:
            return False, problem
        if self.link_monitor.degraded:
            # the operator's explicit way back after a latency stop: measure afresh (a link
            # that is still slow degrades again after window + confirm_s)
            self.link_monitor.reset()
        self.thrust, self.hover_source = self._calibration()
        if self._stop is not None:
            self._stop = None       # the operator takes the vehicle back from the stop
        if self.in_offboard():
            return True, f'already in {p.offboard_mode}'
        self._offboard = _Request(t_s, p.offboard_mode)
        note = f'; hover thrust {self.thrust.hover_thrust_norm:.3f} ({self.hover_source})'
        if p.autopilot == 'ardupilot':
            note += f'; {self.ardupilot_link_loss()}'
        return True, (f'{p.offboard_mode} requested; sent once setpoints have streamed for '
                      f'{p.offboard_warmup_s:.1f} s{note}')

    def _calibration(self) -> tuple[ThrustCalibration, str]:
        """The thrust calibration for the next OFFBOARD / GUIDED_NOGPS and where its hover
        thrust comes from: the autopilot's measured hover (:attr:`hover`), else its hover
        parameter (PX4 ``MPC_THR_HOVER``, ArduPilot ``MOT_THST_HOVER``), else the configured
        one (``hover_thrust_source = 'parameter'``). Both autopilots linearise their
        normalised thrust (``THR_MDL_FAC``, ``MOT_THST_EXPO``), so the curve stays the
        configured residual ``expo`` (0 = linear); ArduPilot's ``MOT_THST_EXPO`` is reported,
        never applied a second time."""
        cal = self.params.thrust
        if self.params.hover_thrust_source != 'autopilot':
            return cal, 'parameter'
        name = 'MPC_THR_HOVER' if self.params.autopilot == 'px4' else 'MOT_THST_HOVER'
        h, src = self.hover.estimate, "measured in the autopilot's hover"
        if math.isnan(h):
            h, src = self.autopilot_params.get(name, math.nan), name
        if not cal.norm_min < h < cal.norm_max:
            return cal, 'parameter'
        return replace(cal, hover_thrust_norm=h), src

    def px4_config_problem(self) -> str:
        """Why PX4 must not be put in OFFBOARD now ('' when fine; always '' on ArduPilot).

        Fail closed: an unknown value is a problem. ``COM_OBL_RC_ACT`` must be one of
        ``offboard_loss_actions`` (default Land or Hold: PX4's default 0 = Position makes an
        emergency descent without RC while the heartbeat reads POSCTL, measured on v1.16);
        ``COM_OF_LOSS_T`` must be at most ``max_offboard_loss_timeout_s`` (PX4 flies the last
        setpoint that long); the hover thrust must be known when it comes from PX4."""
        p = self.params
        if p.autopilot != 'px4':
            return ''
        ap = self.autopilot_params
        act = ap.get('COM_OBL_RC_ACT')
        if act is None:
            return 'COM_OBL_RC_ACT not read yet: the offboard-loss action is unknown'
        name = PX4_OFFBOARD_LOSS_ACTIONS.get(int(act), f'unknown ({int(act)})')
        if name not in p.offboard_loss_actions:
            return (f'COM_OBL_RC_ACT = {int(act)} ({name}): when the setpoints stop PX4 would '
                    f'not {" or ".join(p.offboard_loss_actions)}; set COM_OBL_RC_ACT = 4 '
                    '(Land) or 5 (Hold)')
        lt = ap.get('COM_OF_LOSS_T')
        if lt is None:
            return 'COM_OF_LOSS_T not read yet: the offboard-loss timeout is unknown'
        if not 0.0 < lt <= p.max_offboard_loss_timeout_s:
            return (f'COM_OF_LOSS_T = {lt:g} s not in (0, {p.max_offboard_loss_timeout_s:g}] s: '
                    'PX4 would fly a stale setpoint that long after the companion stops')
        if p.hover_thrust_source == 'autopilot' and not self.hover.valid and \
                'MPC_THR_HOVER' not in ap:
            return 'MPC_THR_HOVER not read yet: the hover thrust is unknown'
        return ''

    def ardupilot_config_problem(self) -> str:
        """Why ArduPilot must not be put in GUIDED_NOGPS now ('' when fine; always '' on PX4).

        Fail closed: an unknown value is a problem (issue 17: a request made before the
        PARAM_VALUE arrived engaged GUIDED_NOGPS with ``GUID_OPTIONS`` = 0). ``GUID_OPTIONS``
        needs bit 3 (otherwise the thrust is read as a climb rate, 0.5 = hold);
        ``ATC_ANGLE_BOOST`` must be 0 (ArduCopter 4.5's name, default 1: it would divide our
        body-axis thrust by cos(tilt) again); ``GUID_TIMEOUT`` at most
        ``max_offboard_loss_timeout_s`` (ArduPilot flies the last setpoint that long when the
        bridge cannot speak); the hover thrust must be known when it comes from ArduPilot."""
        p = self.params
        if p.autopilot != 'ardupilot':
            return ''
        ap = self.autopilot_params

        def unknown(name: str, what: str) -> str:
            n = self._param_requests.get(name, 0)
            tail = (f' (not answered after {n} requests)' if n >= p.param_max_requests else '')
            return f'{name} not read yet{tail}: {what} is unknown'

        opts = ap.get('GUID_OPTIONS')
        if opts is None:
            return unknown('GUID_OPTIONS', 'whether ArduPilot reads the thrust as thrust')
        if not int(opts) & GUID_OPTIONS_THRUST_BIT:
            return (f'GUID_OPTIONS = {int(opts)}: bit 3 (8) is not set, ArduPilot would read '
                    'the thrust as a climb rate; set GUID_OPTIONS = 8')
        boost = ap.get('ATC_ANGLE_BOOST')
        if boost is None:
            return unknown('ATC_ANGLE_BOOST', 'the tilt compensation')
        if boost != 0.0:
            return (f'ATC_ANGLE_BOOST = {boost:g}: ArduPilot would divide the body-axis thrust '
                    'by cos(tilt) again; set ATC_ANGLE_BOOST = 0')
        lt = ap.get('GUID_TIMEOUT')
        if lt is None:
            return unknown('GUID_TIMEOUT', 'how long ArduPilot flies a stale setpoint')
        if not 0.0 < lt <= p.max_offboard_loss_timeout_s:
            return (f'GUID_TIMEOUT = {lt:g} s not in (0, {p.max_offboard_loss_timeout_s:g}] s: '
                    'ArduPilot would fly a stale setpoint that long when the bridge cannot '
                    'speak; set GUID_TIMEOUT <= '
                    f'{p.max_offboard_loss_timeout_s:g}')
        if p.hover_thrust_source == 'autopilot' and not self.hover.valid and \
                'MOT_THST_HOVER' not in ap:
            return unknown('MOT_THST_HOVER', 'the hover thrust')
        return ''

    def ardupilot_link_loss(self) -> str:
        """What ArduPilot does when this link goes silent (the bridge cannot command its stop
        action then): its GCS failsafe lands when ``FS_GCS_ENABLE`` = 5 and ``SYSID_MYGCS`` is
        this companion's system id (measured: LAND 4.8 s after the last heartbeat, disarmed
        15.6 s after, from 2 m); otherwise GUIDED_NOGPS levels after ``GUID_TIMEOUT`` and holds
        altitude indefinitely."""
        ap = self.autopilot_params
        fs, gcs = ap.get('FS_GCS_ENABLE'), ap.get('SYSID_MYGCS')
        if fs is None or gcs is None:
            return 'link-loss action unknown (FS_GCS_ENABLE / SYSID_MYGCS not read)'
        if int(fs) == 5 and self.target_system is not None and int(gcs) == self.params.system_id:
            return 'on link loss ArduPilot lands (GCS failsafe on this companion)'
        return (f'on link loss ArduPilot hovers in GUIDED_NOGPS (FS_GCS_ENABLE = {int(fs)}, '
                f'SYSID_MYGCS = {int(gcs)}): set FS_GCS_ENABLE = 5 and SYSID_MYGCS = '
                f'{self.params.system_id} to land')

    def pending(self) -> dict[str, object]:
        """Pending requests, for diagnostics."""
        return {'offboard': self._offboard is not None,
                'arm': None if self._arm is None else self._arm.value,
                'stop': None if self._stop is None else self._stop.value}

    # --- periodic ------------------------------------------------------------------------

    def step(self, t_s: float) -> list[Outgoing]:
        """What to send now: heartbeat (1 Hz), message intervals and stream trims, parameter
        reads, retries of arm/mode, ArduPilot's stop action."""
        p = self.params
        out: list[Outgoing] = []
        if not math.isfinite(t_s):
            self.rejected['nan'] += 1
            return out
        if t_s - self._last_hb_tx_s >= p.heartbeat_period_s:
            self._last_hb_tx_s = t_s
            out.append(_HEARTBEAT)
        up = self.link_up(t_s)
        if not up:
            if self._link_was_up:
                self.last_result = 'link lost'
            self._link_was_up = False
            self._offboard = None
            self._arm = None
            self._stop = None
            return out
        self._link_was_up = True
        if self.link_monitor.poll(t_s):
            out.append(Outgoing('timesync', params=(t_s,)))
        if t_s - self._last_interval_s >= p.interval_refresh_s:
            self._last_interval_s = t_s
            self._imu_request_due = False
            out.extend(self._interval_requests(t_s))
        elif self._imu_request_due:
            self._imu_request_due = False
            out.extend(self._interval_requests(t_s, only=(self.imu_msg,)))
        if p.trim_telemetry and t_s - self._last_trim_s >= 1.0:
            self._last_trim_s = t_s
            out.extend(self._trim_requests(t_s))
        if t_s - self._last_param_req_s >= p.param_retry_s:
            wanted = PX4_PARAMS if p.autopilot == 'px4' else ARDUPILOT_PARAMS
            missing = [n for n in wanted if n not in self.autopilot_params
                       and self._param_requests.get(n, 0) < p.param_max_requests]
            if missing:
                self._last_param_req_s = t_s
                for n in missing:
                    self._param_requests[n] = self._param_requests.get(n, 0) + 1
                self.counters['param_requests'] += len(missing)
                out.extend(Outgoing('param_request', param_id=n) for n in missing)
        self._step_stop(t_s, out)
        self._step_offboard(t_s, out)
        self._step_arm(t_s, out)
        self.counters['commands_sent'] += sum(1 for o in out if o.kind == 'command')
        return out

    def _interval_request(self, t_s: float, msg_id: int, interval_us: float,
                          note: str) -> Outgoing:
        """A SET_MESSAGE_INTERVAL, remembered until its ACK (:meth:`_on_interval_ack`)."""
        self._interval_fifo.append((t_s, msg_id))
        if len(self._interval_fifo) > 256:
            self._interval_fifo.popleft()
        return Outgoing('command', MAV_CMD_SET_MESSAGE_INTERVAL,
                        (float(msg_id), interval_us, 0.0, 0.0, 0.0, 0.0, 0.0), note=note)

    def _interval_requests(self, t_s: float,
                           only: tuple[str, ...] | None = None) -> list[Outgoing]:
        """SET_MESSAGE_INTERVAL for the telemetry used (``only`` these names), except the
        streams this autopilot refused on this connection. Not HEARTBEAT: PX4 refuses it by
        design (FAILED, v1.16) and sends it at 1 Hz anyway."""
        p = self.params
        rates = [('ATTITUDE', p.attitude_rate_hz),
                 ('LOCAL_POSITION_NED', p.local_position_rate_hz),
                 ('DISTANCE_SENSOR', p.distance_sensor_rate_hz),
                 (self.imu_msg, p.imu_rate_hz),
                 ('EXTENDED_SYS_STATE', p.extended_sys_state_rate_hz)]
        if p.hover_thrust_source == 'autopilot':
            rates.append(('ATTITUDE_TARGET', p.attitude_target_rate_hz))
        return [self._interval_request(t_s, MSG_ID[name], float(round(1e6 / hz)), name)
                for name, hz in rates
                if MSG_ID[name] not in self._refused_ids and (only is None or name in only)]

    def used_msg_ids(self) -> frozenset[int]:
        """Message ids the bridge reads (never trimmed), protocol messages included."""
        p = self.params
        used = {MSG_ID['ATTITUDE'], MSG_ID['LOCAL_POSITION_NED'], MSG_ID['DISTANCE_SENSOR'],
                MSG_ID[self.imu_msg], MSG_ID['EXTENDED_SYS_STATE']}
        if p.hover_thrust_source == 'autopilot':
            used.add(MSG_ID['ATTITUDE_TARGET'])
        return KEEP_MSG_IDS | used

    def _trim_requests(self, t_s: float) -> list[Outgoing]:
        """SET_MESSAGE_INTERVAL(id, −1) — "stop sending" — for every message the autopilot
        sends us that the bridge does not read (PX4's onboard link streams ~33 types by
        default). Each id is asked at most 3 times per connection, 1 s apart, and only while
        it keeps arriving (a refused or non-stream id is not insisted on)."""
        used = self.used_msg_ids()
        out = []
        for mid in sorted(self._seen_ids - used):
            n = self._trimmed.get(mid, 0)
            if n >= 3 or mid in self._refused_ids:
                continue
            self._trimmed[mid] = n + 1
            self.counters['trim_requests'] += 1
            out.append(self._interval_request(t_s, mid, -1.0, f'trim {mid}'))
        self._seen_ids = set()
        return out

    def _start_stop(self, t_s: float, mode: str, reason: str) -> None:
        """ArduPilot: command ``mode`` (LAND / LOITER) now, retried until the HEARTBEAT shows
        it; any OFFBOARD request is dropped."""
        self._offboard = None
        self._stop = _Request(t_s, mode, reason, self.mode)
        self.counters['stop_actions'] += 1
        self.last_result = f'stop: {reason}, commanding {mode}'

    def _step_stop(self, t_s: float, out: list[Outgoing]) -> None:
        """ArduPilot's stop action. GUIDED_NOGPS without setpoints flies the last one for
        ``GUID_TIMEOUT``, then levels and holds altitude forever (measured on 4.5.6): when the
        bridge stops streaming while ArduPilot flies its setpoints (inputs stale, link latency
        too high) it commands ``ardupilot_stop_action`` after ``stop_after_s`` itself."""
        p = self.params
        if p.autopilot != 'ardupilot':
            return
        req = self._stop
        if req is None:
            mode = ARDUPILOT_STOP_MODES[p.ardupilot_stop_action]
            if mode and self.in_offboard() and self._last_sent_s > -math.inf and \
                    t_s - self._last_sent_s > p.stop_after_s:
                why = ('link latency too high' if self.link_monitor.degraded else
                       'control/enabled False' if not self.enabled else
                       'control inputs stale')
                self._start_stop(t_s, mode, f'setpoints stopped {t_s - self._last_sent_s:.2f} s '
                                 f'ago ({why})')
                req = self._stop
            else:
                return
        assert req is not None
        if self.mode == req.value or not self.armed:
            self._stop = None
            self.last_result = (f'{req.value} active ({req.reason})' if self.armed else
                                f'disarmed ({req.reason})')
            return
        if self.mode != req.from_mode:
            self._stop = None       # someone else (an operator, a failsafe) changed the mode
            self.last_result = f'stop {req.value} not sent again: the mode is now {self.mode}'
            return
        if t_s - req.start_s > p.command_timeout_s:
            self._stop = None       # (made again at once while the stream is still stopped)
            self.last_result = f'stop {req.value} request timed out ({req.reason})'
            return
        if t_s - req.last_sent_s >= p.command_retry_s:
            req.last_sent_s = t_s
            req.sends += 1
            p1, p2, p3 = do_set_mode_params(p.autopilot, str(req.value))
            out.append(Outgoing('command', MAV_CMD_DO_SET_MODE,
                                (p1, p2, p3, 0.0, 0.0, 0.0, 0.0), note=str(req.value)))

    def _step_offboard(self, t_s: float, out: list[Outgoing]) -> None:
        req = self._offboard
        if req is None:
            return
        p = self.params
        if self.mode == p.offboard_mode and (self.armed or req.accepted):
            self._offboard = None
            self.last_result = (f'{p.offboard_mode} active' if self.armed else
                                f'{p.offboard_mode} selected (disarmed)')
            return
        if t_s - req.start_s > p.command_timeout_s:
            self._offboard = None
            self.last_result = f'{p.offboard_mode} request timed out'
            return
        if req.accepted:
            return  # the verdict was ACCEPTED: wait for the HEARTBEAT, do not re-send
        if self.stream_age_s(t_s) < p.offboard_warmup_s - 1e-9 or \
                t_s - self._last_sent_s > 0.5 * p.input_timeout_s:
            return  # stream first, and only ask while it is flowing right now
        if t_s - req.last_sent_s >= p.command_retry_s:
            # fail closed at every send: what the autopilot told us since the request (a
            # PARAM_VALUE of GUID_OPTIONS = 0, a re-read after a reconnection) still counts
            problem = self.ardupilot_config_problem() or self.px4_config_problem()
            if problem:
                self._offboard = None
                self.last_result = f'{p.offboard_mode} request cancelled: {problem}'
                return
            req.last_sent_s = t_s
            req.acks = 0
            req.sends += 1
            p1, p2, p3 = do_set_mode_params(p.autopilot, p.offboard_mode)
            out.append(Outgoing('command', MAV_CMD_DO_SET_MODE,
                                (p1, p2, p3, 0.0, 0.0, 0.0, 0.0), note=p.offboard_mode))

    def _step_arm(self, t_s: float, out: list[Outgoing]) -> None:
        req = self._arm
        if req is None:
            return
        p = self.params
        if self.armed == req.value:
            self._arm = None
            self.last_result = 'armed' if req.value else 'disarmed'
            return
        # ArduPilot refuses a disarm until its land detector confirms (FAILED): retried
        # slower and longer (LAND disarms by itself ~0.5 s after the detection)
        ap_disarm = p.autopilot == 'ardupilot' and not req.value
        timeout = p.disarm_timeout_s if ap_disarm else p.command_timeout_s
        retry = p.disarm_retry_s if ap_disarm and req.refusals else p.command_retry_s
        if t_s - req.start_s > timeout:
            self._arm = None
            self.last_result = ('arm' if req.value else 'disarm') + ' request timed out' + (
                ' (the autopilot still says in the air; PX4 disarms by itself after '
                'landing, COM_DISARM_LAND)' if req.deferred else
                f' after {req.refusals} refusals (ArduPilot never confirmed the landing)'
                if req.refusals else '')
            return
        if req.deferred:
            if self.landed is not True:
                return          # wait for the land detector (PX4 would refuse again)
            req.deferred = False
            req.last_sent_s = -math.inf
        if t_s - req.last_sent_s >= retry:
            req.last_sent_s = t_s
            req.sends += 1
            out.append(Outgoing('command', MAV_CMD_COMPONENT_ARM_DISARM,
                                (1.0 if req.value else 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
                                note='arm' if req.value else 'disarm'))
