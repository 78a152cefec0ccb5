"""deckland's world as ArduPilot's physics: the SITL JSON backend, in lockstep (no rclpy).

ArduCopter SITL started with ``--model JSON`` sends, for each physics step it wants
(``SIM_RATE_HZ``), a servo packet (magic 18458, frame rate, frame count, 16 PWM µs) to UDP 9002
+ 10 × instance and waits for one compact JSON line back: IMU in body FRD, NED position and
velocity from home, attitude, ``rng_1``. :class:`ArduPilotJson` is that physics: motors 1-4
(ArduCopter's PLUSREV frame, deckland's plus with its spin directions) go through ArduPilot's
own thrust curve to ``Vehicle.set_motor_thrusts`` (the motor lag follows); deck, contact, camera
and lidar stay the world's. :func:`ardupilot_params` makes ArduCopter see the paper's vehicle.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass, field
import math
import select
import socket
import struct
import time

from deckland_common.frames import enu_to_ned, flu_to_frd, rot_body_to_world
from mavlink_bridge.conversions import euler_enu_to_quat_ned

from deck_simulator.sensor_imu import ImuModel, ImuModelParams, body_rates_from_euler
from deck_simulator.sensor_models import model_streams
from deck_simulator.vehicle import VehicleParams
from deck_simulator.world import World

SERVO_MAGIC_16, SERVO_MAGIC_32 = 18458, 29569      # SIM_JSON.h: 16 and 32 channels
_SERVO_16 = struct.Struct('<HHI16H')                # 40 bytes
_SERVO_32 = struct.Struct('<HHI32H')                # 72 bytes
#: ArduCopter FRAME_TYPE 6, PLUSREV ("plus with reversed motor directions", AP_MotorsMatrix):
#: motor 1 right CW, 2 left CW, 3 front CCW, 4 back CCW — deckland's plus of (1): 1 nose, 2
#: left, 3 tail, 4 right, 1/3 CCW and 2/4 CW (u_ψ = c_d(−F1+F2−F3+F4)). FRAME_TYPE 0 (PLUS)
#: has the spin directions the other way round (its yaw would diverge here), 1 (X) puts the
#: motors at 45°. deckland motor i is driven by ArduCopter output channel PLUSREV_CHANNEL[i].
FRAME_TYPE_PLUSREV = 6
PLUSREV_CHANNEL = (2, 1, 3, 0)
#: SITL home for the JSON physics: ArduPilot's CMAC location at sea level (a ship's deck).
#: ArduCopter scales its thrust by 1 / (air density ratio) from the barometer; at sea level
#: with ``BARO_GND_TEMP`` = 15 °C (ISA) that ratio is 1, so the simulated motors need no
#: density term (measured: open-loop hover at MOT_THST_HOVER 0.9994 g; at 584 m / SITL's
#: 27 °C the same thrust gave 1.107 g)
SEA_LEVEL_HOME = (-35.363261, 149.165230, 0.0, 0.0)


@dataclass(frozen=True, slots=True)
class JsonParams:
    """The physics side of ArduCopter SITL's JSON backend; sources of the defaults."""

    host: str = '127.0.0.1'
    port: int = 9002                          # 9002 + 10 × instance (SIM_JSON)
    # the motor outputs as ArduCopter's defaults drive them (MOT_PWM_MIN/MAX from RC3 in
    # copter.parm, MOT_SPIN_MIN/MAX, MOT_THST_EXPO): a = (pwm − min) / (max − min), and the
    # thrust F = F_max (e t² + (1 − e) t) with t = (a − spin_min) / (spin_max − spin_min) — the
    # curve ArduCopter inverts, so its normalised thrust is linear in newtons
    pwm_min_us: int = 1000
    pwm_max_us: int = 2000
    spin_min: float = 0.15
    spin_max: float = 0.95
    thrust_expo: float = 0.65
    #: the IMU (ICM-42688-P noise, vibration, biases), sampled at the frame rate
    imu: ImuModelParams = field(default_factory=ImuModelParams)
    lockstep_timeout_s: float = 1.0           # wall time to wait for ArduCopter's next frame
    max_frame_gap: int = 100                  # frames skipped that are still integrated
    max_silent_frames: int = 5                # tick mode: timeouts in a row = ArduCopter gone
    seed: int = 0

    def __post_init__(self) -> None:
        if not 0 <= self.port <= 65535:
            raise ValueError(f'JsonParams.port = {self.port!r}: must be a UDP port')
        if not 0 < self.pwm_min_us < self.pwm_max_us <= 3000:
            raise ValueError(f'JsonParams.pwm_min_us/pwm_max_us = {self.pwm_min_us}/'
                             f'{self.pwm_max_us}: need 0 < min < max <= 3000')
        if not 0.0 <= self.spin_min < self.spin_max <= 1.0:
            raise ValueError(f'JsonParams.spin_min/spin_max = {self.spin_min}/'
                             f'{self.spin_max}: need 0 <= min < max <= 1')
        if not 0.0 <= self.thrust_expo <= 1.0:
            raise ValueError(f'JsonParams.thrust_expo = {self.thrust_expo!r}: must be in '
                             '[0, 1]')
        v = self.lockstep_timeout_s
        if not (isinstance(v, int | float) and math.isfinite(v) and v > 0.0):
            raise ValueError(f'JsonParams.lockstep_timeout_s = {v!r}: must be a finite '
                             'number > 0')
        if isinstance(self.max_frame_gap, bool) or not isinstance(self.max_frame_gap, int) \
                or self.max_frame_gap < 1:
            raise ValueError(f'JsonParams.max_frame_gap = {self.max_frame_gap!r}: must be an '
                             'integer >= 1')
        if isinstance(self.max_silent_frames, bool) or \
                not isinstance(self.max_silent_frames, int) or self.max_silent_frames < 1:
            raise ValueError(f'JsonParams.max_silent_frames = {self.max_silent_frames!r}: '
                             'must be an integer >= 1')
        if not isinstance(self.imu, ImuModelParams):
            raise ValueError('JsonParams.imu must be an ImuModelParams')


def ardupilot_params(vehicle: VehicleParams, lidar_min_m: float, lidar_max_m: float,
                     json: JsonParams | None = None) -> dict[str, float]:
    """ArduCopter parameters (for :class:`deckland.sitl.ardupilot.ArduPilotSitl`) that make it
    fly the simulated vehicle as the paper's.

    ArduCopter has no mass parameter: it sees mass and thrust as ``MOT_THST_HOVER = 1 / (T/W)``,
    exact because ``MOT_THST_EXPO`` / ``MOT_SPIN_*`` / ``MOT_PWM_*`` are the simulated thrust
    curve (which ArduCopter then inverts) and the battery compensation is off
    (``MOT_BAT_VOLT_MAX = 0``: the simulated motors do not sag); hover learning off, so the
    value stays the truth; the air-density compensation is 1 at :data:`SEA_LEVEL_HOME` with
    ``BARO_GND_TEMP`` = 15 °C. Frame: quad PLUSREV (:data:`PLUSREV_CHANNEL`). The lidar is
    ArduCopter's rangefinder 1 (SITL type 100 reads ``rng_1``), downward, with the LidarLite's
    limits; its height is not fused (EK3's default: over a heaving deck it would move the
    height estimate; ArduCopter still streams it to the companion)."""
    j = json or JsonParams()
    return {
        'FRAME_CLASS': 1, 'FRAME_TYPE': FRAME_TYPE_PLUSREV,
        'MOT_PWM_MIN': j.pwm_min_us, 'MOT_PWM_MAX': j.pwm_max_us,
        'MOT_SPIN_MIN': j.spin_min, 'MOT_SPIN_MAX': j.spin_max,
        'MOT_THST_EXPO': j.thrust_expo, 'MOT_BAT_VOLT_MAX': 0.0,
        'MOT_THST_HOVER': round(1.0 / vehicle.thrust_to_weight, 4), 'MOT_HOVER_LEARN': 0,
        'BARO_GND_TEMP': 15.0,
        'RNGFND1_TYPE': 100, 'RNGFND1_ORIENT': 25,
        'RNGFND1_MIN_CM': max(1, round(lidar_min_m * 100.0)),
        'RNGFND1_MAX_CM': round(lidar_max_m * 100.0),
    }


class UdpServoLink:
    """The physics' UDP endpoint: bound to ``(host, port)``, answers each servo packet's
    source address."""

    def __init__(self, host: str, port: int) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self.sock.bind((host, port))
        except OSError:
            self.sock.close()
            raise
        self.sock.setblocking(False)
        self.peer: tuple[str, int] | None = None

    def receive(self, timeout_s: float) -> bytes | None:
        """The next datagram within ``timeout_s`` (None when none came)."""
        r, _, _ = select.select([self.sock], [], [], max(timeout_s, 0.0))
        if not r:
            return None
        try:
            data, self.peer = self.sock.recvfrom(256)
        except (BlockingIOError, InterruptedError):
            return None
        except OSError:
            return None
        return data

    def send(self, data: bytes) -> None:
        if self.peer is not None:
            with contextlib.suppress(OSError):
                self.sock.sendto(data, self.peer)

    def close(self) -> None:
        self.sock.close()


def pwm_to_thrust(pwm_us: int, json: JsonParams, motor_max_n: float) -> float:
    """One motor's thrust (N) for its output PWM (µs) through the curve ArduCopter inverts;
    0 below spin-min (spin-arm idles the props) and for an output that is off (0 µs)."""
    a = (pwm_us - json.pwm_min_us) / (json.pwm_max_us - json.pwm_min_us)
    t = (a - json.spin_min) / (json.spin_max - json.spin_min)
    if not t > 0.0:
        return 0.0
    if t > 1.0:
        t = 1.0
    e = json.thrust_expo
    return motor_max_n * (e * t * t + (1.0 - e) * t)


class ArduPilotJson:
    """ArduCopter in the loop as the world's autopilot: servo PWM in, sensors out, lockstep.

    Two ways to drive it: as the world's :class:`~deck_simulator.autopilot.Autopilot`
    (:meth:`accept` once, then the world's steps :meth:`tick` it, as ``px4_hil.Px4Hil``), or
    :meth:`step` with a time step from a lockstep thread of one's own. Each servo frame
    ArduCopter sends: PWM → motor thrusts, the world steps by a frame period, and the answer
    (stamped with the world's time, which is ArduCopter's clock) goes back; a frame sent again
    (ArduCopter resends after ~1 s without an answer) gets the same answer again, a frame
    count going back is a reboot. :attr:`armed` is
    inferred from the outputs (ArduCopter idles armed motors at ``MOT_SPIN_ARM``, above
    ``MOT_PWM_MIN``). ``start_on_ground`` rests the vehicle on the surface below its start.
    """

    def __init__(self, world: World, params: JsonParams | None = None, link=None,
                 start_on_ground: bool = True) -> None:
        self.world = world
        self.params = p = params or JsonParams()
        self.link = link if link is not None else UdpServoLink(p.host, p.port)
        self.armed = False
        self.frame_rate_hz = 0.0
        self.frame_count = -1
        self.pwm: tuple[int, ...] = ()
        self.counters = {'frames': 0, 'answers': 0, 'repeats': 0, 'resets': 0,
                         'lockstep_timeouts': 0, 'skipped_frames': 0}
        self.rejected = {'bad_data': 0, 'nan': 0}
        self.wait_wall_s = 0.0
        self._pending_s = 0.0
        self._answer = b''
        self._imu: ImuModel | None = None
        self._range_due = 0.0
        self._range_m = -1.0
        self._range_period = 1.0 / world.scenario.sensors.lidar.timing.rate_hz
        self._fmax = world.params.motor_max_n
        # the world's Autopilot protocol (tick mode: the simulator loop steps the world)
        self.active = True
        self.failsafes = 0
        self._next_s = 0.0
        self._answer_due = False
        self._silent = 0
        if start_on_ground:
            world.place_on_surface()
        world.vehicle.set_motor_thrusts(0.0, 0.0, 0.0, 0.0)

    # --- connection and the step() mode ---------------------------------------------------------

    def accept(self, timeout_s: float) -> bool:
        """Wait up to ``timeout_s`` for ArduCopter's first servo frame (and answer it)."""
        if self.frame_count >= 0:
            return True
        end = time.monotonic() + timeout_s
        while self.frame_count < 0:
            left = end - time.monotonic()
            if left <= 0.0:
                return False
            if self._receive(left):
                self._answer_due = True      # answered by the first step / tick
        return True

    def step(self, dt_s: float) -> int:
        """Advance the world by ``dt_s`` on ArduCopter's frames; returns the frames run (fewer
        when ArduCopter stopped sending for ``lockstep_timeout_s``, counted)."""
        if not (isinstance(dt_s, int | float) and math.isfinite(dt_s) and dt_s >= 0.0):
            self.rejected['nan'] += 1
            return 0
        self._pending_s += dt_s
        n = 0
        t0 = time.monotonic()
        if self._answer_due and self._pending_s > 1e-9:     # the frame accept() took
            dt = 1.0 / self.frame_rate_hz
            self.world.step(dt)
            self.counters['frames'] += 1
            self._send_answer()
            self._pending_s -= dt
            n += 1
        while self._pending_s > 1e-9:
            advanced = self._frame(self.params.lockstep_timeout_s)
            if advanced is None:
                self.counters['lockstep_timeouts'] += 1
                self._pending_s = 0.0
                break
            self._pending_s -= advanced
            n += 1 if advanced > 0.0 else 0
        self._pending_s = max(self._pending_s, 0.0)
        self.wait_wall_s += time.monotonic() - t0
        return n

    def close(self) -> None:
        self.link.close()

    # --- one frame -----------------------------------------------------------------------

    def _frame(self, timeout_s: float) -> float | None:
        """Handle one servo packet and step the world (:meth:`step`'s mode); the physics
        time it advanced (0 for a repeat or a bad packet), None when none came within
        ``timeout_s``."""
        frames = self._receive(timeout_s)
        if not frames:
            return frames
        dt = frames / self.frame_rate_hz
        self.world.step(dt)
        self.counters['frames'] += 1
        self._send_answer()
        return dt

    def _send_answer(self) -> None:
        self._answer = self._state()
        self.link.send(self._answer)
        self.counters['answers'] += 1
        self._answer_due = False

    def _receive(self, timeout_s: float) -> int | None:
        """One servo packet: its PWM applied to the motors; the frames it advances (0 for a
        repeat, answered again, or a bad packet), None when none came within ``timeout_s``."""
        data = self.link.receive(timeout_s)
        if data is None:
            return None
        parsed = self._parse(data)
        if parsed is None:
            self.rejected['bad_data'] += 1
            return 0
        rate, count, pwm = parsed
        if count == self.frame_count:
            self.counters['repeats'] += 1            # our answer was lost: the same again
            if self._answer:
                self.link.send(self._answer)
            return 0
        if count < self.frame_count or self.frame_count < 0 or rate != self.frame_rate_hz:
            if 0 <= count < self.frame_count:
                self.counters['resets'] += 1         # ArduCopter restarted
            frames = 1
            if rate != self.frame_rate_hz:
                self.frame_rate_hz = float(rate)
                self._imu = ImuModel(self.params.imu, model_streams(
                    self.world.seed, f'ardupilot_json:{self.params.seed}:imu'), 1.0 / rate,
                    self.world.params.gravity_mps2)
        else:
            frames = count - self.frame_count
            if frames > self.params.max_frame_gap:
                self.counters['skipped_frames'] += frames
                frames = 1
        self.frame_count = count
        self.pwm = pwm
        self._apply(pwm)
        return frames

    # --- the world's Autopilot protocol (the simulator loop) ------------------------------

    @property
    def failsafe(self) -> str | None:
        """ArduCopter's failsafes are its own (reported on MAVLink), not the world's."""
        return None

    def tick(self, t_s: float, world: World) -> None:
        """Every physics sub-step (the world steps, :meth:`step` is not used): once a frame
        period is due, the answer to the last servo frame (the state the sub-steps since
        reached) goes back and the next frame's PWM drives the motors. Frames are 1:1 with
        the periods: run the world at ArduCopter's ``SIM_RATE_HZ``. ``max_silent_frames``
        lockstep timeouts in a row raise ConnectionError (ArduCopter is gone)."""
        if self.frame_count >= 0 and t_s + 1e-9 < self._next_s:
            return
        period = 1.0 / self.frame_rate_hz if self.frame_rate_hz > 0.0 else 0.0
        self._next_s += period
        if self._next_s <= t_s + 1e-9:
            self._next_s = t_s + period
        if self._answer_due:
            self._send_answer()
        t0 = time.monotonic()
        end = t0 + self.params.lockstep_timeout_s
        frames: int | None = 0
        while frames == 0:
            frames = self._receive(max(end - time.monotonic(), 0.0))
            if frames == 0 and time.monotonic() >= end:
                frames = None
        self.wait_wall_s += time.monotonic() - t0
        if frames is None:
            self.counters['lockstep_timeouts'] += 1
            self._silent += 1
            if self._silent >= self.params.max_silent_frames:
                raise ConnectionError(f'ArduCopter sent no servo frame for '
                                      f'{self._silent * self.params.lockstep_timeout_s:g} s')
            return
        self._silent = 0
        self.counters['frames'] += 1
        self._answer_due = True

    def _parse(self, data: bytes) -> tuple[int, int, tuple[int, ...]] | None:
        if len(data) == _SERVO_16.size:
            magic, rate, count, *pwm = _SERVO_16.unpack(data)
            ok = magic == SERVO_MAGIC_16
        elif len(data) == _SERVO_32.size:
            magic, rate, count, *pwm = _SERVO_32.unpack(data)
            ok = magic == SERVO_MAGIC_32
        else:
            return None
        if not ok or not 0 < rate <= 10000:
            return None
        return rate, count, tuple(pwm)

    def _apply(self, pwm: tuple[int, ...]) -> None:
        p = self.params
        motors = [pwm[ch] for ch in PLUSREV_CHANNEL]
        self.armed = max(motors) > p.pwm_min_us + 5
        f = [pwm_to_thrust(u, p, self._fmax) for u in motors]
        self.world.vehicle.set_motor_thrusts(f[0], f[1], f[2], f[3])

    def _state(self) -> bytes:
        """The answer: one compact JSON line (ArduPilot's parser is a text search that refuses
        ``"key": value`` with a space), with the IMU model's sample, the truth's NED position
        and velocity, the attitude quaternion and the lidar (held at its rate, −1 = no
        return)."""
        w = self.world
        v = w.vehicle
        r = rot_body_to_world(v.roll, v.pitch, v.yaw)
        imu = self._imu
        assert imu is not None
        f, wb = imu.sample((v.ax, v.ay, v.az), r, body_rates_from_euler(
            v.roll, v.pitch, v.roll_rate, v.pitch_rate, v.yaw_rate))
        ax, ay, az = flu_to_frd(*f)
        gx, gy, gz = flu_to_frd(*wb)
        pn, pe, pd = enu_to_ned(v.x, v.y, v.z)
        vn, ve, vd = enu_to_ned(v.vx, v.vy, v.vz)
        qw, qx, qy, qz = euler_enu_to_quat_ned(v.roll, v.pitch, v.yaw)
        t = w.t_s
        if t + 1e-9 >= self._range_due:
            self._range_due = t + self._range_period
            rng = w.read_lidar()
            self._range_m = rng if rng is not None else -1.0
        return (f'\n{{"timestamp":{t:.9f},"imu":{{"gyro":[{gx:.6f},{gy:.6f},{gz:.6f}],'
                f'"accel_body":[{ax:.5f},{ay:.5f},{az:.5f}]}},'
                f'"position":[{pn:.5f},{pe:.5f},{pd:.5f}],'
                f'"velocity":[{vn:.5f},{ve:.5f},{vd:.5f}],'
                f'"quaternion":[{qw:.7f},{qx:.7f},{qy:.7f},{qz:.7f}],'
                f'"rng_1":{self._range_m:.3f}}}\n').encode('ascii')
