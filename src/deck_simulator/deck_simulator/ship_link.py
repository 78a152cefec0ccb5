"""The ship as a MAVLink system of its own: GNSS/INS telemetry over a radio link (pure, seeded).

Like ArduPilot's FOLL_SYSID beacon, the ship (system id 17 by default) sends GLOBAL_POSITION_INT
and ATTITUDE of its landing pad at a few hertz. :class:`ShipLink` samples the true pad state at
each send time, adds the GNSS/INS errors (a slowly wandering position bias plus white noise, a
velocity and attitude noise, a heading bias), stamps it with the ship's own clock (offset and
drift) and delivers it after a latency with jitter, or loses it. Messages are plain values with
the MAVLink field names and units (:class:`GlobalPositionInt`, :class:`Attitude`): the graph's
simulator encodes them with pymavlink, the in-process runner hands them to
``mavlink_bridge.ship`` as they are. Parameters and sources: docs/world/ship_telemetry.md.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
import heapq
import math
import random

from deckland_common.frames import euler_enu_flu_to_ned_frd, flu_to_frd, mat_t_vec
from deckland_common.validate import in_range, integer_at_least, non_negative, positive, require

from deck_simulator.deck_motion import PadState

#: Metres per 1e-7 degree of latitude (MAVLink's lat/lon unit): ArduPilot's LOCATION_SCALING.
LOCATION_SCALING_M = 0.011131884502145034
UINT32 = 1 << 32
MAX_CM_S = 32767          # int16 velocity fields of GLOBAL_POSITION_INT (cm/s)


@dataclass(frozen=True, slots=True)
class ShipTelemetryParams:
    """The ``ship_telemetry:`` mapping of a scenario (docs/world/ship_telemetry.md)."""

    sysid: int = 17                     # MAVLink system id of the ship (ArduPilot FOLL_SYSID)
    compid: int = 1
    position_rate_hz: float = 5.0       # GLOBAL_POSITION_INT
    attitude_rate_hz: float = 10.0      # ATTITUDE
    latency_s: float = 0.15             # fixed part of the one-way delay (radio, serial, INS)
    jitter_s: float = 0.05              # mean of the exponential extra delay (queueing)
    loss_probability: float = 0.05      # per message
    # GNSS position error: Gauss-Markov bias (σ, τ) + white noise, per axis
    position_bias_sigma_m: float = 0.8  # horizontal; single-point GNSS ~1.2 m CEP
    vertical_bias_sigma_m: float = 1.5
    position_bias_tau_s: float = 300.0
    position_noise_m: float = 0.05
    velocity_noise_mps: float = 0.03    # GNSS Doppler velocity
    attitude_noise_rad: float = 0.0017  # roll/pitch, 0.1 deg
    heading_bias_sigma_rad: float = 0.0035   # dual-antenna heading, 0.2 deg
    rate_noise_radps: float = 0.002
    clock_offset_s: float = 1234.5      # ship clock (time_boot_ms) minus ours at t = 0
    clock_drift_ppm: float = 20.0
    origin_lat_deg: float = 54.32       # geodetic origin of the local ENU frame (EKF origin)
    origin_lon_deg: float = 10.15
    origin_alt_m: float = 0.0
    # a scheduled outage: nothing arrives in [outage_start_s, outage_start_s + duration)
    outage_start_s: float = math.inf
    outage_duration_s: float = 0.0

    def __post_init__(self) -> None:
        o = 'ship_telemetry'
        integer_at_least(f'{o}.sysid', self.sysid, 1)
        require(self.sysid <= 255, f'{o}.sysid', 'must be <= 255', self.sysid)
        integer_at_least(f'{o}.compid', self.compid, 0)
        require(self.compid <= 255, f'{o}.compid', 'must be <= 255', self.compid)
        for name in ('position_rate_hz', 'attitude_rate_hz', 'position_bias_tau_s'):
            positive(f'{o}.{name}', getattr(self, name))
        for name in ('latency_s', 'jitter_s', 'position_bias_sigma_m', 'vertical_bias_sigma_m',
                     'position_noise_m', 'velocity_noise_mps', 'attitude_noise_rad',
                     'heading_bias_sigma_rad', 'rate_noise_radps', 'clock_offset_s',
                     'outage_duration_s'):
            non_negative(f'{o}.{name}', getattr(self, name))
        in_range(f'{o}.loss_probability', self.loss_probability, 0.0, 1.0)
        in_range(f'{o}.clock_drift_ppm', self.clock_drift_ppm, -1000.0, 1000.0)
        in_range(f'{o}.origin_lat_deg', self.origin_lat_deg, -85.0, 85.0)
        in_range(f'{o}.origin_lon_deg', self.origin_lon_deg, -180.0, 180.0)
        require(self.outage_start_s >= 0.0, f'{o}.outage_start_s', 'must be >= 0',
                self.outage_start_s)

    @property
    def origin(self) -> tuple[float, float, float]:
        return self.origin_lat_deg, self.origin_lon_deg, self.origin_alt_m


@dataclass(frozen=True, slots=True)
class GlobalPositionInt:
    """MAVLink GLOBAL_POSITION_INT (#33): degE7, mm, cm/s NED, cdeg."""

    time_boot_ms: int
    lat: int
    lon: int
    alt: int
    relative_alt: int
    vx: int
    vy: int
    vz: int
    hdg: int

    def get_type(self) -> str:   # as pymavlink's messages
        return 'GLOBAL_POSITION_INT'


@dataclass(frozen=True, slots=True)
class Attitude:
    """MAVLink ATTITUDE (#30): FRD in NED, rad, rad/s."""

    time_boot_ms: int
    roll: float
    pitch: float
    yaw: float
    rollspeed: float
    pitchspeed: float
    yawspeed: float

    def get_type(self) -> str:
        return 'ATTITUDE'


ShipMessage = GlobalPositionInt | Attitude


def enu_to_geodetic(origin: tuple[float, float, float], east_m: float, north_m: float,
                    up_m: float) -> tuple[int, int, int]:
    """Local ENU (m) → (lat degE7, lon degE7, alt mm), flat earth about ``origin``."""
    lat0, lon0, alt0 = origin
    lat_e7 = round(lat0 * 1e7) + round(north_m / LOCATION_SCALING_M)
    lon_e7 = round(lon0 * 1e7) + round(east_m / (LOCATION_SCALING_M
                                                 * math.cos(math.radians(lat0))))
    return lat_e7, lon_e7, round((alt0 + up_m) * 1e3)


class ShipLink:
    """The ship's telemetry stream at the receiver.

    Args:
        params: the link and GNSS/INS error model.
        pad_state: the true pad state at a time (``World.pad_state``).
        seed_text: seeds the one random stream (``f'{seed}:ship_link'``).

    :meth:`poll` (``t_s`` non-decreasing) generates every message sent up to ``t_s`` and
    returns those that arrived by then, ``(t_arrival_s, message)`` in arrival order.
    ``sent``/``lost`` count messages; :attr:`last_truth` is the pad state of the last send.
    """

    def __init__(self, params: ShipTelemetryParams, pad_state: Callable[[float], PadState],
                 seed_text: str) -> None:
        self.params = params
        self._pad = pad_state
        self._rng = random.Random(seed_text)
        rng = self._rng
        p = params
        self._t_pos = rng.uniform(0.0, 1.0 / p.position_rate_hz)     # first send times
        self._t_att = rng.uniform(0.0, 1.0 / p.attitude_rate_hz)
        sb = p.position_bias_sigma_m
        self._bias = [rng.gauss(0.0, sb), rng.gauss(0.0, sb),
                      rng.gauss(0.0, p.vertical_bias_sigma_m)]
        self._t_bias = 0.0
        self._heading_bias = rng.gauss(0.0, p.heading_bias_sigma_rad)
        self._queue: list[tuple[float, int, ShipMessage]] = []
        self._n = 0
        self.sent = 0
        self.lost = 0

    @property
    def position_bias_m(self) -> tuple[float, float, float]:
        """The GNSS position error's bias now (ENU, m): what the receiver must learn."""
        b = self._bias
        return b[0], b[1], b[2]

    @property
    def in_flight(self) -> int:
        """Messages sent and not yet arrived."""
        return len(self._queue)

    def ship_time_ms(self, t_s: float) -> int:
        """The ship's clock (time_boot_ms, wrapping at 2^32) at our time ``t_s``."""
        p = self.params
        return round((p.clock_offset_s + t_s * (1.0 + p.clock_drift_ppm * 1e-6)) * 1e3) % UINT32

    def _advance_bias(self, t_s: float) -> None:
        dt = t_s - self._t_bias
        if dt <= 0.0:
            return
        p = self.params
        a = math.exp(-dt / p.position_bias_tau_s)
        k = math.sqrt(max(0.0, 1.0 - a * a))
        g = self._rng.gauss
        b = self._bias
        b[0] = a * b[0] + k * p.position_bias_sigma_m * g(0.0, 1.0)
        b[1] = a * b[1] + k * p.position_bias_sigma_m * g(0.0, 1.0)
        b[2] = a * b[2] + k * p.vertical_bias_sigma_m * g(0.0, 1.0)
        self._t_bias = t_s

    def _position(self, t_s: float) -> GlobalPositionInt:
        p, g = self.params, self._rng.gauss
        ps = self._pad(t_s)
        self._advance_bias(t_s)
        b = self._bias
        sp, sv = p.position_noise_m, p.velocity_noise_mps
        x, y, z = ps.position_m
        vx, vy, vz = ps.velocity_mps
        lat, lon, alt = enu_to_geodetic(p.origin, x + b[0] + g(0.0, sp), y + b[1] + g(0.0, sp),
                                        z + b[2] + g(0.0, sp))
        n, e, d = vy + g(0.0, sv), vx + g(0.0, sv), -(vz + g(0.0, sv))
        hdg = math.degrees(math.pi / 2.0 - ps.rpy_rad[2] + self._heading_bias) % 360.0

        def cm(v: float) -> int:
            return max(-MAX_CM_S, min(MAX_CM_S, round(v * 100.0)))

        return GlobalPositionInt(self.ship_time_ms(t_s), lat, lon, alt,
                                 round((z + b[2]) * 1e3), cm(n), cm(e), cm(d),
                                 round(hdg * 100.0) % 36000)

    def _attitude(self, t_s: float) -> Attitude:
        p, g = self.params, self._rng.gauss
        ps = self._pad(t_s)
        roll, pitch, yaw = ps.rpy_rad
        sa, sr = p.attitude_noise_rad, p.rate_noise_radps
        r_ned = euler_enu_flu_to_ned_frd(roll + g(0.0, sa), pitch + g(0.0, sa),
                                         yaw - self._heading_bias + g(0.0, sa))
        w_flu = mat_t_vec(ps.rotation, ps.omega_radps)     # world ω → deck (FLU) axes
        w_frd = flu_to_frd(w_flu[0] + g(0.0, sr), w_flu[1] + g(0.0, sr), w_flu[2] + g(0.0, sr))
        return Attitude(self.ship_time_ms(t_s), r_ned[0], r_ned[1], r_ned[2],
                        w_frd[0], w_frd[1], w_frd[2])

    def _send(self, t_s: float, msg: ShipMessage) -> None:
        p = self.params
        self.sent += 1
        rng = self._rng
        lost = rng.random() < p.loss_probability
        delay = p.latency_s + (rng.expovariate(1.0 / p.jitter_s) if p.jitter_s > 0.0 else 0.0)
        t_arrive = t_s + delay
        if lost or p.outage_start_s <= t_arrive < p.outage_start_s + p.outage_duration_s:
            self.lost += 1
            return
        self._n += 1
        heapq.heappush(self._queue, (t_arrive, self._n, msg))

    def poll(self, t_s: float) -> list[tuple[float, ShipMessage]]:
        """Messages sent up to ``t_s`` generated; those arrived by ``t_s`` returned."""
        p = self.params
        while self._t_pos <= t_s or self._t_att <= t_s:
            if self._t_pos <= self._t_att:
                self._send(self._t_pos, self._position(self._t_pos))
                self._t_pos += 1.0 / p.position_rate_hz
            else:
                self._send(self._t_att, self._attitude(self._t_att))
                self._t_att += 1.0 / p.attitude_rate_hz
        out = []
        q = self._queue
        while q and q[0][0] <= t_s:
            t_a, _, msg = heapq.heappop(q)
            out.append((t_a, msg))
        return out


class ShipEncoder:
    """Ship messages → MAVLink 2 bytes from the ship's system id (the graph's simulator node
    sends them as UDP datagrams to ``ship_telemetry_node``)."""

    def __init__(self, sysid: int, compid: int = 1) -> None:
        from pymavlink.dialects.v20 import common as mavlink2
        self._buf = bytearray()
        self._mav = mavlink2.MAVLink(self, srcSystem=sysid, srcComponent=compid)

    def write(self, data: bytes) -> None:   # pymavlink's file interface
        self._buf += data

    def encode(self, msg: ShipMessage) -> bytes:
        mav = self._mav
        if isinstance(msg, GlobalPositionInt):
            mav.global_position_int_send(msg.time_boot_ms, msg.lat, msg.lon, msg.alt,
                                         msg.relative_alt, msg.vx, msg.vy, msg.vz, msg.hdg)
        else:
            mav.attitude_send(msg.time_boot_ms, msg.roll, msg.pitch, msg.yaw, msg.rollspeed,
                              msg.pitchspeed, msg.yawspeed)
        out = bytes(self._buf)
        self._buf.clear()
        return out
