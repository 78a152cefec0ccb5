"""Pure conversions between the deckland ROS side (ENU/FLU, SI) and MAVLink (NED/FRD, cm, µs).

More in the package README, "Module notes" (`mavlink_bridge.conversions`).
"""

from __future__ import annotations

from dataclasses import dataclass
import math
import struct

from deckland_common.contract import VehicleDescription
from deckland_common.frames import (
    euler_enu_flu_to_ned_frd,
    euler_ned_frd_to_enu_flu,
    euler_to_quaternion,
    frd_to_flu,
    ned_to_enu,
    quaternion_to_euler,
)

Vec3 = tuple[float, float, float]
Quat = tuple[float, float, float, float]

# --- MAVLink numbers used here (common.xml), kept as plain ints so this module stays pure ----
MAV_FRAME_LOCAL_NED = 1
MAV_FRAME_BODY_FRD = 12
MAV_SENSOR_ROTATION_PITCH_270 = 25  # downward-facing
LANDING_TARGET_TYPE_LIGHT_BEACON = 0
MAV_MODE_FLAG_CUSTOM_MODE_ENABLED = 1
MAV_MODE_FLAG_SAFETY_ARMED = 128
MAV_LANDED_STATE_ON_GROUND = 1
MAV_LANDED_STATE_IN_AIR = 2

#: SET_ATTITUDE_TARGET type_mask bits (ATTITUDE_TARGET_TYPEMASK).
IGNORE_ROLL_RATE = 1
IGNORE_PITCH_RATE = 2
IGNORE_YAW_RATE = 4
IGNORE_THRUST = 64
IGNORE_ATTITUDE = 128

_S2 = math.sqrt(0.5)
#: Rotation taking ENU vectors to NED vectors: π about (1, 1, 0)/√2, as a quaternion (w,x,y,z).
Q_NED_FROM_ENU: Quat = (0.0, _S2, _S2, 0.0)
#: Rotation taking FRD body vectors to FLU body vectors: π about body x.
Q_FLU_FROM_FRD: Quat = (0.0, 1.0, 0.0, 0.0)


# --- vectors, Euler angles and quaternions ---------------------------------------------------

def quat_mul(a: Quat, b: Quat) -> Quat:
    """Hamilton product a ⊗ b of quaternions (w, x, y, z)."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return (
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    )


def quat_normalize(q: Quat) -> Quat | None:
    """Unit quaternion with w >= 0, or None when q is not finite or has (near) zero norm."""
    w, x, y, z = q
    n2 = w * w + x * x + y * y + z * z
    if not math.isfinite(n2) or n2 < 1e-12:
        return None
    inv = 1.0 / math.sqrt(n2)
    if w < 0.0:
        inv = -inv
    return w * inv, x * inv, y * inv, z * inv


def quat_enu_flu_to_ned_frd(q: Quat) -> Quat:
    """Attitude quaternion of FLU-in-ENU → attitude quaternion of FRD-in-NED.

    ``q_ned_frd = q_ned←enu ⊗ q_enu_flu ⊗ q_flu←frd``; the result is normalised with w >= 0.
    """
    out = quat_normalize(quat_mul(quat_mul(Q_NED_FROM_ENU, q), Q_FLU_FROM_FRD))
    return out if out is not None else (1.0, 0.0, 0.0, 0.0)


def quat_ned_frd_to_enu_flu(q: Quat) -> Quat:
    """Inverse of :func:`quat_enu_flu_to_ned_frd` (both frame rotations are their own inverse)."""
    out = quat_normalize(quat_mul(quat_mul(Q_NED_FROM_ENU, q), Q_FLU_FROM_FRD))
    return out if out is not None else (1.0, 0.0, 0.0, 0.0)


def euler_enu_to_quat_ned(roll_rad: float, pitch_rad: float, yaw_rad: float) -> Quat:
    """FLU/ENU Z-Y-X Euler → FRD/NED quaternion (w, x, y, z), as SET_ATTITUDE_TARGET wants."""
    r, p, y = euler_enu_flu_to_ned_frd(roll_rad, pitch_rad, yaw_rad)
    return euler_to_quaternion(r, p, y)


def quat_ned_to_euler_enu(q: Quat) -> Vec3:
    """FRD/NED quaternion → FLU/ENU Z-Y-X Euler (roll, pitch, yaw)."""
    qn = quat_normalize(q) or (1.0, 0.0, 0.0, 0.0)
    return euler_ned_frd_to_enu_flu(*quaternion_to_euler(*qn))


def rates_frd_to_flu(p: float, q: float, r: float) -> Vec3:
    """Body rates FRD → FLU (rad/s)."""
    return frd_to_flu(p, q, r)


# --- thrust calibration --------------------------------------------------------------------

#: The paper's vehicle (Table 2): the defaults of every vehicle-dependent number here.
_VEHICLE = VehicleDescription()


@dataclass(frozen=True, slots=True)
class ThrustCalibration:
    """Newtons ↔ normalised collective thrust (SET_ATTITUDE_TARGET.thrust, 0..1).

    Model (the PX4 ``THR_MDL_FAC`` / ArduPilot ``MOT_THST_EXPO`` curve, applied to the collective
    command ``n`` shared by all motors)::

        F(n) = F_max · (e·n² + (1 − e)·n),      0 <= e <= 1

    ``F_max`` (:attr:`max_thrust_n`) is *derived* so that hover, ``F = m·g``, maps exactly to
    :attr:`hover_thrust_norm` (PX4 ``MPC_THR_HOVER``, ArduPilot ``MOT_THST_HOVER``)::

        F_max = m·g / (e·h² + (1 − e)·h)

    Which ``e`` to use: both autopilots already linearise their normalised thrust with their own
    ``THR_MDL_FAC`` / ``MOT_THST_EXPO``. If that parameter matches the propulsion, the normalised
    thrust is proportional to newtons and ``expo = 0`` is right. ``expo > 0`` models the residual
    curvature when the autopilot does *not* linearise (PX4's default ``THR_MDL_FAC = 0`` with
    real props, thrust ∝ ω²). See the README for calibrating ``hover_thrust_norm`` in flight.

    Tilt: ``thrust_n`` is the thrust magnitude along body z (the paper's u_z); PX4 offboard
    attitude control applies it as body thrust without tilt compensation. ArduPilot GUIDED_NOGPS
    boosts it by 1/cos(tilt) unless ``ATC_ANGLE_BOOST = 0`` (the bridge checks that parameter).
    """

    mass_kg: float = _VEHICLE.mass_kg                    # the shared vehicle description
    gravity_mps2: float = _VEHICLE.gravity_mps2
    hover_thrust_norm: float = _VEHICLE.hover_thrust_norm
    expo: float = _VEHICLE.thrust_expo
    norm_min: float = 0.0
    norm_max: float = 1.0

    def __post_init__(self) -> None:
        def bad(field: str, value: float, rule: str) -> None:
            raise ValueError(f'ThrustCalibration.{field} = {value!r}: {rule}')

        for name in ('mass_kg', 'gravity_mps2', 'hover_thrust_norm', 'expo', 'norm_min',
                     'norm_max'):
            v = getattr(self, name)
            if not isinstance(v, (int, float)) or not math.isfinite(v):
                bad(name, v, 'must be a finite number')
        if self.mass_kg <= 0.0:
            bad('mass_kg', self.mass_kg, 'must be > 0')
        if self.gravity_mps2 <= 0.0:
            bad('gravity_mps2', self.gravity_mps2, 'must be > 0')
        if not 0.0 <= self.expo <= 1.0:
            bad('expo', self.expo, 'must be in [0, 1]')
        if not 0.0 <= self.norm_min < self.norm_max <= 1.0:
            bad('norm_min', self.norm_min, 'need 0 <= norm_min < norm_max <= 1')
        if not self.norm_min < self.hover_thrust_norm < self.norm_max:
            bad('hover_thrust_norm', self.hover_thrust_norm,
                'must lie strictly inside (norm_min, norm_max)')

    @classmethod
    def from_vehicle(cls, vehicle: VehicleDescription, **kwargs: float) -> ThrustCalibration:
        """The calibration of a :class:`~deckland_common.contract.VehicleDescription`."""
        return cls(mass_kg=vehicle.mass_kg, gravity_mps2=vehicle.gravity_mps2,
                   hover_thrust_norm=vehicle.hover_thrust_norm, expo=vehicle.thrust_expo,
                   **kwargs)

    @classmethod
    def from_max_thrust(cls, max_thrust_n: float, expo: float,
                        mass_kg: float = _VEHICLE.mass_kg,
                        gravity_mps2: float = _VEHICLE.gravity_mps2,
                        **kwargs: float) -> ThrustCalibration:
        """Build from a measured total maximum thrust (bench test) instead of the hover point."""
        if not (math.isfinite(max_thrust_n) and max_thrust_n > mass_kg * gravity_mps2):
            raise ValueError(f'ThrustCalibration.max_thrust_n = {max_thrust_n!r}: must exceed '
                             f'the weight m·g = {mass_kg * gravity_mps2:.3f} N')
        if not 0.0 <= expo <= 1.0:
            raise ValueError(f'ThrustCalibration.expo = {expo!r}: must be in [0, 1]')
        h = _solve_curve(mass_kg * gravity_mps2 / max_thrust_n, expo)
        return cls(mass_kg=mass_kg, gravity_mps2=gravity_mps2, hover_thrust_norm=h, expo=expo,
                   **kwargs)

    @property
    def hover_thrust_n(self) -> float:
        """Weight m·g (N): the thrust that maps to :attr:`hover_thrust_norm`."""
        return self.mass_kg * self.gravity_mps2

    @property
    def max_thrust_n(self) -> float:
        """Total thrust at normalised 1.0 (N), implied by the hover calibration."""
        h, e = self.hover_thrust_norm, self.expo
        return self.mass_kg * self.gravity_mps2 / (e * h * h + (1.0 - e) * h)

    def to_norm(self, thrust_n: float) -> float:
        """Newtons → normalised thrust, clamped to [norm_min, norm_max]; NaN → norm_min."""
        if not math.isfinite(thrust_n):
            return self.norm_min if thrust_n != math.inf else self.norm_max
        n = _solve_curve(max(thrust_n, 0.0) / self.max_thrust_n, self.expo)
        return min(max(n, self.norm_min), self.norm_max)

    def to_newtons(self, thrust_norm: float) -> float:
        """Normalised thrust → newtons (input clamped to [norm_min, norm_max]; NaN → norm_min)."""
        n = thrust_norm if math.isfinite(thrust_norm) else self.norm_min
        n = min(max(n, self.norm_min), self.norm_max)
        e = self.expo
        return self.max_thrust_n * (e * n * n + (1.0 - e) * n)


def _solve_curve(f: float, e: float) -> float:
    """Positive root n of e·n² + (1 − e)·n = f, in the form that is stable as e → 0."""
    b = 1.0 - e
    return 2.0 * f / (b + math.sqrt(b * b + 4.0 * e * f)) if f > 0.0 else 0.0


# --- SET_ATTITUDE_TARGET -------------------------------------------------------------------

def attitude_target_type_mask(ignore_body_rates: bool = True, ignore_thrust: bool = False,
                              ignore_attitude: bool = False) -> int:
    """SET_ATTITUDE_TARGET.type_mask: bits 1/2/4 ignore roll/pitch/yaw rate, 64 thrust, 128
    attitude."""
    mask = 0
    if ignore_body_rates:
        mask |= IGNORE_ROLL_RATE | IGNORE_PITCH_RATE | IGNORE_YAW_RATE
    if ignore_thrust:
        mask |= IGNORE_THRUST
    if ignore_attitude:
        mask |= IGNORE_ATTITUDE
    return mask


def set_attitude_target_fields(roll_rad: float, pitch_rad: float, yaw_rad: float,
                               thrust_n: float, calib: ThrustCalibration, *,
                               target_system: int = 1, target_component: int = 1,
                               time_boot_ms: int = 0) -> dict:
    """Keyword arguments for pymavlink ``set_attitude_target_send(**fields)``.

    Input attitude is FLU-in-ENU Z-Y-X Euler (the planner's), thrust in newtons (the paper's
    u_z, (16)); output quaternion is FRD-in-NED and thrust normalised by ``calib``.
    """
    return {
        'time_boot_ms': int(time_boot_ms) & 0xFFFFFFFF,
        'target_system': int(target_system),
        'target_component': int(target_component),
        'type_mask': attitude_target_type_mask(),
        'q': list(euler_enu_to_quat_ned(roll_rad, pitch_rad, yaw_rad)),
        'body_roll_rate': 0.0,
        'body_pitch_rate': 0.0,
        'body_yaw_rate': 0.0,
        'thrust': calib.to_norm(thrust_n),
    }


@dataclass(frozen=True, slots=True)
class AttitudeTarget:
    """A decoded SET_ATTITUDE_TARGET on the ROS side (ENU/FLU, newtons)."""

    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    thrust_n: float
    thrust_norm: float
    attitude_valid: bool
    thrust_valid: bool


def decode_attitude_target(q: Quat, thrust_norm: float, type_mask: int,
                           calib: ThrustCalibration) -> AttitudeTarget | None:
    """SET_ATTITUDE_TARGET fields → :class:`AttitudeTarget`; None if a used field is bad."""
    att_ok = not type_mask & IGNORE_ATTITUDE
    thr_ok = not type_mask & IGNORE_THRUST
    roll = pitch = yaw = 0.0
    if att_ok:
        qn = quat_normalize(tuple(q))
        if qn is None:
            return None
        roll, pitch, yaw = euler_ned_frd_to_enu_flu(*quaternion_to_euler(*qn))
    thrust_n = 0.0
    if thr_ok:
        if not math.isfinite(thrust_norm):
            return None
        thrust_n = calib.to_newtons(thrust_norm)
    return AttitudeTarget(roll, pitch, yaw, thrust_n, thrust_norm if thr_ok else 0.0, att_ok,
                          thr_ok)


# --- telemetry -----------------------------------------------------------------------------

def distance_sensor_to_range_m(current_distance_cm: int, min_distance_cm: int,
                               max_distance_cm: int, orientation: int,
                               want_orientation: int = MAV_SENSOR_ROTATION_PITCH_270
                               ) -> float | None:
    """DISTANCE_SENSOR → range in metres, or None (not the downward sensor, or no valid
    return); :func:`distance_sensor_to_rep117` says which kind of invalid."""
    if orientation != want_orientation:
        return None
    r = distance_sensor_to_rep117(current_distance_cm, min_distance_cm, max_distance_cm)
    return r if math.isfinite(r) else None


def distance_sensor_to_rep117(current_distance_cm: int, min_distance_cm: int,
                              max_distance_cm: int) -> float:
    """DISTANCE_SENSOR distances (cm) → ``sensor_msgs/Range.range`` as REP-117 defines it.

    * a reading at or below ``min_distance`` (0 included) is **too close**: ``-inf``. PX4's
      SIH lidar reads 0 cm on the ground (v1.16 SITL, measured); the gear resting on a deck
      is the same case on hardware;
    * a reading beyond ``max_distance`` (ArduPilot sends max + 1 cm, PX4 may send max) or
      UINT16_MAX ("unknown") is **no return**: ``+inf``;
    * PX4 casts ``current_distance`` (float metres × 100) to uint16, so a slightly negative
      simulated reading arrives wrapped (65531 = −5 cm, measured after an SIH landing): a
      value ≥ 0x8000 when ``max_distance`` < 0x8000 cannot be a far reading and is a
      negative one, ``-inf``.
    """
    c, lo, hi = int(current_distance_cm), int(min_distance_cm), int(max_distance_cm)
    if c == 0xFFFF:
        return math.inf
    if 0 < hi < 0x8000 <= c:
        return -math.inf          # a wrapped negative reading
    if c <= 0 or c <= lo:
        return -math.inf
    if hi > 0 and c >= hi:
        return math.inf
    return c * 0.01


def range_m_to_distance_cm(range_m: float | None, max_distance_cm: int) -> int:
    """Range (m) or None → DISTANCE_SENSOR.current_distance (cm); no return → max + 1."""
    if range_m is None or not math.isfinite(range_m) or range_m < 0.0:
        return min(max_distance_cm + 1, 65535)
    return min(round(range_m * 100.0), max_distance_cm + 1, 65535)


#: metres per 1e-7 degree of latitude (ArduPilot's LOCATION_SCALING_FACTOR, flat earth)
LOCATION_SCALING_M = 0.011131884502145034


def parse_llh(text: str) -> tuple[float, float, float] | None:
    """``'lat_deg,lon_deg,alt_m'`` → the tuple; '' → None; anything else: ValueError."""
    if not text.strip():
        return None
    parts = [float(v) for v in text.split(',')]
    if len(parts) != 3 or not all(map(math.isfinite, parts)) or not -90.0 < parts[0] < 90.0 \
            or not -180.0 <= parts[1] <= 180.0:
        raise ValueError(f'{text!r} is not "lat_deg,lon_deg,alt_m"')
    return parts[0], parts[1], parts[2]


def origin_offset_enu(origin_e7: tuple[int, int, int],
                      anchor: tuple[float, float, float]) -> tuple[float, float, float]:
    """Where the autopilot's local-frame origin (GPS_GLOBAL_ORIGIN: lat/lon 1e-7 deg, alt mm)
    lies in a map anchored at ``anchor`` (lat_deg, lon_deg, alt_m), ENU metres, with the flat
    earth ArduPilot's EKF uses for its local frame."""
    lat, lon, alt = anchor
    dn = (origin_e7[0] - round(lat * 1e7)) * LOCATION_SCALING_M
    de = (origin_e7[1] - round(lon * 1e7)) * LOCATION_SCALING_M * \
        math.cos(math.radians(origin_e7[0] * 1e-7))
    return de, dn, origin_e7[2] * 1e-3 - alt


def local_position_ned_to_enu(x: float, y: float, z: float, vx: float, vy: float,
                              vz: float) -> tuple[Vec3, Vec3]:
    """LOCAL_POSITION_NED → (position ENU, velocity ENU)."""
    return ned_to_enu(x, y, z), ned_to_enu(vx, vy, vz)


def attitude_to_enu(roll: float, pitch: float, yaw: float, rollspeed: float, pitchspeed: float,
                    yawspeed: float) -> tuple[Vec3, Vec3]:
    """ATTITUDE (FRD in NED) → ((roll, pitch, yaw) FLU in ENU, body rates FLU)."""
    return (euler_ned_frd_to_enu_flu(roll, pitch, yaw),
            rates_frd_to_flu(rollspeed, pitchspeed, yawspeed))


def imu_frd_to_flu(xacc: float, yacc: float, zacc: float, xgyro: float, ygyro: float,
                   zgyro: float) -> tuple[Vec3, Vec3]:
    """HIGHRES_IMU (FRD, m/s², rad/s) → (specific force FLU, angular rate FLU).

    The accelerometer measures specific force: at rest FRD reads z = −g, FLU reads z = +g
    (REP-145).
    """
    return frd_to_flu(xacc, yacc, zacc), frd_to_flu(xgyro, ygyro, zgyro)


def scaled_imu_to_flu(xacc_mg: int, yacc_mg: int, zacc_mg: int, xgyro_mrad: int,
                      ygyro_mrad: int, zgyro_mrad: int,
                      gravity_mps2: float = 9.80665) -> tuple[Vec3, Vec3]:
    """SCALED_IMU (FRD, milli-g and mrad/s) → (specific force FLU m/s², rate FLU rad/s)."""
    k = gravity_mps2 * 1e-3
    return (frd_to_flu(xacc_mg * k, yacc_mg * k, zacc_mg * k),
            frd_to_flu(xgyro_mrad * 1e-3, ygyro_mrad * 1e-3, zgyro_mrad * 1e-3))


def landed_from_extended_sys_state(landed_state: int) -> bool | None:
    """EXTENDED_SYS_STATE.landed_state → landed (True/False) or None when undefined."""
    if landed_state == MAV_LANDED_STATE_ON_GROUND:
        return True
    if landed_state in (MAV_LANDED_STATE_IN_AIR, 3, 4):  # in air, taking off, landing
        return False
    return None


# --- parameters ----------------------------------------------------------------------------

#: MAV_PARAM_TYPE integer types (UINT8 … INT64); 9 = REAL32, 10 = REAL64
_PARAM_INT_TYPES = {1: '<B', 2: '<b', 3: '<H', 4: '<h', 5: '<I', 6: '<i'}
MAV_PARAM_TYPE_REAL32 = 9


def param_value_from_wire(param_value: float, param_type: int, bytewise: bool) -> float:
    """PARAM_VALUE.param_value → the parameter's value.

    PX4 encodes integer parameters *bytewise* (MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE):
    the int's bytes are sent as the float's bytes, so ``MPC_USE_HTE = 1`` (INT32) arrives as
    1.4e-45 (measured, v1.16 SITL). ArduPilot casts the integer to a float instead
    (``bytewise = False``). A non-finite float parameter stays as it is (the caller rejects
    it)."""
    fmt = _PARAM_INT_TYPES.get(int(param_type))
    if not bytewise or fmt is None:
        return float(param_value)
    raw = struct.pack('<f', param_value)    # (an int like -1 is a NaN pattern: kept as bits)
    return float(struct.unpack(fmt, raw[:struct.calcsize(fmt)])[0])


def param_value_to_wire(value: float, param_type: int, bytewise: bool) -> float:
    """Inverse of :func:`param_value_from_wire` (for the emulated autopilot's PARAM_VALUE)."""
    fmt = _PARAM_INT_TYPES.get(int(param_type))
    if not bytewise or fmt is None:
        return float(value)
    raw = struct.pack(fmt, int(value)).ljust(4, b'\0')
    return float(struct.unpack('<f', raw)[0])


# --- modes ---------------------------------------------------------------------------------

#: PX4 v1.16 ``PX4_CUSTOM_MAIN_MODE`` (px4_custom_mode.h); 9 is reserved (SIMPLE)
PX4_MAIN_MODES = {1: 'MANUAL', 2: 'ALTCTL', 3: 'POSCTL', 4: 'AUTO', 5: 'ACRO', 6: 'OFFBOARD',
                  7: 'STABILIZED', 8: 'RATTITUDE', 10: 'TERMINATION', 11: 'ALTITUDE_CRUISE'}
#: PX4 v1.16 ``PX4_CUSTOM_SUB_MODE_AUTO`` (7 was RTGS, reserved since 2020); 11-18 are the
#: external (ROS 2 / MAVLink-registered) modes 1-8
PX4_AUTO_SUB_MODES = {1: 'READY', 2: 'TAKEOFF', 3: 'LOITER', 4: 'MISSION', 5: 'RTL',
                      6: 'LAND', 7: 'RESERVED', 8: 'FOLLOW_TARGET', 9: 'PRECLAND',
                      10: 'VTOL_TAKEOFF', **{10 + k: f'EXTERNAL{k}' for k in range(1, 9)}}
#: PX4 ``COM_OBL_RC_ACT`` (offboard-loss action) values → names
PX4_OFFBOARD_LOSS_ACTIONS = {0: 'position', 1: 'altitude', 2: 'manual', 3: 'return',
                             4: 'land', 5: 'hold', 6: 'terminate', 7: 'disarm'}
#: ArduCopter 4.5 ``Mode::Number`` (mode.h): 28 TURTLE is new, 13 SPORT was removed in 4.5
#: ("No such mode 13", measured on 4.5.6 SITL), 26 AUTOROTATE exists in helicopter builds only
ARDUCOPTER_MODES = {0: 'STABILIZE', 1: 'ACRO', 2: 'ALT_HOLD', 3: 'AUTO', 4: 'GUIDED',
                    5: 'LOITER', 6: 'RTL', 7: 'CIRCLE', 9: 'LAND', 11: 'DRIFT', 14: 'FLIP',
                    15: 'AUTOTUNE', 16: 'POSHOLD', 17: 'BRAKE', 18: 'THROW', 19: 'AVOID_ADSB',
                    20: 'GUIDED_NOGPS', 21: 'SMART_RTL', 22: 'FLOWHOLD', 23: 'FOLLOW',
                    24: 'ZIGZAG', 25: 'SYSTEMID', 26: 'AUTOROTATE', 27: 'AUTO_RTL',
                    28: 'TURTLE'}


def px4_custom_mode(main_mode: int, sub_mode: int = 0) -> int:
    """PX4 HEARTBEAT.custom_mode: main mode in bits 16-23, sub mode in bits 24-31."""
    return ((main_mode & 0xFF) << 16) | ((sub_mode & 0xFF) << 24)


def px4_mode_name(custom_mode: int) -> str:
    """PX4 HEARTBEAT.custom_mode → 'OFFBOARD', 'POSCTL', 'AUTO.LAND', 'TERMINATION', ...
    ('UNKNOWN(n)' for a main mode PX4 v1.16 does not define, 'AUTO.<n>' for an unknown
    AUTO sub-mode)."""
    main = (custom_mode >> 16) & 0xFF
    sub = (custom_mode >> 24) & 0xFF
    name = PX4_MAIN_MODES.get(main)
    if name is None:
        return f'UNKNOWN({custom_mode})'
    if main == 4:
        return 'AUTO.' + PX4_AUTO_SUB_MODES.get(sub, str(sub))
    return name


def px4_mode_from_name(name: str) -> tuple[int, int]:
    """'OFFBOARD' → (6, 0); 'AUTO.LAND' → (4, 6). Raises ValueError for unknown names."""
    main_by_name = {v: k for k, v in PX4_MAIN_MODES.items()}
    if name.startswith('AUTO.'):
        sub_by_name = {v: k for k, v in PX4_AUTO_SUB_MODES.items()}
        if name[5:] in sub_by_name:
            return 4, sub_by_name[name[5:]]
    elif name in main_by_name:
        return main_by_name[name], 0
    raise ValueError(f'unknown PX4 mode name {name!r}')


def ardupilot_mode_name(custom_mode: int) -> str:
    """ArduCopter HEARTBEAT.custom_mode → 'GUIDED_NOGPS', 'LAND', ... ('UNKNOWN(n)')."""
    return ARDUCOPTER_MODES.get(custom_mode, f'UNKNOWN({custom_mode})')


def ardupilot_mode_from_name(name: str) -> int:
    """'GUIDED_NOGPS' → 20. Raises ValueError for unknown names."""
    for k, v in ARDUCOPTER_MODES.items():
        if v == name:
            return k
    raise ValueError(f'unknown ArduCopter mode name {name!r}')


def mode_name(autopilot: str, custom_mode: int) -> str:
    """Mode name for ``autopilot`` in {'px4', 'ardupilot'}."""
    return px4_mode_name(custom_mode) if autopilot == 'px4' else ardupilot_mode_name(custom_mode)


def do_set_mode_params(autopilot: str, name: str) -> tuple[float, float, float]:
    """(param1, param2, param3) of MAV_CMD_DO_SET_MODE selecting mode ``name``."""
    if autopilot == 'px4':
        main, sub = px4_mode_from_name(name)
        return float(MAV_MODE_FLAG_CUSTOM_MODE_ENABLED), float(main), float(sub)
    return float(MAV_MODE_FLAG_CUSTOM_MODE_ENABLED), float(ardupilot_mode_from_name(name)), 0.0


# --- LANDING_TARGET (optional output) ------------------------------------------------------

def landing_target_px4(time_usec: int, target_position_enu: Vec3) -> dict:
    """LANDING_TARGET for PX4: ``position_valid`` with the target's absolute position in
    MAV_FRAME_LOCAL_NED (keyword arguments for ``landing_target_send``)."""
    x, y, z = (float(v) for v in (target_position_enu[1], target_position_enu[0],
                                  -target_position_enu[2]))
    return {'time_usec': int(time_usec), 'target_num': 0, 'frame': MAV_FRAME_LOCAL_NED,
            'angle_x': 0.0, 'angle_y': 0.0, 'distance': 0.0, 'size_x': 0.0, 'size_y': 0.0,
            'x': x, 'y': y, 'z': z, 'q': [1.0, 0.0, 0.0, 0.0],
            'type': LANDING_TARGET_TYPE_LIGHT_BEACON, 'position_valid': 1}


def landing_target_ardupilot(time_usec: int, rel_position_body_flu: Vec3) -> dict:
    """LANDING_TARGET for ArduPilot (PLND_TYPE = 1): MAV_FRAME_BODY_FRD with the angles of the
    target's line of sight and the distance, plus the FRD offset with ``position_valid``.

    ``rel_position_body_flu`` is target minus vehicle in the body (FLU) frame; the target below
    has z < 0. The angles follow the camera-image convention ArduPilot's AC_PrecLand_Companion
    decodes as the line of sight ``(−tan angle_y, tan angle_x, 1)`` in FRD (image x = right,
    image y = toward the tail): ``angle_x = atan(right/down)``, ``angle_y = atan(−fwd/down)``.
    """
    fx, fy, fz = rel_position_body_flu[0], -rel_position_body_flu[1], -rel_position_body_flu[2]
    dist = math.sqrt(fx * fx + fy * fy + fz * fz)
    depth = max(fz, 1e-6)
    return {'time_usec': int(time_usec), 'target_num': 0, 'frame': MAV_FRAME_BODY_FRD,
            'angle_x': math.atan2(fy, depth), 'angle_y': math.atan2(-fx, depth),
            'distance': dist, 'size_x': 0.0, 'size_y': 0.0, 'x': fx, 'y': fy, 'z': fz,
            'q': [1.0, 0.0, 0.0, 0.0], 'type': LANDING_TARGET_TYPE_LIGHT_BEACON,
            'position_valid': 1}
