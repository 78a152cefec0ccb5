"""deckland's world as PX4's simulator: the Simulator MAVLink API, in lockstep (no rclpy).

More in the package README, "Module notes" (`deck_simulator.px4_hil`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
import math
import random
import select
import socket
import time

from deckland_common.frames import enu_to_ned, flu_to_frd, mat_t_vec, ned_to_enu, rot_body_to_world
from mavlink_bridge.conversions import (
    MAV_SENSOR_ROTATION_PITCH_270,
    euler_enu_to_quat_ned,
    range_m_to_distance_cm,
)
from pymavlink.dialects.v20 import common as mavlink

from deck_simulator.sensor_imu import ImuModel, ImuModelParams, body_rates_from_euler
from deck_simulator.sensor_models import model_streams
from deck_simulator.vehicle import VehicleParams
from deck_simulator.world import World

EARTH_RADIUS_M = 6378137.0            # WGS-84 equatorial radius
# HIL_SENSOR.fields_updated bits PX4's simulator_mavlink reads (SensorSource)
FIELDS_ACCEL, FIELDS_GYRO, FIELDS_MAG, FIELDS_BARO = 0x007, 0x038, 0x1C0, 0x1A00
MAV_MODE_FLAG_SAFETY_ARMED = 128


@dataclass(frozen=True, slots=True)
class HilParams:
    """The simulator side of PX4 SITL; sources of the defaults in the comments."""

    host: str = '127.0.0.1'
    port: int = 4560                          # 4560 + PX4 instance (px4-rc.mavlinksim)
    # PX4 SITL's default home (PX4_HOME_LAT/LON/ALT; Zurich)
    home_lat_deg: float = 47.397742
    home_lon_deg: float = 8.545594
    home_alt_m: float = 488.0
    # Earth field at home, NOAA WMM2025 (approximate; EKF2_MAG_DECL is set to the same
    # declination by px4_params, so the heading is exact whatever the model's error)
    mag_declination_deg: float = 3.3
    mag_inclination_deg: float = 63.6
    mag_strength_gauss: float = 0.481
    imu_rate_hz: float = 250.0                # PX4 IMU_INTEG_RATE 250 for simulation; Gazebo
    mag_rate_hz: float = 100.0                # iris: IMU 250 Hz, mag 100 Hz, baro 50 Hz,
    baro_rate_hz: float = 50.0                # GPS 10 Hz (sitl_gazebo models)
    gps_rate_hz: float = 10.0
    state_rate_hz: float = 50.0               # HIL_STATE_QUATERNION (ground truth)
    #: the raw IMU: the simulator's own model (sensor_imu, ICM-42688-P noise, vibration,
    #: turn-on bias and bias walk), sampled at imu_rate_hz
    imu: ImuModelParams = field(default_factory=ImuModelParams)
    # noise: HMC5883L noise floor 2 mG, MS5611 RMS resolution 0.012 mbar at OSR 4096
    mag_noise_gauss: float = 0.002
    baro_noise_hpa: float = 0.012
    gps_eph_m: float = 0.3                    # reported accuracy (HIL_GPS eph/epv)
    gps_epv_m: float = 0.4
    #: motor thrust F = F_max (e u² + (1 − e) u) for PX4's output u ∈ [0, 1]: a fixed-pitch
    #: prop's static thrust ∝ ω² with ω roughly linear in the ESC command; e = 0.65 is
    #: ArduPilot's MOT_THST_EXPO default (FACTS.md); px4_params sets THR_MDL_FAC = e so PX4
    #: linearises it
    thrust_expo: float = 0.65
    lockstep_timeout_s: float = 1.0           # wall time to wait for PX4's actuator outputs
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ('imu_rate_hz', 'mag_rate_hz', 'baro_rate_hz', 'gps_rate_hz',
                     'state_rate_hz', 'mag_strength_gauss', 'lockstep_timeout_s'):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and math.isfinite(v) and v > 0.0):
                raise ValueError(f'HilParams.{name} = {v!r}: must be a finite number > 0')
        if not isinstance(self.imu, ImuModelParams):
            raise ValueError('HilParams.imu must be an ImuModelParams')
        for name in ('mag_noise_gauss', 'baro_noise_hpa', 'gps_eph_m', 'gps_epv_m'):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and math.isfinite(v) and v >= 0.0):
                raise ValueError(f'HilParams.{name} = {v!r}: must be a finite number >= 0')
        if not 0.0 <= self.thrust_expo <= 1.0:
            raise ValueError(f'HilParams.thrust_expo = {self.thrust_expo!r}: must be in [0, 1]')
        if not 0 <= self.port <= 65535:
            raise ValueError(f'HilParams.port = {self.port!r}: must be a TCP port')
        if not (-90.0 < self.home_lat_deg < 90.0 and -180.0 <= self.home_lon_deg <= 180.0):
            raise ValueError('HilParams.home_lat_deg/home_lon_deg: not a position on Earth')


def px4_params(vehicle: VehicleParams, hil: HilParams | None = None, *,
               takeoff_alt_m: float = 2.0, offboard_loss_timeout_s: float = 1.0) -> dict:
    """PX4 parameters (for :class:`deckland.sitl.px4.Px4Sitl`) that make PX4's none_iris the
    simulated vehicle.

    PX4 has no mass parameter for a multicopter: it sees mass and thrust as the normalised
    hover thrust ``MPC_THR_HOVER = 1 / (T/W)`` (exact with ``THR_MDL_FAC`` = the simulated
    thrust curve, which PX4 then inverts). Geometry: the paper's plus configuration, motor 1
    on the nose (rotor 0 in PX4's numbering), 2 left, 3 tail, 4 right, at ``arm_length_m``
    (FRD positions), spinning as (1) says: u_ψ = c_d(−F1+F2−F3+F4) in FLU, so 1 and 3 turn
    CCW (``CA_ROTORn_KM = +c_d``), 2 and 4 CW (−c_d); ``CA_ROTORn_CT`` = the motor's
    maximum thrust. No RC (``COM_RC_IN_MODE = 4``); offboard loss → Land
    (``COM_OBL_RC_ACT = 4``); the range sensor is not fused into EKF2's height
    (``EKF2_RNG_CTRL = 0``: over a heaving deck it would move the height estimate; PX4 still
    streams it to the companion); the declination is the simulated field's.
    """
    hil = hil or HilParams()
    L, cd = vehicle.arm_length_m, vehicle.yaw_moment_coeff_m
    geom = ((L, 0.0, cd), (0.0, -L, -cd), (-L, 0.0, cd), (0.0, L, -cd))
    p: dict = {'CA_AIRFRAME': 0, 'CA_ROTOR_COUNT': 4}
    for i, (px, py, km) in enumerate(geom):
        p[f'CA_ROTOR{i}_PX'] = px
        p[f'CA_ROTOR{i}_PY'] = py
        p[f'CA_ROTOR{i}_KM'] = km
        p[f'CA_ROTOR{i}_CT'] = round(vehicle.motor_max_n, 4)
    p.update({
        'THR_MDL_FAC': hil.thrust_expo,
        'MPC_THR_HOVER': round(1.0 / vehicle.thrust_to_weight, 4),
        'COM_RC_IN_MODE': 4,
        'COM_OBL_RC_ACT': 4,
        'COM_OF_LOSS_T': offboard_loss_timeout_s,
        'MIS_TAKEOFF_ALT': takeoff_alt_m,
        'EKF2_RNG_CTRL': 0,
        'EKF2_DECL_TYPE': 0,
        'EKF2_MAG_DECL': hil.mag_declination_deg,
    })
    return p


class TcpServerLink:
    """The simulator's TCP endpoint: listens on ``(host, port)``, one peer (PX4)."""

    def __init__(self, host: str, port: int) -> None:
        self.server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            self.server.bind((host, port))
            self.server.listen(1)
        except OSError:
            self.server.close()
            raise
        self.conn: socket.socket | None = None

    def accept(self, timeout_s: float) -> bool:
        """Wait up to ``timeout_s`` for PX4 to connect; True once connected."""
        if self.conn is not None:
            return True
        r, _, _ = select.select([self.server], [], [], timeout_s)
        if not r:
            return False
        self.conn, _ = self.server.accept()
        self.conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        return True

    def write(self, data: bytes) -> None:
        if self.conn is not None:
            self.conn.sendall(data)

    def receive(self, timeout_s: float) -> bytes:
        """Bytes available within ``timeout_s`` (b'' when none; ConnectionError when PX4
        closed the connection)."""
        if self.conn is None:
            return b''
        r, _, _ = select.select([self.conn], [], [], max(timeout_s, 0.0))
        if not r:
            return b''
        data = self.conn.recv(65536)
        if not data:
            raise ConnectionError('PX4 closed the simulator connection')
        return data

    def close(self) -> None:
        for s in (self.conn, self.server):
            if s is not None:
                s.close()
        self.conn = None


class Px4Hil:
    """PX4 in the loop as the world's autopilot: sensors out, motor outputs in, lockstep.

    An :class:`~deck_simulator.autopilot.Autopilot` like the emulated one: the constructor
    attaches it to ``world``, and :meth:`tick` runs at the start of every physics sub-step
    (``World.step``). When a lockstep period (``1 / imu_rate_hz``, a whole number of physics
    sub-steps) is due it sends the sensors at ``world.t_s`` and waits for PX4's
    HIL_ACTUATOR_CONTROLS answering them, which set the motor thrusts the sub-steps of the
    period fly. Until PX4's first actuator message the world is not held back (PX4 boots on
    our clock); afterwards each period waits up to ``lockstep_timeout_s`` (wall) for PX4's
    answer to it (a timeout is counted, the last outputs kept). ``start_on_ground`` puts the
    vehicle at rest on the ground below its start (motors off), for PX4's own take-off.
    PX4's failsafes are PX4's: it reports them over MAVLink, not on this link
    (:attr:`failsafe` is None).
    """

    failsafe = None          # PX4's failsafe state is on its MAVLink links, not this one

    def __init__(self, world: World, params: HilParams | None = None, link=None,
                 start_on_ground: bool = True) -> None:
        self.world = world
        self.params = p = params or HilParams()
        self.period_s = 1.0 / p.imu_rate_hz
        ratio = self.period_s / world.physics_dt_s
        if abs(ratio - round(ratio)) > 1e-6 or round(ratio) < 1:
            raise ValueError(
                f'HilParams.imu_rate_hz = {p.imu_rate_hz:g}: the lockstep period must be a '
                f'whole number of physics steps ({world.physics_dt_s * 1e3:g} ms; e.g. a '
                'physics rate of 500 Hz for 250 Hz)')
        self.link = link if link is not None else TcpServerLink(p.host, p.port)
        self.mav = mavlink.MAVLink(self.link, srcSystem=1, srcComponent=51)
        self.mav.robust_parsing = True
        self.rx = mavlink.MAVLink(None)
        self.rx.robust_parsing = True
        self._next_s = world.t_s
        self._due = {'mag': 0.0, 'baro': 0.0, 'gps': 0.0, 'state': 0.0, 'range': 0.0}
        self._periods = {'mag': 1.0 / p.mag_rate_hz, 'baro': 1.0 / p.baro_rate_hz,
                         'gps': 1.0 / p.gps_rate_hz, 'state': 1.0 / p.state_rate_hz,
                         'range': 1.0 / world.scenario.sensors.lidar.timing.rate_hz}
        self._rng = {k: random.Random(f'{world.seed}:px4_hil:{p.seed}:{k}')
                     for k in ('mag', 'baro')}
        self.imu = ImuModel(p.imu, model_streams(world.seed, f'px4_hil:{p.seed}:imu'),
                            self.period_s, world.params.gravity_mps2)
        d, i = math.radians(p.mag_declination_deg), math.radians(p.mag_inclination_deg)
        f = p.mag_strength_gauss
        self._mag_enu = ned_to_enu(f * math.cos(i) * math.cos(d), f * math.cos(i) * math.sin(d),
                                   f * math.sin(i))
        self._mag_frd = (0.0, 0.0, 0.0)
        self._baro = (1013.25, 0.0, 15.0)
        vp = world.params
        self._fmax = vp.motor_max_n
        self.controls: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
        self.active = True
        self.armed = False
        self.failsafes = 0
        self.got_first_controls = False
        self._last_controls_us = -1
        self.counters = {'periods': 0, 'controls_rx': 0, 'lockstep_timeouts': 0,
                         'heartbeats_rx': 0, 'messages_tx': 0}
        self.rejected = {'bad_data': 0, 'nan': 0}
        self.wait_wall_s = 0.0          # wall time spent waiting for PX4 (lockstep)
        if start_on_ground:
            self._place_on_ground()
        world.vehicle.set_motor_thrusts(0.0, 0.0, 0.0, 0.0)
        world.attach_autopilot(self)

    # --- set-up --------------------------------------------------------------------------

    def _place_on_ground(self) -> None:
        """Rest on the ground (or the deck) below the start until the thrust lifts it (the
        touchdown monitor watches from the lift-off on: no touchdown at t0)."""
        self.world.place_on_surface()

    def accept(self, timeout_s: float) -> bool:
        """Wait for PX4's connection (it retries every 0.5 ms while booting)."""
        return self.link.accept(timeout_s)

    def close(self) -> None:
        self.link.close()

    # --- the lockstep ----------------------------------------------------------------------

    def tick(self, t_s: float, world: World) -> None:
        """Every physics sub-step at ``t_s`` (before the physics): the lockstep exchange when
        a period is due. PX4 closing the connection raises ConnectionError."""
        if t_s + 1e-9 < self._next_s:
            return
        self._next_s += self.period_s
        if self._next_s <= t_s + 1e-9:     # the world was stepped past whole periods
            self._next_s = t_s + self.period_s
        self._exchange()

    def time_usec(self) -> int:
        """PX4's clock: the world's time (µs), from 1 s (PX4 treats 0 as "never")."""
        return round((self.world.t_s + 1.0) * 1e6)

    def _exchange(self) -> None:
        t_us = self.time_usec()
        self._send_sensors(t_us)
        if self.got_first_controls:
            t0 = time.monotonic()
            end = t0 + self.params.lockstep_timeout_s
            while self._last_controls_us < t_us:
                left = end - time.monotonic()
                if left <= 0.0:
                    self.counters['lockstep_timeouts'] += 1
                    break
                self._read(left)
            self.wait_wall_s += time.monotonic() - t0
        else:
            self._read(0.0)
        self.counters['periods'] += 1

    def _read(self, timeout_s: float) -> None:
        data = self.link.receive(timeout_s)
        if not data:
            return
        try:
            msgs = self.rx.parse_buffer(data) or []
        except Exception:    # pymavlink raises on some malformed input even when robust
            self.rejected['bad_data'] += 1
            return
        for m in msgs:
            kind = m.get_type()
            if kind == 'HIL_ACTUATOR_CONTROLS':
                self._on_controls(m)
            elif kind == 'HEARTBEAT':
                self.counters['heartbeats_rx'] += 1
            elif kind == 'BAD_DATA':
                self.rejected['bad_data'] += 1

    def _on_controls(self, m) -> None:
        u = tuple(m.controls[:4])
        if not all(map(math.isfinite, u)):
            self.rejected['nan'] += 1
            return
        self.counters['controls_rx'] += 1
        self.got_first_controls = True
        self._last_controls_us = max(self._last_controls_us, int(m.time_usec))
        self.armed = bool(m.mode & MAV_MODE_FLAG_SAFETY_ARMED)
        e, fmax = self.params.thrust_expo, self._fmax
        f = [fmax * (e * c * c + (1.0 - e) * c) if c > 0.0 else 0.0
             for c in (min(max(x, 0.0), 1.0) for x in u)] if self.armed else [0.0] * 4
        self.controls = (u[0], u[1], u[2], u[3]) if self.armed else (0.0, 0.0, 0.0, 0.0)
        # PX4 rotor i = deckland motor i + 1 (px4_params: nose, left, tail, right)
        self.world.vehicle.set_motor_thrusts(f[0], f[1], f[2], f[3])

    # --- sensors -------------------------------------------------------------------------

    def _due_now(self, name: str, t: float) -> bool:
        if t + 1e-9 < self._due[name]:
            return False
        nxt = self._due[name] + self._periods[name]
        self._due[name] = nxt if nxt > t + 1e-9 else t + self._periods[name]
        return True

    def _send_sensors(self, t_us: int) -> None:
        w, p = self.world, self.params
        t = w.t_s
        v = w.vehicle
        r = rot_body_to_world(v.roll, v.pitch, v.yaw)
        rm, rb = self._rng['mag'], self._rng['baro']
        # specific force in the body (REP-145: +g up at rest) and body rates, measured by the
        # simulator's IMU model; FRD for PX4
        f, w_b = self.imu.sample((v.ax, v.ay, v.az), r, body_rates_from_euler(
            v.roll, v.pitch, v.roll_rate, v.pitch_rate, v.yaw_rate))
        ax, ay, az = flu_to_frd(*f)
        gx, gy, gz = flu_to_frd(*w_b)
        fields = FIELDS_ACCEL | FIELDS_GYRO
        if self._due_now('mag', t):
            bx, by, bz = flu_to_frd(*mat_t_vec(r, self._mag_enu))
            s = p.mag_noise_gauss
            self._mag_frd = (bx + rm.gauss(0.0, s), by + rm.gauss(0.0, s), bz + rm.gauss(0.0, s))
            fields |= FIELDS_MAG
        if self._due_now('baro', t):
            h = p.home_alt_m + v.z
            pressure = 1013.25 * (1.0 - 2.25577e-5 * h) ** 5.25588      # ISA troposphere
            self._baro = (pressure + rb.gauss(0.0, p.baro_noise_hpa), h, 15.0 - 0.0065 * h)
            fields |= FIELDS_BARO
        mx, my, mz = self._mag_frd
        pa, alt, temp = self._baro
        self.mav.hil_sensor_send(t_us, ax, ay, az, gx, gy, gz, mx, my, mz, pa, 0.0, alt, temp,
                                 fields, 0)
        self.counters['messages_tx'] += 1
        if self._due_now('gps', t):
            self._send_gps(t_us)
        if self._due_now('state', t):
            self._send_state(t_us)
        if self._due_now('range', t):
            lp = w.scenario.sensors.lidar
            max_cm = round(lp.max_range_m * 100.0)
            self.mav.distance_sensor_send(
                int(t_us // 1000) & 0xFFFFFFFF, round(lp.min_range_m * 100.0), max_cm,
                range_m_to_distance_cm(w.read_lidar(), max_cm),
                mavlink.MAV_DISTANCE_SENSOR_LASER, 0, MAV_SENSOR_ROTATION_PITCH_270, 0)
            self.counters['messages_tx'] += 1

    def _lat_lon(self, x_east_m: float, y_north_m: float) -> tuple[int, int]:
        p = self.params
        lat = p.home_lat_deg + math.degrees(y_north_m / EARTH_RADIUS_M)
        lon = p.home_lon_deg + math.degrees(
            x_east_m / (EARTH_RADIUS_M * math.cos(math.radians(p.home_lat_deg))))
        return round(lat * 1e7), round(lon * 1e7)

    def _send_gps(self, t_us: int) -> None:
        """HIL_GPS from deckland's GPS model (its bias, noise and faults)."""
        p = self.params
        (x, y, z), (vx, vy, vz) = self.world.read_local_position()
        lat, lon = self._lat_lon(x, y)
        vn, ve, vd = enu_to_ned(vx, vy, vz)
        cog = (round(math.degrees(math.atan2(ve, vn)) * 100.0) % 36000
               if math.hypot(vn, ve) > 0.2 else 65535)
        self.mav.hil_gps_send(t_us, 3, lat, lon, round((p.home_alt_m + z) * 1000.0),
                              round(p.gps_eph_m * 100.0), round(p.gps_epv_m * 100.0),
                              round(math.hypot(vn, ve) * 100.0), round(vn * 100.0),
                              round(ve * 100.0), round(vd * 100.0), cog, 12, 0, 0)
        self.counters['messages_tx'] += 1

    def _send_state(self, t_us: int) -> None:
        """HIL_STATE_QUATERNION: the truth (PX4 publishes it as its *_groundtruth topics)."""
        v, p = self.world.vehicle, self.params
        q = euler_enu_to_quat_ned(v.roll, v.pitch, v.yaw)
        wx, wy, wz = flu_to_frd(*body_rates_from_euler(v.roll, v.pitch, v.roll_rate,
                                                       v.pitch_rate, v.yaw_rate))
        lat, lon = self._lat_lon(v.x, v.y)
        vn, ve, vd = enu_to_ned(v.vx, v.vy, v.vz)
        an, ae, ad = enu_to_ned(v.ax, v.ay, v.az)
        k = 1000.0 / 9.80665

        def i16(x: float) -> int:
            return max(-32768, min(32767, round(x)))

        self.mav.hil_state_quaternion_send(
            t_us, list(q), wx, wy, wz, lat, lon, round((p.home_alt_m + v.z) * 1000.0),
            i16(vn * 100.0), i16(ve * 100.0), i16(vd * 100.0), 0, 0, i16(an * k), i16(ae * k),
            i16(ad * k))
        self.counters['messages_tx'] += 1
