"""A PX4-like autopilot for the simulator: the MAVLink side the bridge talks to (no rclpy).

:class:`Px4Emulator` speaks MAVLink 2 (pymavlink's ``common`` dialect, encoder and decoder used
directly, no ``mavutil`` global state) over a byte transport: a loopback UDP socket by default
(:class:`UdpTransport`, bound to 127.0.0.1 like PX4 SITL, sending to the companion's port and
answering whoever last sent it a valid packet) or an in-memory pair (:class:`MemoryLink`).

It is stepped with the simulator's time ``t_s`` (never the wall clock):

``update(t_s)``
    read every pending packet and act on it: COMMAND_LONG (SET_MESSAGE_INTERVAL,
    COMPONENT_ARM_DISARM, DO_SET_MODE, all answered with COMMAND_ACK), TIMESYNC requests
    (answered at once like PX4: ``tc1`` = emulator time in ns, ``ts1`` echoed), SET_ATTITUDE_TARGET
    (decoded back to ENU/FLU angles and newtons with the bridge's own
    :class:`~mavlink_bridge.conversions.ThrustCalibration`), HEARTBEAT, PARAM_REQUEST_READ /
    PARAM_SET; then run the mode logic with PX4 v1.16's personality (:class:`Px4Personality`):
    OFFBOARD is accepted with one setpoint younger than ``COM_OF_LOSS_T`` (always while
    disarmed); if the setpoints stop for ``offboard_loss_timeout_s`` (``COM_OF_LOSS_T``, 1.0 s)
    the failsafe switches to AUTO.LAND, AUTO.LOITER, AUTO.RTL or (PX4's default, Position
    without RC) a descent in POSCTL, and :attr:`failsafe_active` is set; auto-disarm after
    landing (``COM_DISARM_LAND``) or when never taking off (``COM_DISARM_PRFLT``).
``publish_state(t_s, ...)``
    the simulator's truth/sensor values; streams HEARTBEAT, ATTITUDE, LOCAL_POSITION_NED,
    DISTANCE_SENSOR (cm, orientation 25), HIGHRES_IMU / SCALED_IMU and EXTENDED_SYS_STATE at the
    rates the companion asked for.
``command()``
    what the vehicle should fly now, a :class:`VehicleCommand` named tuple
    ``(kind, roll_rad, pitch_rad, yaw_rad, thrust_n)`` with kind ``'idle'`` (disarmed),
    ``'offboard'`` (the last setpoint), ``'hold'`` (level, vertical speed 0), ``'land'`` or
    ``'failsafe_land'`` (level, descend at ``land_speed_mps``), ``'failsafe_return'`` (AUTO.RTL:
    fly to :attr:`home_m`, where OFFBOARD was engaged, then land there — the simulator node's
    ``AutopilotEmulation`` flies it; the thrust here only holds the vertical speed at 0).
    Hold/land thrust comes from a simple vertical-speed loop on the last published state,
    tilt-compensated.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
import math
import socket
from typing import NamedTuple

from deckland_common.frames import enu_to_ned, euler_enu_flu_to_ned_frd, flu_to_frd
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

Vec3 = tuple[float, float, float]

MODE_POSCTL = (3, 0)
MODE_ALTCTL = (2, 0)
MODE_OFFBOARD = (6, 0)
MODE_AUTO_LOITER = (4, 3)
MODE_AUTO_RTL = (4, 5)
MODE_AUTO_LAND = (4, 6)
_ACCEPTED_MODES = (MODE_POSCTL, MODE_ALTCTL, MODE_OFFBOARD, MODE_AUTO_LOITER, MODE_AUTO_LAND)
FORCE_DISARM_MAGIC = 21196
#: offboard_loss_action → the mode PX4 switches to (COM_OBL_RC_ACT); 'position' is PX4's
#: default 0: without RC an emergency descent while the heartbeat reads POSCTL
_LOSS_MODES = {'land': MODE_AUTO_LAND, 'return': MODE_AUTO_RTL, 'hold': MODE_AUTO_LOITER,
               'position': MODE_POSCTL}
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


class VehicleCommand(NamedTuple):
    """What the simulated vehicle should do: ``world.set_command(roll, pitch, yaw, thrust)``."""

    kind: str        # 'idle' | 'offboard' | 'hold' | 'land' | 'failsafe_land' | 'failsafe_return'
    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    thrust_n: float


@dataclass(frozen=True, slots=True)
class EmulatorParams:
    """PX4-like behaviour; names in comments are the PX4 parameters they stand for."""

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
    vz_gain_per_s: float = 2.0             # hold/land vertical speed loop gain
    disarm_landed_s: float = 2.0           # COM_DISARM_LAND (<= 0: off)
    disarm_preflight_s: float = 10.0       # COM_DISARM_PRFLT (<= 0: off)
    range_min_cm: int = 5                  # LidarLite v3
    range_max_cm: int = 4000
    thrust: ThrustCalibration = field(default_factory=ThrustCalibration)

    def __post_init__(self) -> None:
        for name in ('offboard_loss_timeout_s', 'land_speed_mps', 'vz_gain_per_s'):
            v = getattr(self, name)
            if not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0.0:
                raise ValueError(f'EmulatorParams.{name} = {v!r}: must be a finite number > 0')
        for name in ('disarm_landed_s', 'disarm_preflight_s'):
            v = getattr(self, name)
            if not isinstance(v, (int, float)) or not math.isfinite(v):
                raise ValueError(f'EmulatorParams.{name} = {v!r}: must be finite')
        if self.offboard_loss_action not in _LOSS_MODES:
            raise ValueError(f'EmulatorParams.offboard_loss_action = '
                             f"{self.offboard_loss_action!r}: must be 'land', 'hold', "
                             "'return' or 'position'")
        for name in ('system_id', 'component_id'):
            if not 1 <= getattr(self, name) <= 255:
                raise ValueError(f'EmulatorParams.{name} = {getattr(self, name)!r}: '
                                 'must be in [1, 255]')
        for name in ('bind_port', 'remote_port'):
            if not 0 <= getattr(self, name) <= 65535:
                raise ValueError(f'EmulatorParams.{name} = {getattr(self, name)!r}: '
                                 'must be a UDP port')
        if not 0 < self.range_min_cm < self.range_max_cm < 65535:
            raise ValueError(f'EmulatorParams.range_min_cm/range_max_cm = '
                             f'{self.range_min_cm}/{self.range_max_cm}: need 0 < min < max')


# --- transports ----------------------------------------------------------------------------

class UdpTransport:
    """Non-blocking UDP socket bound to ``bind``; sends to ``remote`` (updated by the emulator
    to the source of the last *valid* MAVLink packet, as PX4 does)."""

    def __init__(self, bind: tuple[str, int], remote: tuple[str, int]) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(bind)
        self.sock.setblocking(False)
        self.remote = remote
        self.send_errors = 0

    @property
    def local_address(self) -> tuple[str, int]:
        return self.sock.getsockname()

    def send(self, data: bytes) -> None:
        try:
            self.sock.sendto(data, self.remote)
        except OSError:
            self.send_errors += 1  # nobody listening yet (ECONNREFUSED) and the like

    def receive(self) -> list[tuple[bytes, object]]:
        out = []
        for _ in range(1000):
            try:
                data, addr = self.sock.recvfrom(65535)
            except (BlockingIOError, InterruptedError):
                break
            except OSError:
                continue  # ICMP port unreachable reported on a later recv
            out.append((data, addr))
        return out

    def set_peer(self, addr: object) -> None:
        self.remote = addr

    def close(self) -> None:
        self.sock.close()


class MemoryLink:
    """Two in-memory endpoints ``a`` and ``b``: bytes sent on one are received on the other."""

    class End:
        def __init__(self) -> None:
            self.inbox: list[bytes] = []
            self.peer: MemoryLink.End | None = None

        def send(self, data: bytes) -> None:
            self.peer.inbox.append(bytes(data))

        def write(self, data: bytes) -> None:  # pymavlink file-like writer
            self.send(data)

        def receive(self) -> list[tuple[bytes, object]]:
            out, self.inbox = self.inbox, []
            return [(d, None) for d in out]

        def set_peer(self, addr: object) -> None:
            pass

        def close(self) -> None:
            pass

    def __init__(self) -> None:
        self.a, self.b = MemoryLink.End(), MemoryLink.End()
        self.a.peer, self.b.peer = self.b, self.a


class _Writer:
    """File-like adapter pymavlink's encoder writes packed messages to."""

    def __init__(self, transport) -> None:
        self.transport = transport

    def write(self, data: bytes) -> None:
        self.transport.send(data)


# --- the emulator --------------------------------------------------------------------------

class Px4Emulator:
    """PX4-like autopilot endpoint for the simulator (see the module docstring)."""

    def __init__(self, params: EmulatorParams | None = None, transport=None) -> None:
        self.params = params or EmulatorParams()
        p = self.params
        self.transport = transport if transport is not None else UdpTransport(
            (p.bind_host, p.bind_port), (p.remote_host, p.remote_port))
        self.mav = mavlink.MAVLink(_Writer(self.transport), srcSystem=p.system_id,
                                   srcComponent=p.component_id)
        self.mav.robust_parsing = True
        self.rejected: dict[str, int] = {'nan': 0, 'bad_data': 0, 'out_of_order': 0,
                                         'wrong_target': 0, 'unsupported_mask': 0,
                                         'bad_signature': 0}
        self.counters: dict[str, int] = {'setpoints_rx': 0, 'commands_rx': 0,
                                         'heartbeats_rx': 0, 'messages_tx': 0,
                                         'failsafes': 0, 'timesync_rx': 0}
        self.intervals_s = dict(DEFAULT_INTERVALS_S)
        self._next_due = dict.fromkeys(self.intervals_s, -math.inf)
        self.armed = False
        self.main_mode, self.sub_mode = MODE_POSCTL
        self.failsafe_active = False
        #: (x, y) ENU where OFFBOARD was last engaged: the RTL target (None before)
        self.home_m: tuple[float, float] | None = None
        self.acks: list[tuple[int, int]] = []   # (command, result) sent, for tests/diagnostics
        self.setpoint: VehicleCommand | None = None
        self.last_setpoint_s = -math.inf
        self._user_mode = MODE_POSCTL   # PX4's "user intention": restored after a failsafe
        self.last_peer_heartbeat_s = -math.inf
        self._t_s = -math.inf
        self._t0_s: float | None = None
        # latest published state
        self._pos: Vec3 = (0.0, 0.0, 0.0)
        self._vel: Vec3 = (0.0, 0.0, 0.0)
        self._att: Vec3 = (0.0, 0.0, 0.0)
        self._rates: Vec3 = (0.0, 0.0, 0.0)
        self._accel: Vec3 = (0.0, 0.0, 9.81)
        self._range_m: float | None = None
        self.landed = True
        self._hold_yaw = 0.0
        self._armed_since_s = -math.inf
        self._airborne_since_arm = False
        self._landed_since_s: float | None = None

    # --- properties ----------------------------------------------------------------------

    @property
    def mode(self) -> str:
        """PX4 mode name ('POSCTL', 'OFFBOARD', 'AUTO.LAND', ...)."""
        return px4_mode_name(px4_custom_mode(self.main_mode, self.sub_mode))

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
        """Swap the byte transport (e.g. wrap it in the simulator's link-fault impairment,
        :class:`deck_simulator.node.ImpairedLink`); the encoder writes to the new one."""
        self.transport = transport
        self.mav.file = _Writer(transport)

    # --- stepping ------------------------------------------------------------------------

    def update(self, t_s: float) -> None:
        """Read and handle every pending packet, then run the failsafe and disarm logic."""
        if not math.isfinite(t_s):
            self.rejected['nan'] += 1
            return
        if t_s < self._t_s:
            self.rejected['out_of_order'] += 1
            return
        self._t_s = t_s
        if self._t0_s is None:
            self._t0_s = t_s
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
        self._run_logic(t_s)
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
        if t_s < self._t_s:
            self.rejected['out_of_order'] += 1
            return
        self._t_s = t_s
        if self._t0_s is None:
            self._t0_s = t_s
        self._pos, self._vel = tuple(position_enu), tuple(velocity_enu)
        self._att, self._rates = (roll, pitch, yaw), tuple(rates_flu)
        self._accel = tuple(accel_body_flu)
        self._range_m = range_m if range_m is not None and math.isfinite(range_m) else None
        self.landed = bool(landed)
        self._send_due(t_s, only_heartbeat=False)

    def command(self) -> VehicleCommand:
        """What the vehicle should fly now (see :class:`VehicleCommand`)."""
        roll, pitch, yaw = self._att
        if not self.armed:
            return VehicleCommand('idle', 0.0, 0.0, yaw, 0.0)
        mode = (self.main_mode, self.sub_mode)
        if mode == MODE_OFFBOARD and self.setpoint is not None:
            return self.setpoint
        cal = self.params.thrust
        if mode == MODE_AUTO_LAND or (mode == MODE_POSCTL and self.failsafe_active):
            # (POSCTL in a failsafe: PX4's 'position' action without RC is a descent)
            vz_ref, kind = -self.params.land_speed_mps, (
                'failsafe_land' if self.failsafe_active else 'land')
        elif mode == MODE_AUTO_RTL:
            vz_ref, kind = 0.0, 'failsafe_return'
        else:
            vz_ref, kind = 0.0, 'hold'
        accel = cal.gravity_mps2 + self.params.vz_gain_per_s * (vz_ref - self._vel[2])
        tilt = max(math.cos(roll) * math.cos(pitch), 0.5)
        thrust = min(max(cal.mass_kg * accel / tilt, 0.0), cal.max_thrust_n)
        return VehicleCommand(kind, 0.0, 0.0, self._hold_yaw, thrust)

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

    def _set_mode(self, mode: tuple[int, int]) -> None:
        if mode != MODE_OFFBOARD:
            self._hold_yaw = self._att[2]  # hold/land keep the heading of the switch
        elif (self.main_mode, self.sub_mode) != MODE_OFFBOARD:
            self.home_m = (self._pos[0], self._pos[1])   # RTL comes back here
        self.main_mode, self.sub_mode = mode

    def _ack(self, command: int, result: int, msg) -> None:
        self.acks.append((command, result))
        del self.acks[:-50]
        self.mav.command_ack_send(command, result, 0, 0, msg.get_srcSystem(),
                                  msg.get_srcComponent())

    def _handle(self, t_s: float, msg) -> None:
        kind = msg.get_type()
        p = self.params
        if kind == 'HEARTBEAT':
            self.counters['heartbeats_rx'] += 1
            self.last_peer_heartbeat_s = t_s
        elif kind == 'SET_ATTITUDE_TARGET':
            if msg.target_system not in (0, p.system_id):
                self.rejected['wrong_target'] += 1
                return
            if msg.type_mask & (64 | 128):
                self.rejected['unsupported_mask'] += 1
                return
            tgt = decode_attitude_target(tuple(msg.q), msg.thrust, msg.type_mask, p.thrust)
            if tgt is None:
                self.rejected['nan'] += 1
                return
            self.counters['setpoints_rx'] += 1
            self.last_setpoint_s = t_s
            self.setpoint = VehicleCommand('offboard', tgt.roll_rad, tgt.pitch_rad,
                                           tgt.yaw_rad, tgt.thrust_n)
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
        interval is refused (FAILED), a disarm in the air is TEMPORARILY_REJECTED, a
        DO_SET_MODE is ACKed twice (the MAVLink receiver's ACCEPTED, then the commander's
        verdict), OFFBOARD needs one setpoint younger than COM_OF_LOSS_T when armed and is
        always accepted while disarmed (arming in OFFBOARD then needs the setpoint)."""
        cmd = msg.command
        fresh = t_s - self.last_setpoint_s <= self.params.offboard_loss_timeout_s
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
            if msg.param1 >= 0.5:
                if (self.main_mode, self.sub_mode) == MODE_OFFBOARD and not fresh \
                        and not self.armed:
                    self._ack(cmd, mavlink.MAV_RESULT_TEMPORARILY_REJECTED, msg)
                    return
                if not self.armed:
                    self.armed = True
                    self._armed_since_s = t_s
                    self._airborne_since_arm = not self.landed
                    self._landed_since_s = None
                    self._hold_yaw = self._att[2]
                self._ack(cmd, mavlink.MAV_RESULT_ACCEPTED, msg)
            elif self.landed or int(msg.param2) == FORCE_DISARM_MAGIC or not self.armed:
                self._disarm()
                self._ack(cmd, mavlink.MAV_RESULT_ACCEPTED, msg)
            else:   # no disarm in the air (PX4: "Disarming denied: not landed")
                self._ack(cmd, mavlink.MAV_RESULT_TEMPORARILY_REJECTED, msg)
        elif cmd == mavlink.MAV_CMD_DO_SET_MODE:
            self._ack(cmd, mavlink.MAV_RESULT_ACCEPTED, msg)      # PX4's MAVLink receiver
            mode = (int(msg.param2), int(msg.param3) if int(msg.param2) == 4 else 0)
            if not int(msg.param1) & MAV_MODE_FLAG_CUSTOM_MODE_ENABLED or \
                    mode not in _ACCEPTED_MODES:
                self._ack(cmd, mavlink.MAV_RESULT_UNSUPPORTED, msg)
                return
            if mode == MODE_OFFBOARD and self.armed and not fresh:
                self._ack(cmd, mavlink.MAV_RESULT_TEMPORARILY_REJECTED, msg)
                return
            self._set_mode(mode)
            self._user_mode = mode
            self.failsafe_active = False
            self._ack(cmd, mavlink.MAV_RESULT_ACCEPTED, msg)       # the commander's verdict
        else:
            self._ack(cmd, mavlink.MAV_RESULT_UNSUPPORTED, msg)

    # --- parameters (PX4 v1.16 names, defaults and encoding) -----------------------------

    def param_table(self) -> dict[str, tuple[int, float]]:
        """The parameters this emulator answers, ``name → (MAV_PARAM_TYPE, value)``: PX4
        v1.16's names and defaults, with the values this emulator behaves by."""
        p = self.params
        return {
            'COM_OBL_RC_ACT': (MAV_PARAM_TYPE_INT32,
                               float(_LOSS_ACTION_VALUE[p.offboard_loss_action])),
            'COM_OF_LOSS_T': (MAV_PARAM_TYPE_REAL32, p.offboard_loss_timeout_s),
            'MPC_THR_HOVER': (MAV_PARAM_TYPE_REAL32, p.thrust.hover_thrust_norm),
            'MPC_USE_HTE': (MAV_PARAM_TYPE_INT32, 1.0),
            'MPC_LAND_SPEED': (MAV_PARAM_TYPE_REAL32, p.land_speed_mps),
            'COM_DISARM_LAND': (MAV_PARAM_TYPE_REAL32, p.disarm_landed_s),
            'COM_DISARM_PRFLT': (MAV_PARAM_TYPE_REAL32, p.disarm_preflight_s),
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
            typ = table[name][0]
            v = param_value_from_wire(msg.param_value, typ, True)
            try:
                if name == 'COM_OBL_RC_ACT' and int(v) in PX4_OFFBOARD_LOSS_ACTIONS and \
                        PX4_OFFBOARD_LOSS_ACTIONS[int(v)] in _LOSS_MODES:
                    self.params = replace(self.params,
                                          offboard_loss_action=PX4_OFFBOARD_LOSS_ACTIONS[int(v)])
                elif name == 'COM_OF_LOSS_T':
                    self.params = replace(self.params, offboard_loss_timeout_s=v)
                elif name == 'MPC_LAND_SPEED':
                    self.params = replace(self.params, land_speed_mps=v)
            except ValueError:
                self.rejected['bad_data'] += 1   # out of range: the value stays
            table = self.param_table()
        names = list(table)
        typ, value = table[name]
        self.mav.param_value_send(name.encode('ascii'), param_value_to_wire(value, typ, True),
                                  typ, len(names), names.index(name))

    def _disarm(self) -> None:
        self.armed = False
        if self.failsafe_active:
            # PX4 restores the user's mode once the failsafe clears (at disarm): after a
            # failsafe landing the heartbeat reads OFFBOARD while disarmed (v1.16, measured)
            self.main_mode, self.sub_mode = self._user_mode
        self.failsafe_active = False  # counters['failsafes'] keeps the history
        self._landed_since_s = None

    def _run_logic(self, t_s: float) -> None:
        p = self.params
        if self.armed and (self.main_mode, self.sub_mode) == MODE_OFFBOARD and \
                t_s - self.last_setpoint_s > p.offboard_loss_timeout_s:
            self._set_mode(_LOSS_MODES[p.offboard_loss_action])
            self.failsafe_active = True
            self.counters['failsafes'] += 1
        if not self.armed:
            return
        if not self.landed:
            self._airborne_since_arm = True
            self._landed_since_s = None
            return
        if self._landed_since_s is None:
            self._landed_since_s = t_s
        limit = p.disarm_landed_s if self._airborne_since_arm else p.disarm_preflight_s
        if limit > 0.0 and t_s - self._landed_since_s >= limit:
            self._disarm()

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
            base = MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (MAV_MODE_FLAG_SAFETY_ARMED
                                                        if self.armed else 0)
            status = mavlink.MAV_STATE_ACTIVE if self.armed else mavlink.MAV_STATE_STANDBY
            m.heartbeat_send(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4, base,
                             px4_custom_mode(self.main_mode, self.sub_mode), status)
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
