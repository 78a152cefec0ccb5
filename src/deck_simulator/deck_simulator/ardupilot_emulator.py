"""The emulator's ArduCopter 4.5.6 personality: the MAVLink side as ArduCopter presents it.

:class:`ArduPilotEmulator` keeps :class:`~deck_simulator.px4_emulator.Px4Emulator`'s wire
(transport, parser, signing, telemetry encoding, TIMESYNC answers) and replaces what differs on
ArduCopter, each point measured on 4.5.6 SITL (``test_sitl_ardupilot_conformance.py``
runs the same expectations against both): streams off until asked, HIGHRES_IMU DENIED, custom
modes, PARAM_VALUE as plain floats, GUID_OPTIONS (climb-rate thrust when bit 3 is clear),
FAILED for refusals, GUID_TIMEOUT (last setpoint, then level and hold altitude, never a landing),
LAND's land detector and auto-disarm, the GCS failsafe, and STATUSTEXT with ArduCopter's wording.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
import math
from typing import NamedTuple

from mavlink_bridge.conversions import (
    ARDUCOPTER_MODES,
    MAV_SENSOR_ROTATION_PITCH_270,
    ThrustCalibration,
    euler_enu_to_quat_ned,
    range_m_to_distance_cm,
)
from pymavlink.dialects.v20 import common as mavlink

from deck_simulator.px4_emulator import EmulatorParams, Px4Emulator

STABILIZE, ALT_HOLD, GUIDED, LOITER, RTL, LAND = 0, 2, 4, 5, 6, 9
POSHOLD, BRAKE, GUIDED_NOGPS = 16, 17, 20
#: modes ArduCopter 4.5.6 SITL enters from the ground without RC (measured); the others of
#: ARDUCOPTER_MODES exist but refuse ("Mode change to X failed: init failed" and the like)
_ENTERABLE = frozenset({0, 1, 2, 3, 4, 5, 6, 7, 9, 11, 16, 17, 18, 19, 20, 21, 24})
_REFUSAL_TEXT = {27: 'Mode change to AUTO RTL failed: No landing sequence found'}
_HOLD_MODES = frozenset({ALT_HOLD, GUIDED, LOITER, POSHOLD, BRAKE})
_NOT_ARMABLE = frozenset({LAND, RTL, 21})
FORCE_DISARM_MAGIC = 21196
BASE_MODE = 81          # custom mode enabled | stabilize | manual input (ArduCopter, disarmed)
#: what ArduCopter streams on a SERIAL port whose SRn_* rates are 0 (SITL's SERIAL0): only
#: HEARTBEAT; the others once asked for (SET_MESSAGE_INTERVAL)
_STREAMS = (mavlink.MAVLINK_MSG_ID_ATTITUDE, mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED,
            mavlink.MAVLINK_MSG_ID_DISTANCE_SENSOR, mavlink.MAVLINK_MSG_ID_SCALED_IMU,
            mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE, mavlink.MAVLINK_MSG_ID_ATTITUDE_TARGET)
MAV_PARAM_TYPE_INT8, MAV_PARAM_TYPE_INT16 = 2, 4
MAV_PARAM_TYPE_INT32, MAV_PARAM_TYPE_REAL32 = 6, 9


class VehicleCommand(NamedTuple):
    """What ArduCopter flies now: ``kind`` ('idle', 'offboard', 'hold', 'land',
    'failsafe_land', 'failsafe_return'), attitude (FLU in ENU) and collective thrust (N)."""

    kind: str
    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    thrust_n: float


def _sitl_vehicle() -> ThrustCalibration:
    """ArduCopter SITL's built-in quad, as a thrust calibration: it hovers at 0.348 normalised
    thrust (measured in GUIDED_NOGPS, ATTITUDE_TARGET 0.345 in GUIDED); its mass is not
    reported, the paper's 2.71 kg stands in."""
    return ThrustCalibration(mass_kg=2.71, hover_thrust_norm=0.348)


@dataclass(frozen=True, slots=True)
class ArduPilotParams:
    """ArduCopter 4.5.6's defaults (SITL with ``copter.parm``); each field is the parameter
    in the comment. ``thrust`` is the emulated vehicle's true normalised thrust curve (what
    the physics does), ``MOT_THST_HOVER`` what ArduCopter believes before it has learned."""

    guid_options: int = 0                  # GUID_OPTIONS (bit 3: thrust, not climb rate)
    guid_timeout_s: float = 3.0            # GUID_TIMEOUT
    angle_boost: int = 1                   # ATC_ANGLE_BOOST
    hover_thrust_norm: float = 0.39        # MOT_THST_HOVER (copter.parm; learned at disarm)
    hover_learn: int = 2                   # MOT_HOVER_LEARN (2: learn, save at disarm)
    thrust_expo: float = 0.65              # MOT_THST_EXPO
    speed_up_mps: float = 2.5              # WPNAV_SPEED_UP (climb-rate thrust 1.0)
    speed_down_mps: float = 1.5            # WPNAV_SPEED_DN (climb-rate thrust 0.0)
    land_speed_mps: float = 0.5            # LAND_SPEED (cm/s on the wire)
    disarm_delay_s: float = 10.0           # DISARM_DELAY (landed, not in LAND)
    fs_gcs_enable: int = 0                 # FS_GCS_ENABLE (5: land)
    fs_gcs_timeout_s: float = 5.0          # FS_GCS_TIMEOUT
    sysid_mygcs: int = 255                 # SYSID_MYGCS
    arming_check: int = 1                  # ARMING_CHECK (not enforced here)
    range_min_cm: int = 20                 # RNGFND1_MIN_CM
    range_max_cm: int = 700                # RNGFND1_MAX_CM
    land_detect_s: float = 1.0             # LAND_DETECTOR_TRIGGER_SEC (firmware constant)
    land_disarm_s: float = 0.5             # LAND: spool-down to "Disarming motors" (measured)
    vz_gain_per_s: float = 2.0             # the emulated vertical-speed loop
    thrust: ThrustCalibration = field(default_factory=_sitl_vehicle)

    def __post_init__(self) -> None:
        for name in ('guid_timeout_s', 'hover_thrust_norm', 'speed_up_mps', 'speed_down_mps',
                     'land_speed_mps', 'fs_gcs_timeout_s', 'land_detect_s', 'vz_gain_per_s'):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v) \
                    or v <= 0.0:
                raise ValueError(f'ArduPilotParams.{name} = {v!r}: must be a finite number > 0')
        for name in ('disarm_delay_s', 'land_disarm_s', 'thrust_expo'):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v) \
                    or v < 0.0:
                raise ValueError(f'ArduPilotParams.{name} = {v!r}: must be a finite number >= 0')
        for name in ('guid_options', 'angle_boost', 'hover_learn', 'fs_gcs_enable',
                     'sysid_mygcs', 'arming_check', 'range_min_cm', 'range_max_cm'):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int):
                raise ValueError(f'ArduPilotParams.{name} = {v!r}: must be an integer')
        if not 0 < self.range_min_cm < self.range_max_cm < 65535:
            raise ValueError(f'ArduPilotParams.range_min_cm/range_max_cm = '
                             f'{self.range_min_cm}/{self.range_max_cm}: need 0 < min < max')
        if not isinstance(self.thrust, ThrustCalibration):
            raise ValueError('ArduPilotParams.thrust must be a ThrustCalibration')


#: PARAM_VALUE name → (MAV_PARAM_TYPE, ArduPilotParams field, scale to the wire)
_PARAMS = {
    'GUID_OPTIONS': (MAV_PARAM_TYPE_INT32, 'guid_options', 1.0),
    'GUID_TIMEOUT': (MAV_PARAM_TYPE_REAL32, 'guid_timeout_s', 1.0),
    'ATC_ANGLE_BOOST': (MAV_PARAM_TYPE_INT8, 'angle_boost', 1.0),
    'MOT_THST_HOVER': (MAV_PARAM_TYPE_REAL32, 'hover_thrust_norm', 1.0),
    'MOT_HOVER_LEARN': (MAV_PARAM_TYPE_INT8, 'hover_learn', 1.0),
    'MOT_THST_EXPO': (MAV_PARAM_TYPE_REAL32, 'thrust_expo', 1.0),
    'WPNAV_SPEED_UP': (MAV_PARAM_TYPE_REAL32, 'speed_up_mps', 100.0),
    'WPNAV_SPEED_DN': (MAV_PARAM_TYPE_REAL32, 'speed_down_mps', 100.0),
    'LAND_SPEED': (MAV_PARAM_TYPE_INT16, 'land_speed_mps', 100.0),
    'DISARM_DELAY': (MAV_PARAM_TYPE_INT8, 'disarm_delay_s', 1.0),
    'FS_GCS_ENABLE': (MAV_PARAM_TYPE_INT8, 'fs_gcs_enable', 1.0),
    'FS_GCS_TIMEOUT': (MAV_PARAM_TYPE_REAL32, 'fs_gcs_timeout_s', 1.0),
    'SYSID_MYGCS': (MAV_PARAM_TYPE_INT16, 'sysid_mygcs', 1.0),
    'ARMING_CHECK': (MAV_PARAM_TYPE_INT32, 'arming_check', 1.0),
    'RNGFND1_MIN_CM': (MAV_PARAM_TYPE_INT16, 'range_min_cm', 1.0),
    'RNGFND1_MAX_CM': (MAV_PARAM_TYPE_INT16, 'range_max_cm', 1.0),
}


class ArduPilotEmulator(Px4Emulator):
    """ArduCopter-like autopilot endpoint for the simulator (see the module docstring).

    Same stepping as :class:`Px4Emulator`: ``update(t_s)``, ``publish_state(t_s, ...)``,
    ``command()``; :attr:`mode` is the ArduCopter mode name, :attr:`custom_mode` its number,
    :attr:`land_complete` ArduCopter's land detector, :attr:`texts` the STATUSTEXT sent.
    ``params`` are the MAVLink side (ports, ids); ``ardupilot`` the firmware's behaviour.
    """

    def __init__(self, params: EmulatorParams | None = None, transport=None,
                 ardupilot: ArduPilotParams | None = None) -> None:
        ap = ardupilot or ArduPilotParams()
        base = params or EmulatorParams()
        super().__init__(EmulatorParams(
            system_id=base.system_id, component_id=base.component_id,
            bind_host=base.bind_host, bind_port=base.bind_port, remote_host=base.remote_host,
            remote_port=base.remote_port, range_min_cm=ap.range_min_cm,
            range_max_cm=ap.range_max_cm, land_speed_mps=ap.land_speed_mps,
            thrust=ap.thrust), transport)
        # ArduCopter's own mode logic (below), not the PX4-like EmulatedAutopilot's: the base
        # class is the wire (transport, parser, signing, telemetry encoding, TIMESYNC)
        self._drives_autopilot = False
        self.ardupilot = ap
        self._armed = False
        self._failsafe = False
        self._setpoint: VehicleCommand | None = None
        self._last_setpoint_s = -math.inf
        self.intervals_s = dict.fromkeys((mavlink.MAVLINK_MSG_ID_HEARTBEAT, *_STREAMS), 0.0)
        self.intervals_s[mavlink.MAVLINK_MSG_ID_HEARTBEAT] = 1.0
        self._next_due = dict.fromkeys(self.intervals_s, -math.inf)
        self.custom_mode = STABILIZE
        self.land_complete = True
        self.texts: list[tuple[int, str]] = []
        self.counters.update({'statustext_tx': 0, 'gcs_failsafes': 0})
        self._raw_thrust = 0.0
        self._use_thrust = False
        self._target_yaw = 0.0
        self._gcs_hb_s: float | None = None
        self._land_since_s: float | None = None     # the land detector's conditions held
        self._complete_since_s: float | None = None
        self._text_id = 0
        self._hovered = False

    # --- the firmware's state ---------------------------------------------------------------

    @property
    def armed(self) -> bool:
        return self._armed

    @armed.setter
    def armed(self, value: bool) -> None:
        self._armed = value

    @property
    def failsafe_active(self) -> bool:
        """The GCS failsafe's LAND / RTL flies (until a mode is set or the vehicle disarms)."""
        return self._failsafe

    @failsafe_active.setter
    def failsafe_active(self, value: bool) -> None:
        self._failsafe = value

    @property
    def setpoint(self) -> VehicleCommand | None:
        """The last decoded SET_ATTITUDE_TARGET (ENU/FLU, newtons)."""
        return self._setpoint

    @setpoint.setter
    def setpoint(self, value: VehicleCommand | None) -> None:
        self._setpoint = value

    @property
    def last_setpoint_s(self) -> float:
        return self._last_setpoint_s

    @last_setpoint_s.setter
    def last_setpoint_s(self, value: float) -> None:
        self._last_setpoint_s = value

    @property
    def kind(self) -> str:
        """What flies the vehicle (:meth:`command`'s kind)."""
        return self.command().kind

    def update(self, t_s: float) -> None:
        """Read and handle every pending packet, then run ArduCopter's mode logic."""
        super().update(t_s)
        if math.isfinite(t_s) and t_s >= self._t_s:
            self._run_logic(t_s)

    @property
    def mode(self) -> str:
        """ArduCopter mode name ('GUIDED_NOGPS', 'LAND', …)."""
        return ARDUCOPTER_MODES.get(self.custom_mode, f'UNKNOWN({self.custom_mode})')

    def statustext(self, severity: int, text: str) -> None:
        """Send ``text`` as ArduPilot does: 50-character MAVLink 2 chunks, one id per text."""
        self.texts.append((severity, text))
        del self.texts[:-50]
        raw = text.encode('ascii', 'replace')
        chunks = [raw[i:i + 50] for i in range(0, len(raw), 50)] or [b'']
        if len(chunks) == 1:
            self.mav.statustext_send(severity, chunks[0])
        else:
            self._text_id = self._text_id % 65535 + 1
            for seq, c in enumerate(chunks):
                self.mav.statustext_send(severity, c, self._text_id, seq)
        self.counters['statustext_tx'] += 1

    def _set_custom_mode(self, mode: int) -> None:
        if mode != self.custom_mode:
            self._target_yaw = self._att[2]
            self._land_since_s = None
            self._complete_since_s = None
        self.custom_mode = mode

    # --- MAVLink in -------------------------------------------------------------------------

    def _handle(self, t_s: float, msg) -> None:
        kind = msg.get_type()
        if kind == 'HEARTBEAT' and msg.get_srcSystem() == self.ardupilot.sysid_mygcs:
            self._gcs_hb_s = t_s
        if kind == 'SET_ATTITUDE_TARGET':
            tgt = self._attitude_target(msg)
            if tgt is None:
                return
            self.last_setpoint_s = t_s
            self._raw_thrust = float(msg.thrust)
            self._use_thrust = bool(self.ardupilot.guid_options & 8)
            self.setpoint = VehicleCommand('offboard', tgt.roll_rad, tgt.pitch_rad,
                                           tgt.yaw_rad, tgt.thrust_n)
            return
        super()._handle(t_s, msg)

    def _handle_command(self, t_s: float, msg) -> None:
        """COMMAND_LONG with ArduCopter 4.5.6's answers: one COMMAND_ACK each; a refusal is
        FAILED (4) with its reason in a STATUSTEXT; an interval for a message it has no
        ap_message for is DENIED (2)."""
        cmd = msg.command
        if cmd == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
            msg_id, interval_us = int(msg.param1), msg.param2
            if msg_id not in self.intervals_s or not math.isfinite(interval_us):
                self.statustext(mavlink.MAV_SEVERITY_INFO, f'No ap_message for mavlink id '
                                f'({msg_id})')
                self._ack(cmd, mavlink.MAV_RESULT_DENIED, msg)
                return
            if interval_us < 0:
                self.intervals_s[msg_id] = 0.0
            elif interval_us == 0:
                self.intervals_s[msg_id] = 1.0 if msg_id == 0 else 0.0
            else:
                self.intervals_s[msg_id] = interval_us * 1e-6
            self._next_due[msg_id] = -math.inf
            self._ack(cmd, mavlink.MAV_RESULT_ACCEPTED, msg)
        elif cmd == mavlink.MAV_CMD_COMPONENT_ARM_DISARM:
            self._arm_disarm(t_s, msg)
        elif cmd == mavlink.MAV_CMD_DO_SET_MODE:
            mode = int(msg.param2)
            if not int(msg.param1) & 1:
                self._ack(cmd, mavlink.MAV_RESULT_FAILED, msg)
            elif mode not in ARDUCOPTER_MODES or mode == 26:
                self.statustext(mavlink.MAV_SEVERITY_WARNING, f'No such mode {mode}')
                self._ack(cmd, mavlink.MAV_RESULT_FAILED, msg)
            elif mode not in _ENTERABLE:
                self.statustext(mavlink.MAV_SEVERITY_WARNING, _REFUSAL_TEXT.get(
                    mode, f'Mode change to {ARDUCOPTER_MODES[mode]} failed: init failed'))
                self._ack(cmd, mavlink.MAV_RESULT_FAILED, msg)
            else:
                self._set_custom_mode(mode)
                self._ack(cmd, mavlink.MAV_RESULT_ACCEPTED, msg)
        else:
            self._ack(cmd, mavlink.MAV_RESULT_UNSUPPORTED, msg)

    def _arm_disarm(self, t_s: float, msg) -> None:
        cmd = msg.command
        if msg.param1 >= 0.5:
            if self.armed:
                self._ack(cmd, mavlink.MAV_RESULT_ACCEPTED, msg)
            elif self.custom_mode in _NOT_ARMABLE:
                self.statustext(mavlink.MAV_SEVERITY_CRITICAL, 'Arm: Mode not armable')
                self._ack(cmd, mavlink.MAV_RESULT_FAILED, msg)
            else:
                self.armed = True
                self.land_complete = True
                self._target_yaw = self._att[2]
                self._hovered = False
                if self.ardupilot.arming_check == 0:
                    self.statustext(mavlink.MAV_SEVERITY_WARNING,
                                    'Warning: Arming Checks Disabled')
                self.statustext(mavlink.MAV_SEVERITY_INFO, 'Arming motors')
                self._ack(cmd, mavlink.MAV_RESULT_ACCEPTED, msg)
        elif not self.armed or self.land_complete or int(msg.param2) == FORCE_DISARM_MAGIC:
            self._disarm()
            self._ack(cmd, mavlink.MAV_RESULT_ACCEPTED, msg)
        else:   # "do not allow disarm via mavlink if we think we are flying" (no text)
            self._ack(cmd, mavlink.MAV_RESULT_FAILED, msg)

    # --- parameters (ArduCopter names; values as floats, never bytewise) -------------------

    def param_table(self) -> dict[str, tuple[int, float]]:
        ap = self.ardupilot
        return {name: (typ, float(getattr(ap, f)) * scale)
                for name, (typ, f, scale) in _PARAMS.items()}

    def _handle_param(self, msg) -> None:
        """PARAM_REQUEST_READ by name (an unknown name is not answered: ANGLE_BOOST) and
        PARAM_SET of the parameters in :data:`_PARAMS`, answered with PARAM_VALUE (value as
        a float, param_index 65535 for a read by name, as ArduCopter does)."""
        name = msg.param_id.rstrip('\x00') if isinstance(msg.param_id, str) else ''
        if name not in _PARAMS:
            return
        typ, fname, scale = _PARAMS[name]
        if msg.get_type() == 'PARAM_SET':
            v = float(msg.param_value) / scale
            current = getattr(self.ardupilot, fname)
            try:
                self.ardupilot = replace(self.ardupilot, **{
                    fname: round(v) if isinstance(current, int) else v})
            except (ValueError, TypeError, OverflowError):
                self.rejected['bad_data'] += 1
        value = float(getattr(self.ardupilot, fname)) * scale
        self.mav.param_value_send(name.encode('ascii'), value, typ, len(_PARAMS), 65535)

    # --- the mode logic ---------------------------------------------------------------------

    def _disarm(self) -> None:
        if self.armed:
            self.statustext(mavlink.MAV_SEVERITY_INFO, 'Disarming motors')
            ap = self.ardupilot
            if ap.hover_learn == 2 and self._hovered:
                # MOT_HOVER_LEARN = 2 saves the learned hover at disarm: the true one here
                self.ardupilot = replace(ap, hover_thrust_norm=round(
                    self.params.thrust.hover_thrust_norm, 4))
        self.armed = False
        self.land_complete = True
        self._land_since_s = None
        self._complete_since_s = None

    def _climb_rate(self) -> float:
        """ArduCopter's reading of SET_ATTITUDE_TARGET.thrust with GUID_OPTIONS bit 3 clear:
        0.5 holds, 1.0 climbs at WPNAV_SPEED_UP, 0.0 descends at WPNAV_SPEED_DN."""
        th = min(max(self._raw_thrust, 0.0), 1.0)
        ap = self.ardupilot
        if th >= 0.5:
            return (th - 0.5) * 2.0 * ap.speed_up_mps
        return (th - 0.5) * 2.0 * ap.speed_down_mps

    def _guided_state(self) -> tuple[str, float]:
        """GUIDED_NOGPS now: ('thrust', 0) flying the setpoint's thrust, ('climb', rate)
        flying its attitude at a climb rate, ('hold', 0) level at climb rate 0 (no setpoint
        yet, or older than GUID_TIMEOUT)."""
        if self.setpoint is None or self._t_s - self.last_setpoint_s > \
                self.ardupilot.guid_timeout_s:
            return 'hold', 0.0
        if self._use_thrust:
            return 'thrust', 0.0
        return 'climb', self._climb_rate()

    def _run_logic(self, t_s: float) -> None:
        ap = self.ardupilot
        if not self.armed:
            return
        # GCS failsafe: the heartbeat of SYSID_MYGCS silent for FS_GCS_TIMEOUT
        if ap.fs_gcs_enable and self._gcs_hb_s is not None and \
                t_s - self._gcs_hb_s > ap.fs_gcs_timeout_s and self.custom_mode != LAND:
            self.counters['gcs_failsafes'] += 1
            self._gcs_hb_s = None
            self.statustext(mavlink.MAV_SEVERITY_WARNING, 'GCS Failsafe')
            if self.land_complete:
                self._disarm()
                return
            self._set_custom_mode(LAND if ap.fs_gcs_enable == 5 else RTL)
            self.failsafe_active = True
        mode = self.custom_mode
        demand_descent = mode == LAND
        climbing = False
        if mode == GUIDED_NOGPS:
            state, rate = self._guided_state()
            climbing = (state == 'thrust' and self._raw_thrust > 0.0) or rate > 0.0
            demand_descent = state == 'climb' and rate < 0.0
        elif mode in _HOLD_MODES or mode == RTL:
            climbing = not self.landed
        if self.land_complete:
            if climbing or not self.landed:
                self.land_complete = False          # take-off
                self._complete_since_s = None
            elif mode == LAND or self.failsafe_active:
                if self._complete_since_s is None:
                    self._complete_since_s = t_s
                if t_s - self._complete_since_s >= ap.land_disarm_s:
                    self._disarm()
                    self.failsafe_active = False
            elif ap.disarm_delay_s > 0.0:
                if self._complete_since_s is None:
                    self._complete_since_s = t_s
                if t_s - self._complete_since_s >= ap.disarm_delay_s:
                    self._disarm()
            return
        # the land detector: resting with the throttle mix at its minimum, which ArduCopter
        # sets only while a descent is demanded (LAND, a negative climb rate) — never in
        # GUIDED_NOGPS on thrust nor in its timeout's altitude hold (measured: 20 s FAILED)
        if self.landed and demand_descent:
            if self._land_since_s is None:
                self._land_since_s = t_s
            if t_s - self._land_since_s >= ap.land_detect_s:
                self.land_complete = True
                self._land_since_s = None
                self._complete_since_s = t_s
        else:
            self._land_since_s = None
            if not self.landed and abs(self._vel[2]) < 0.15 and mode != LAND:
                self._hovered = True

    def _vz_thrust(self, vz_ref: float) -> float:
        roll, pitch, _ = self._att
        cal = self.params.thrust
        accel = cal.gravity_mps2 + self.ardupilot.vz_gain_per_s * (vz_ref - self._vel[2])
        tilt = max(math.cos(roll) * math.cos(pitch), 0.5)
        return min(max(cal.mass_kg * accel / tilt, 0.0), cal.max_thrust_n)

    def command(self) -> VehicleCommand:
        """What the vehicle should fly now (:class:`VehicleCommand`): 'idle' disarmed or
        landed; 'offboard' our setpoint in GUIDED_NOGPS (its thrust, or its attitude at the
        climb rate the thrust field means without GUID_OPTIONS bit 3); 'hold' level at climb
        rate 0 (GUIDED_NOGPS's timeout, the position modes); 'land' / 'failsafe_land' level
        at LAND_SPEED down; 'failsafe_return' (RTL)."""
        _, _, yaw = self._att
        if not self.armed or (self.land_complete and self.landed and
                              self.custom_mode in (LAND, STABILIZE)):
            return VehicleCommand('idle', 0.0, 0.0, yaw, 0.0)
        mode = self.custom_mode
        if mode == GUIDED_NOGPS:
            state, rate = self._guided_state()
            sp = self.setpoint
            if state == 'thrust' and sp is not None:
                return sp
            if state == 'climb' and sp is not None:
                return VehicleCommand('offboard', sp.roll_rad, sp.pitch_rad, sp.yaw_rad,
                                      self._vz_thrust(rate))
            if self.land_complete:
                return VehicleCommand('idle', 0.0, 0.0, yaw, 0.0)
            if sp is not None:
                return VehicleCommand('hold', 0.0, 0.0, sp.yaw_rad, self._vz_thrust(0.0))
            return VehicleCommand('hold', 0.0, 0.0, self._target_yaw, self._vz_thrust(0.0))
        if mode == LAND:
            kind = 'failsafe_land' if self.failsafe_active else 'land'
            return VehicleCommand(kind, 0.0, 0.0, self._target_yaw,
                                  self._vz_thrust(-self.ardupilot.land_speed_mps))
        if mode == RTL:
            return VehicleCommand('failsafe_return', 0.0, 0.0, self._target_yaw,
                                  self._vz_thrust(0.0))
        if self.land_complete and self.landed:
            return VehicleCommand('idle', 0.0, 0.0, yaw, 0.0)
        return VehicleCommand('hold', 0.0, 0.0, self._target_yaw, self._vz_thrust(0.0))

    # --- telemetry as ArduCopter sends it ----------------------------------------------------

    def _send(self, msg_id: int, t_s: float) -> None:
        m = self.mav
        ms = self._time_boot_ms(t_s)
        if msg_id == mavlink.MAVLINK_MSG_ID_HEARTBEAT:
            base = BASE_MODE | (mavlink.MAV_MODE_FLAG_SAFETY_ARMED if self.armed else 0)
            status = mavlink.MAV_STATE_ACTIVE if self.armed else mavlink.MAV_STATE_STANDBY
            m.heartbeat_send(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                             base, self.custom_mode, status)
        elif msg_id == mavlink.MAVLINK_MSG_ID_DISTANCE_SENSOR:
            # the reading as it is: 0 on the ground (below RNGFND1_MIN_CM), the raw value
            # beyond RNGFND1_MAX_CM (947 cm at 9.5 m with a 700 cm maximum, measured)
            ap = self.ardupilot
            r = self._range_m
            cm = (range_m_to_distance_cm(None, ap.range_max_cm) if r is None else
                  max(0, min(round(r * 100.0), 65534)))
            m.distance_sensor_send(ms, ap.range_min_cm, ap.range_max_cm, cm,
                                   mavlink.MAV_DISTANCE_SENSOR_UNKNOWN, 0,
                                   MAV_SENSOR_ROTATION_PITCH_270, 0)
        elif msg_id == mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE:
            landed = (mavlink.MAV_LANDED_STATE_ON_GROUND if not self.armed or self.land_complete
                      else mavlink.MAV_LANDED_STATE_LANDING if self.custom_mode == LAND
                      else mavlink.MAV_LANDED_STATE_IN_AIR)
            m.extended_sys_state_send(mavlink.MAV_VTOL_STATE_UNDEFINED, landed)
        elif msg_id == mavlink.MAVLINK_MSG_ID_ATTITUDE_TARGET:
            c = self.command()
            q = euler_enu_to_quat_ned(c.roll_rad, c.pitch_rad, c.yaw_rad)
            thrust = (self._raw_thrust if c.kind == 'offboard' and self._use_thrust else
                      self.params.thrust.to_norm(c.thrust_n))
            m.attitude_target_send(ms, 0, list(q), 0.0, 0.0, 0.0, thrust)
        else:
            super()._send(msg_id, t_s)
