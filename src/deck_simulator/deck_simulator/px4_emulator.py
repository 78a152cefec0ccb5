"""A PX4-like MAVLink endpoint for the simulator: the autopilot's wire side (no rclpy).

:class:`Px4Emulator` speaks MAVLink 2 (pymavlink's ``common`` dialect, no ``mavutil`` global
state) over a byte transport (:mod:`deck_simulator.transport`) as PX4 presents itself, and
hands what it decodes to an :class:`~deck_simulator.autopilot.EmulatedAutopilot` (modes,
offboard acceptance, failsafes; the world flies it): ``update(t_s)`` reads the wire
(SET_ATTITUDE_TARGET, COMMAND_LONG with PX4 v1.16's ACKs, TIMESYNC, PARAM_REQUEST_READ /
PARAM_SET of PX4's parameters, HEARTBEAT); ``publish_state(t_s, ...)`` streams HEARTBEAT,
ATTITUDE, LOCAL_POSITION_NED, DISTANCE_SENSOR, HIGHRES_IMU / SCALED_IMU, EXTENDED_SYS_STATE.
Stepped with the simulator's time, never the wall clock.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
import math

from deckland_common.frames import enu_to_ned, euler_enu_flu_to_ned_frd, flu_to_frd
from deckland_common.validate import in_range, integer_at_least, require
from mavlink_bridge.conversions import (
    MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
    MAV_MODE_FLAG_SAFETY_ARMED,
    MAV_SENSOR_ROTATION_PITCH_270,
    PX4_OFFBOARD_LOSS_ACTIONS,
    ThrustCalibration,
    decode_attitude_target,
    param_value_from_wire,
    param_value_to_wire,
    px4_custom_mode,
    px4_mode_name,
    range_m_to_distance_cm,
)
from mavlink_bridge.signing import verify_signature_first
from pymavlink.dialects.v20 import common as mavlink

from deck_simulator import autopilot as ap_modes
from deck_simulator.autopilot import AttitudeSetpoint, AutopilotParams, EmulatedAutopilot
from deck_simulator.transport import MemoryLink, UdpTransport
from deck_simulator.vehicle import VehicleParams

Vec3 = tuple[float, float, float]

MODE_POSCTL = (3, 0)
MODE_ALTCTL = (2, 0)
MODE_OFFBOARD = (6, 0)
MODE_AUTO_LOITER = (4, 3)
MODE_AUTO_RTL = (4, 5)
MODE_AUTO_LAND = (4, 6)
#: PX4 (main, sub) custom mode of each generic autopilot mode
PX4_MODES = {ap_modes.POSITION: MODE_POSCTL, ap_modes.ALTITUDE: MODE_ALTCTL,
             ap_modes.OFFBOARD: MODE_OFFBOARD, ap_modes.HOLD: MODE_AUTO_LOITER,
             ap_modes.RETURN: MODE_AUTO_RTL, ap_modes.LAND: MODE_AUTO_LAND}


def px4_name(generic_mode: str) -> str:
    """The PX4 v1.16 name of a generic autopilot mode (``'return'`` → ``'AUTO.RTL'``), as the
    bridge reports it from the emulator's heartbeat; the generic name when PX4 has none."""
    mode = PX4_MODES.get(generic_mode)
    if mode is None:
        return generic_mode
    return px4_mode_name(px4_custom_mode(*mode))


#: the modes a companion may ask for with DO_SET_MODE
_ACCEPTED_MODES = {MODE_POSCTL: ap_modes.POSITION, MODE_ALTCTL: ap_modes.ALTITUDE,
                   MODE_OFFBOARD: ap_modes.OFFBOARD, MODE_AUTO_LOITER: ap_modes.HOLD,
                   MODE_AUTO_LAND: ap_modes.LAND}
FORCE_DISARM_MAGIC = 21196
_LOSS_ACTION_VALUE = {v: k for k, v in PX4_OFFBOARD_LOSS_ACTIONS.items()}
MAV_PARAM_TYPE_INT32 = 6
MAV_PARAM_TYPE_REAL32 = 9

#: message id → default stream interval (s); ≤ 0 = off. SET_MESSAGE_INTERVAL changes them.
DEFAULT_INTERVALS_S = {
    mavlink.MAVLINK_MSG_ID_HEARTBEAT: 1.0,
    mavlink.MAVLINK_MSG_ID_ATTITUDE: 1.0 / 50.0,
    mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED: 1.0 / 30.0,
    mavlink.MAVLINK_MSG_ID_DISTANCE_SENSOR: 1.0 / 10.0,
    mavlink.MAVLINK_MSG_ID_HIGHRES_IMU: 1.0 / 50.0,
    mavlink.MAVLINK_MSG_ID_SCALED_IMU: 0.0,
    mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: 1.0 / 5.0,
}


def vehicle_thrust_calibration(vehicle: VehicleParams) -> ThrustCalibration:
    """Normalised thrust as the simulated vehicle's motors give it: hover at 1 / (T/W)."""
    return ThrustCalibration(mass_kg=vehicle.mass_kg, gravity_mps2=vehicle.gravity_mps2,
                             hover_thrust_norm=1.0 / vehicle.thrust_to_weight)


@dataclass(frozen=True, slots=True)
class EmulatorParams:
    """The MAVLink side and the PX4 parameters the autopilot behaves by (PX4 names in the
    comments; :meth:`autopilot_params` turns them into the autopilot's settings)."""

    system_id: int = 1
    component_id: int = 1
    bind_host: str = '127.0.0.1'
    bind_port: int = 14580                 # PX4 SITL's onboard link port (0 = any free port)
    remote_host: str = '127.0.0.1'
    remote_port: int = 14540               # where the companion (the bridge) listens
    offboard_loss_timeout_s: float = 1.0   # COM_OF_LOSS_T (PX4 default 1.0 s)
    #: COM_OBL_RC_ACT: 'land' (4, deckland's set-up, the README), 'hold' (5), 'return' (3,
    #: RTL) or 'position' (0, PX4's default: without RC a descent while the heartbeat says
    #: POSCTL)
    offboard_loss_action: str = 'land'
    land_speed_mps: float = 0.7            # MPC_LAND_SPEED
    disarm_landed_s: float = 2.0           # COM_DISARM_LAND (<= 0: off)
    disarm_preflight_s: float = 10.0       # COM_DISARM_PRFLT (<= 0: off)
    range_min_cm: int = 5                  # LidarLite v3
    range_max_cm: int = 4000
    thrust: ThrustCalibration = field(
        default_factory=lambda: vehicle_thrust_calibration(VehicleParams()))

    def __post_init__(self) -> None:
        for name in ('system_id', 'component_id'):
            in_range(f'EmulatorParams.{name}', getattr(self, name), 1, 255)
        for name in ('bind_port', 'remote_port'):
            in_range(f'EmulatorParams.{name}', getattr(self, name), 0, 65535)
        integer_at_least('EmulatorParams.range_min_cm', self.range_min_cm, 1)
        require(isinstance(self.range_max_cm, int)
                and self.range_min_cm < self.range_max_cm < 65535,
                'EmulatorParams.range_max_cm',
                f'must be an integer in ({self.range_min_cm}, 65535)', self.range_max_cm)
        self.autopilot_params()   # validates the autopilot's fields (ValueError naming them)

    def autopilot_params(self) -> AutopilotParams:
        """The autopilot's settings these PX4 parameters stand for."""
        return AutopilotParams(offboard_loss_timeout_s=self.offboard_loss_timeout_s,
                               offboard_loss_action=self.offboard_loss_action,
                               land_speed_mps=self.land_speed_mps,
                               disarm_landed_s=self.disarm_landed_s,
                               disarm_preflight_s=self.disarm_preflight_s)


class _Writer:
    """File-like adapter pymavlink's encoder writes packed messages to."""

    def __init__(self, transport) -> None:
        self.transport = transport

    def write(self, data: bytes) -> None:
        self.transport.send(data)


class Px4Emulator:
    """PX4's MAVLink face of an autopilot (see the module docstring).

    ``autopilot`` None: the emulator makes its own from ``params.autopilot`` and runs its mode
    logic in :meth:`update` (no world flies it: a MAVLink peer for the bridge's tests).
    Otherwise the caller's world ticks the autopilot (:class:`deck_simulator.loop.SimulationLoop`).
    """

    def __init__(self, params: EmulatorParams | None = None, transport=None,
                 autopilot: EmulatedAutopilot | None = None) -> None:
        self.params = params or EmulatorParams()
        p = self.params
        self.transport = transport if transport is not None else UdpTransport(
            (p.bind_host, p.bind_port), (p.remote_host, p.remote_port))
        self.mav = mavlink.MAVLink(_Writer(self.transport), srcSystem=p.system_id,
                                   srcComponent=p.component_id)
        self.mav.robust_parsing = True
        self._drives_autopilot = autopilot is None
        self.autopilot = autopilot if autopilot is not None else EmulatedAutopilot(
            p.autopilot_params())
        self.rejected: dict[str, int] = {'nan': 0, 'bad_data': 0, 'out_of_order': 0,
                                         'wrong_target': 0, 'unsupported_mask': 0,
                                         'bad_signature': 0}
        self.counters: dict[str, int] = {'setpoints_rx': 0, 'commands_rx': 0,
                                         'heartbeats_rx': 0, 'messages_tx': 0,
                                         'timesync_rx': 0}
        self.intervals_s = dict(DEFAULT_INTERVALS_S)
        self._next_due = dict.fromkeys(self.intervals_s, -math.inf)
        self.acks: list[tuple[int, int]] = []   # (command, result) sent, for tests/diagnostics
        self.last_peer_heartbeat_s = -math.inf
        self._t_s = -math.inf
        self._t0_s: float | None = None
        # latest published state
        self._pos: Vec3 = (0.0, 0.0, 0.0)
        self._vel: Vec3 = (0.0, 0.0, 0.0)
        self._att: Vec3 = (0.0, 0.0, 0.0)
        self._rates: Vec3 = (0.0, 0.0, 0.0)
        self._accel: Vec3 = (0.0, 0.0, VehicleParams().gravity_mps2)
        self._range_m: float | None = None
        self.landed = True

    # --- the autopilot's state, as PX4 names it -------------------------------------------

    @property
    def mode(self) -> str:
        """PX4 mode name ('POSCTL', 'OFFBOARD', 'AUTO.LAND', ...)."""
        return px4_mode_name(px4_custom_mode(*PX4_MODES[self.autopilot.mode]))

    @property
    def armed(self) -> bool:
        return self.autopilot.armed

    @property
    def failsafe_active(self) -> bool:
        """The offboard-loss failsafe flies (until a mode is set or the vehicle disarms)."""
        return self.autopilot.in_failsafe

    @property
    def kind(self) -> str:
        """What flies the vehicle (:attr:`EmulatedAutopilot.kind`)."""
        return self.autopilot.kind

    @property
    def home_m(self) -> tuple[float, float] | None:
        """(x, y) ENU where OFFBOARD was last engaged: the RTL target."""
        return self.autopilot.home_m

    @property
    def setpoint(self) -> AttitudeSetpoint | None:
        """The last decoded SET_ATTITUDE_TARGET (ENU/FLU, newtons)."""
        return self.autopilot.setpoint

    @property
    def last_setpoint_s(self) -> float:
        return self.autopilot.last_setpoint_s

    @property
    def local_address(self):
        return getattr(self.transport, 'local_address', None)

    def close(self) -> None:
        self.transport.close()

    def setup_signing(self, secret_key: bytes, initial_timestamp: int, link_id: int = 0) -> None:
        """MAVLink 2 signing as PX4 does it once a key is provisioned: every outgoing message
        is signed with ``secret_key`` (32 bytes), and incoming messages without a valid
        signature for it are dropped (``rejected['bad_signature']``). ``initial_timestamp``
        is in 10 µs units since 2015-01-01 (the caller's wall clock: a receiver refuses a new
        stream more than 60 s behind its own time)."""
        if not isinstance(secret_key, bytes | bytearray) or len(secret_key) != 32:
            raise ValueError('Px4Emulator.setup_signing: secret_key must be 32 bytes')
        if not isinstance(initial_timestamp, int) or initial_timestamp < 0:
            raise ValueError('Px4Emulator.setup_signing: initial_timestamp must be an int >= 0')
        sig = self.mav.signing
        sig.secret_key = bytes(secret_key)
        sig.sign_outgoing = True
        sig.allow_unsigned_callback = None
        sig.link_id = link_id
        sig.timestamp = initial_timestamp
        # a forged packet must not advance a stream's replay timestamp
        verify_signature_first(self.mav)

    def set_transport(self, transport) -> None:
        """Swap the byte transport (e.g. wrap it in the link faults' impairment,
        :class:`deck_simulator.link.ImpairedLink`); the encoder writes to the new one."""
        self.transport = transport
        self.mav.file = _Writer(transport)

    def use_autopilot(self, autopilot: EmulatedAutopilot) -> None:
        """Be the MAVLink face of ``autopilot`` (ticked by its world from now on)."""
        self.autopilot = autopilot
        self._drives_autopilot = False

    # --- stepping ------------------------------------------------------------------------

    def _advance_clock(self, t_s: float) -> bool:
        """Take ``t_s`` as the emulator's time; False (counted ``out_of_order``) if it went
        backwards."""
        if t_s < self._t_s:
            self.rejected['out_of_order'] += 1
            return False
        self._t_s = t_s
        if self._t0_s is None:
            self._t0_s = t_s
        return True

    def update(self, t_s: float) -> None:
        """Read and handle every pending packet (and, without a world, run the mode logic)."""
        if not math.isfinite(t_s):
            self.rejected['nan'] += 1
            return
        if not self._advance_clock(t_s):
            return
        for data, addr in self.transport.receive():
            self._reset_parser()  # a datagram is self-contained: a truncated one ends here
            try:
                msgs = self.mav.parse_buffer(data) or []
            except Exception:  # pymavlink raises on some malformed input even when robust
                self.rejected['bad_data'] += 1
                continue
            valid = False
            for msg in msgs:
                if msg.get_type() == 'BAD_DATA':
                    if getattr(msg, 'reason', '') == 'Invalid signature':
                        self.rejected['bad_signature'] += 1
                    else:
                        self.rejected['bad_data'] += 1
                    continue
                valid = True
                try:
                    self._handle(t_s, msg)
                except Exception:
                    self.rejected['bad_data'] += 1
            if valid and addr is not None:
                self.transport.set_peer(addr)
        if self._drives_autopilot:
            self.autopilot.update(t_s, self.landed)
        self._send_due(t_s, only_heartbeat=True)

    def publish_state(self, t_s: float, position_enu: Vec3, velocity_enu: Vec3, roll: float,
                      pitch: float, yaw: float, rates_flu: Vec3, accel_body_flu: Vec3,
                      range_m: float | None, landed: bool) -> None:
        """The simulator's vehicle state (ENU/FLU, SI, specific force in body FLU); streams
        the telemetry that is due. Non-finite values are rejected (the previous state kept)."""
        vals = (t_s, *position_enu, *velocity_enu, roll, pitch, yaw, *rates_flu, *accel_body_flu)
        if not all(map(math.isfinite, vals)):
            self.rejected['nan'] += 1
            return
        if not self._advance_clock(t_s):
            return
        self._pos, self._vel = tuple(position_enu), tuple(velocity_enu)
        self._att, self._rates = (roll, pitch, yaw), tuple(rates_flu)
        self._accel = tuple(accel_body_flu)
        self._range_m = range_m if range_m is not None and math.isfinite(range_m) else None
        self.landed = bool(landed)
        if self._drives_autopilot:
            self.autopilot.landed = self.landed
        self._send_due(t_s, only_heartbeat=False)

    # --- internals -----------------------------------------------------------------------

    def _reset_parser(self) -> None:
        m = self.mav
        if m.buf_len() > 0:
            self.rejected['bad_data'] += 1  # leftover of a truncated packet
        m.buf = bytearray()
        m.buf_index = 0
        m.expected_length = mavlink.HEADER_LEN_V1 + 2
        m.have_prefix_error = False

    def _time_boot_ms(self, t_s: float) -> int:
        return max(int((t_s - (self._t0_s or 0.0)) * 1000.0), 0) & 0xFFFFFFFF

    def _ack(self, command: int, result: int, msg) -> None:
        self.acks.append((command, result))
        del self.acks[:-50]
        self.mav.command_ack_send(command, result, 0, 0, msg.get_srcSystem(),
                                  msg.get_srcComponent())

    def _attitude_target(self, msg):
        """A SET_ATTITUDE_TARGET for us, decoded (counted ``setpoints_rx``), or None, counted:
        another target system, body rates asked for (mask bits 64/128, ignored by PX4 and
        ArduCopter alike), or non-finite values."""
        p = self.params
        if msg.target_system not in (0, p.system_id):
            self.rejected['wrong_target'] += 1
            return None
        if msg.type_mask & (64 | 128):
            self.rejected['unsupported_mask'] += 1
            return None
        tgt = decode_attitude_target(tuple(msg.q), msg.thrust, msg.type_mask, p.thrust)
        if tgt is None:
            self.rejected['nan'] += 1
            return None
        self.counters['setpoints_rx'] += 1
        return tgt

    def _handle(self, t_s: float, msg) -> None:
        kind = msg.get_type()
        p = self.params
        if kind == 'HEARTBEAT':
            self.counters['heartbeats_rx'] += 1
            self.last_peer_heartbeat_s = t_s
        elif kind == 'SET_ATTITUDE_TARGET':
            tgt = self._attitude_target(msg)
            if tgt is None:
                return
            self.autopilot.on_setpoint(t_s, tgt.roll_rad, tgt.pitch_rad, tgt.yaw_rad,
                                       tgt.thrust_n)
        elif kind == 'TIMESYNC':
            # PX4 (Timesync::handle_time_sync): a request (tc1 == 0) is answered at once with
            # tc1 = our time (ns) and the request's ts1 echoed; the companion's round trip is
            # then (its receive time − ts1), through whatever impairs the link
            if msg.tc1 == 0:
                self.counters['timesync_rx'] += 1
                self.mav.timesync_send(max(1, round((t_s - (self._t0_s or 0.0)) * 1e9)),
                                       msg.ts1)
        elif kind == 'COMMAND_LONG':
            if msg.target_system not in (0, p.system_id):
                self.rejected['wrong_target'] += 1
                return
            self.counters['commands_rx'] += 1
            self._handle_command(t_s, msg)
        elif kind in ('PARAM_REQUEST_READ', 'PARAM_SET'):
            if msg.target_system not in (0, p.system_id):
                self.rejected['wrong_target'] += 1
                return
            self._handle_param(msg)

    def _handle_command(self, t_s: float, msg) -> None:
        """COMMAND_LONG with PX4 v1.16's answers (measured against its SITL): HEARTBEAT's
        interval is refused (FAILED), a DO_SET_MODE is ACKed twice (the MAVLink receiver's
        ACCEPTED, then the commander's verdict); arming and modes are the autopilot's rules."""
        cmd = msg.command
        ap = self.autopilot
        if cmd == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
            msg_id, interval_us = int(msg.param1), msg.param2
            if msg_id == mavlink.MAVLINK_MSG_ID_HEARTBEAT:
                self._ack(cmd, mavlink.MAV_RESULT_FAILED, msg)   # PX4: 1 Hz, by design
                return
            if msg_id not in self.intervals_s or not math.isfinite(interval_us):
                self._ack(cmd, mavlink.MAV_RESULT_UNSUPPORTED, msg)
                return
            if interval_us < 0:
                self.intervals_s[msg_id] = 0.0
            elif interval_us == 0:
                self.intervals_s[msg_id] = DEFAULT_INTERVALS_S[msg_id]
            else:
                self.intervals_s[msg_id] = interval_us * 1e-6
            self._next_due[msg_id] = -math.inf
            self._ack(cmd, mavlink.MAV_RESULT_ACCEPTED, msg)
        elif cmd == mavlink.MAV_CMD_COMPONENT_ARM_DISARM:
            self._ack(cmd, ap.request_arm(t_s, msg.param1 >= 0.5,
                                          force=int(msg.param2) == FORCE_DISARM_MAGIC), msg)
        elif cmd == mavlink.MAV_CMD_DO_SET_MODE:
            self._ack(cmd, mavlink.MAV_RESULT_ACCEPTED, msg)      # PX4's MAVLink receiver
            mode = (int(msg.param2), int(msg.param3) if int(msg.param2) == 4 else 0)
            if not int(msg.param1) & MAV_MODE_FLAG_CUSTOM_MODE_ENABLED or \
                    mode not in _ACCEPTED_MODES:
                self._ack(cmd, mavlink.MAV_RESULT_UNSUPPORTED, msg)
                return
            self._ack(cmd, ap.request_mode(t_s, _ACCEPTED_MODES[mode]), msg)   # the verdict
        else:
            self._ack(cmd, mavlink.MAV_RESULT_UNSUPPORTED, msg)

    # --- parameters (PX4 v1.16 names, defaults and encoding) -----------------------------

    def param_table(self) -> dict[str, tuple[int, float]]:
        """The parameters this emulator answers, ``name → (MAV_PARAM_TYPE, value)``: PX4
        v1.16's names and defaults, with the values its autopilot behaves by."""
        a = self.autopilot.params
        return {
            'COM_OBL_RC_ACT': (MAV_PARAM_TYPE_INT32,
                               float(_LOSS_ACTION_VALUE[a.offboard_loss_action])),
            'COM_OF_LOSS_T': (MAV_PARAM_TYPE_REAL32, a.offboard_loss_timeout_s),
            'MPC_THR_HOVER': (MAV_PARAM_TYPE_REAL32, self.params.thrust.hover_thrust_norm),
            'MPC_USE_HTE': (MAV_PARAM_TYPE_INT32, 1.0),
            'MPC_LAND_SPEED': (MAV_PARAM_TYPE_REAL32, a.land_speed_mps),
            'COM_DISARM_LAND': (MAV_PARAM_TYPE_REAL32, a.disarm_landed_s),
            'COM_DISARM_PRFLT': (MAV_PARAM_TYPE_REAL32, a.disarm_preflight_s),
        }

    def _handle_param(self, msg) -> None:
        """PARAM_REQUEST_READ (by name; PX4 answers nothing for an unknown one) and PARAM_SET
        of the behaviour parameters (COM_OBL_RC_ACT, COM_OF_LOSS_T, MPC_LAND_SPEED), each
        answered with PARAM_VALUE; integers are encoded bytewise as PX4 does."""
        name = msg.param_id.rstrip('\x00') if isinstance(msg.param_id, str) else ''
        table = self.param_table()
        if name not in table:
            return
        if msg.get_type() == 'PARAM_SET':
            v = param_value_from_wire(msg.param_value, table[name][0], True)
            change = {}
            if name == 'COM_OBL_RC_ACT' and PX4_OFFBOARD_LOSS_ACTIONS.get(int(v)) in \
                    ap_modes.LOSS_ACTIONS:
                change['offboard_loss_action'] = PX4_OFFBOARD_LOSS_ACTIONS[int(v)]
            elif name == 'COM_OF_LOSS_T':
                change['offboard_loss_timeout_s'] = v
            elif name == 'MPC_LAND_SPEED':
                change['land_speed_mps'] = v
            try:
                self.autopilot.params = replace(self.autopilot.params, **change)
                self.params = replace(self.params, **change)
            except ValueError:
                self.rejected['bad_data'] += 1   # out of range: the value stays
            table = self.param_table()
        names = list(table)
        typ, value = table[name]
        self.mav.param_value_send(name.encode('ascii'), param_value_to_wire(value, typ, True),
                                  typ, len(names), names.index(name))

    def _send_due(self, t_s: float, only_heartbeat: bool) -> None:
        for msg_id, interval in self.intervals_s.items():
            if interval <= 0.0 or t_s < self._next_due[msg_id]:
                continue
            if only_heartbeat and msg_id != mavlink.MAVLINK_MSG_ID_HEARTBEAT:
                continue
            nxt = self._next_due[msg_id] + interval
            self._next_due[msg_id] = nxt if nxt > t_s else t_s + interval
            self._send(msg_id, t_s)
            self.counters['messages_tx'] += 1

    def _send(self, msg_id: int, t_s: float) -> None:
        m = self.mav
        ms = self._time_boot_ms(t_s)
        if msg_id == mavlink.MAVLINK_MSG_ID_HEARTBEAT:
            armed = self.autopilot.armed
            base = MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (MAV_MODE_FLAG_SAFETY_ARMED
                                                        if armed else 0)
            status = mavlink.MAV_STATE_ACTIVE if armed else mavlink.MAV_STATE_STANDBY
            m.heartbeat_send(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4, base,
                             px4_custom_mode(*PX4_MODES[self.autopilot.mode]), status)
        elif msg_id == mavlink.MAVLINK_MSG_ID_ATTITUDE:
            r, p, y = euler_enu_flu_to_ned_frd(*self._att)
            wr, wp, wy = flu_to_frd(*self._rates)
            m.attitude_send(ms, r, p, y, wr, wp, wy)
        elif msg_id == mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED:
            x, y, z = enu_to_ned(*self._pos)
            vx, vy, vz = enu_to_ned(*self._vel)
            m.local_position_ned_send(ms, x, y, z, vx, vy, vz)
        elif msg_id == mavlink.MAVLINK_MSG_ID_DISTANCE_SENSOR:
            p = self.params
            m.distance_sensor_send(ms, p.range_min_cm, p.range_max_cm,
                                   range_m_to_distance_cm(self._range_m, p.range_max_cm),
                                   mavlink.MAV_DISTANCE_SENSOR_LASER, 0,
                                   MAV_SENSOR_ROTATION_PITCH_270, 255)
        elif msg_id == mavlink.MAVLINK_MSG_ID_HIGHRES_IMU:
            ax, ay, az = flu_to_frd(*self._accel)
            gx, gy, gz = flu_to_frd(*self._rates)
            m.highres_imu_send(ms * 1000, ax, ay, az, gx, gy, gz, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0,
                               0.0, 0x3F)
        elif msg_id == mavlink.MAVLINK_MSG_ID_SCALED_IMU:
            ax, ay, az = flu_to_frd(*self._accel)
            gx, gy, gz = flu_to_frd(*self._rates)
            k = 1000.0 / 9.80665

            def i16(v: float) -> int:
                return max(-32768, min(32767, round(v)))

            m.scaled_imu_send(ms, i16(ax * k), i16(ay * k), i16(az * k), i16(gx * 1e3),
                              i16(gy * 1e3), i16(gz * 1e3), 0, 0, 0)
        elif msg_id == mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE:
            m.extended_sys_state_send(mavlink.MAV_VTOL_STATE_UNDEFINED,
                                      mavlink.MAV_LANDED_STATE_ON_GROUND if self.landed
                                      else mavlink.MAV_LANDED_STATE_IN_AIR)


__all__ = ['DEFAULT_INTERVALS_S', 'PX4_MODES', 'EmulatorParams', 'MemoryLink', 'Px4Emulator',
           'UdpTransport', 'vehicle_thrust_calibration']
