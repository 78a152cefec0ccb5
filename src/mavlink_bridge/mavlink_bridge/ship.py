"""Ship telemetry decode (pure): a ship's MAVLink GLOBAL_POSITION_INT / ATTITUDE → ENU deck state.

The ship is a MAVLink system of its own (``ship_sysid``, like ArduPilot's FOLL_SYSID); its other
messages and every other system are ignored. Positions (degE7, mm) become ENU metres in the
local frame about a geodetic origin (flat earth, as ArduPilot's EKF); NED velocities and FRD/NED
attitude become ENU / FLU (``deckland_common.frames``). The ship stamps with its own clock: the
offset to ours is the smallest (arrival − ship time) seen less the link's nominal fastest delay
(``min_latency_s``), with a drift allowance. Stale, out-of-order, repeated
and non-finite messages are rejected and counted. Output: :class:`DeckTelemetry` samples.
"""

from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Any

from deckland_common.frames import euler_ned_frd_to_enu_flu, frd_to_flu, ned_to_enu
from deckland_common.validate import in_range, integer_at_least, non_negative, positive

#: Metres per 1e-7 degree of latitude (ArduPilot's LOCATION_SCALING; as conversions.py).
LOCATION_SCALING_M = 0.011131884502145034
UINT32 = 1 << 32
REJECTED = ('other_system', 'other_message', 'non_finite', 'out_of_order', 'stale',
            'implausible')


@dataclass(frozen=True, slots=True)
class ShipDecodeParams:
    """Decoder settings (the ship-telemetry node's parameters)."""

    ship_sysid: int = 17
    origin_lat_deg: float = 54.32       # the local frame's geodetic origin
    origin_lon_deg: float = 10.15
    origin_alt_m: float = 0.0
    max_age_s: float = 1.0              # older on arrival (clock-corrected) → stale
    min_latency_s: float = 0.1          # the link's fastest one-way delay (nominal, radio)
    clock_drift_ppm: float = 100.0      # allowance: the offset estimate may creep this fast
    max_speed_mps: float = 30.0         # a faster deck is implausible

    def __post_init__(self) -> None:
        o = 'ShipDecodeParams'
        integer_at_least(f'{o}.ship_sysid', self.ship_sysid, 1)
        in_range(f'{o}.origin_lat_deg', self.origin_lat_deg, -85.0, 85.0)
        in_range(f'{o}.origin_lon_deg', self.origin_lon_deg, -180.0, 180.0)
        positive(f'{o}.max_age_s', self.max_age_s)
        non_negative(f'{o}.min_latency_s', self.min_latency_s)
        non_negative(f'{o}.clock_drift_ppm', self.clock_drift_ppm)
        positive(f'{o}.max_speed_mps', self.max_speed_mps)


@dataclass(frozen=True, slots=True)
class DeckTelemetry:
    """One decoded telemetry sample, ENU / FLU, stamped in the receiver's clock.

    ``kind`` is ``'position'`` (position_m, velocity_mps valid) or ``'attitude'`` (rpy_rad,
    rates_flu_radps and yaw_rate_radps valid); the other fields are zero.
    """

    kind: str
    t_s: float                                   # measurement time, receiver clock
    t_arrival_s: float
    position_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    velocity_mps: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rpy_rad: tuple[float, float, float] = (0.0, 0.0, 0.0)   # deck FLU in ENU, Z-Y-X
    rates_flu_radps: tuple[float, float, float] = (0.0, 0.0, 0.0)
    yaw_rate_radps: float = 0.0                  # dψ/dt of the ENU yaw


def geodetic_to_enu(origin: tuple[float, float, float], lat_e7: int, lon_e7: int,
                    alt_mm: int) -> tuple[float, float, float]:
    """(degE7, degE7, mm) → ENU metres about ``origin`` (lat_deg, lon_deg, alt_m), flat earth."""
    lat0, lon0, alt0 = origin
    north = (lat_e7 - round(lat0 * 1e7)) * LOCATION_SCALING_M
    east = (lon_e7 - round(lon0 * 1e7)) * LOCATION_SCALING_M * math.cos(math.radians(lat0))
    return east, north, alt_mm * 1e-3 - alt0


def yaw_rate_from_body_rates(roll_rad: float, pitch_rad: float, q_radps: float,
                             r_radps: float) -> float:
    """Z-Y-X Euler kinematics: ψ̇ = (q sin φ + r cos φ) / cos θ (FLU body rates, ENU yaw)."""
    c = math.cos(pitch_rad)
    if abs(c) < 1e-6:
        return 0.0
    return (q_radps * math.sin(roll_rad) + r_radps * math.cos(roll_rad)) / c


class ShipTelemetryDecoder:
    """Ship messages in, :class:`DeckTelemetry` out; ``rejected`` counts what was refused."""

    def __init__(self, params: ShipDecodeParams | None = None) -> None:
        self.params = params if params is not None else ShipDecodeParams()
        p = self.params
        self.origin = (p.origin_lat_deg, p.origin_lon_deg, p.origin_alt_m)
        self.rejected: dict[str, int] = dict.fromkeys(REJECTED, 0)
        self.accepted = 0
        self._offset_s: float | None = None    # receiver time − ship time (min over arrivals)
        self._t_offset = 0.0                   # arrival time of the last offset update
        self._ms_unwrapped: dict[str, int] = {}
        self._last_ms: dict[str, int] = {}

    @property
    def clock_offset_s(self) -> float | None:
        """Receiver clock minus ship clock (None before the first message)."""
        return self._offset_s

    def _ship_seconds(self, kind: str, time_boot_ms: int) -> float:
        """Unwrapped ship time of ``time_boot_ms`` (uint32 ms wraps every 49.7 days)."""
        last = self._last_ms.get(kind)
        ms = int(time_boot_ms) % UINT32
        if last is not None:
            d = (ms - last % UINT32) % UINT32
            if d >= UINT32 // 2:
                d -= UINT32
            ms = last + d
        return ms * 1e-3

    def on_message(self, t_arrival_s: float, sysid: int, msg: Any) -> DeckTelemetry | None:
        """One MAVLink message (pymavlink's or ship_link's), received at ``t_arrival_s``."""
        if sysid != self.params.ship_sysid:
            self.rejected['other_system'] += 1
            return None
        kind = {'GLOBAL_POSITION_INT': 'position', 'ATTITUDE': 'attitude'}.get(msg.get_type())
        if kind is None:
            self.rejected['other_message'] += 1
            return None
        try:
            if kind == 'position':
                fields = [float(msg.lat), float(msg.lon), float(msg.alt), float(msg.vx),
                          float(msg.vy), float(msg.vz)]
            else:
                fields = [float(msg.roll), float(msg.pitch), float(msg.yaw), float(msg.rollspeed),
                          float(msg.pitchspeed), float(msg.yawspeed)]
            t_ship = self._ship_seconds(kind, msg.time_boot_ms)
        except (AttributeError, TypeError, ValueError, OverflowError):
            self.rejected['non_finite'] += 1
            return None
        if not (math.isfinite(t_arrival_s) and all(math.isfinite(f) for f in fields)):
            self.rejected['non_finite'] += 1
            return None
        last = self._last_ms.get(kind)
        ms = round(t_ship * 1e3)
        if last is not None and ms <= last:
            self.rejected['out_of_order'] += 1
            return None
        t_s = self._receiver_time(t_arrival_s, t_ship)
        if t_arrival_s - t_s > self.params.max_age_s:
            self.rejected['stale'] += 1
            self._last_ms[kind] = ms
            return None
        if kind == 'position':
            pos = geodetic_to_enu(self.origin, round(fields[0]), round(fields[1]),
                                  round(fields[2]))
            vel = ned_to_enu(fields[3] * 0.01, fields[4] * 0.01, fields[5] * 0.01)
            if math.hypot(vel[0], vel[1]) > self.params.max_speed_mps or abs(fields[0]) > 9e8:
                self.rejected['implausible'] += 1
                return None
            out = DeckTelemetry('position', t_s, t_arrival_s, position_m=pos, velocity_mps=vel)
        else:
            rpy = euler_ned_frd_to_enu_flu(fields[0], fields[1], fields[2])
            w = frd_to_flu(fields[3], fields[4], fields[5])
            out = DeckTelemetry('attitude', t_s, t_arrival_s, rpy_rad=rpy, rates_flu_radps=w,
                                yaw_rate_radps=yaw_rate_from_body_rates(rpy[0], rpy[1], w[1],
                                                                        w[2]))
        self._last_ms[kind] = ms
        self.accepted += 1
        return out

    def _receiver_time(self, t_arrival_s: float, t_ship_s: float) -> float:
        """Ship time → receiver time: offset = min(arrival − ship time), allowed to creep up
        by the drift allowance between updates (a clock that runs slow is followed)."""
        sample = t_arrival_s - t_ship_s
        off = self._offset_s
        if off is None:
            off = sample
        else:
            off += self.params.clock_drift_ppm * 1e-6 * max(0.0, t_arrival_s - self._t_offset)
            off = min(off, sample)
        self._offset_s = off
        self._t_offset = t_arrival_s
        return t_ship_s + off - self.params.min_latency_s


@dataclass(frozen=True, slots=True)
class DeckOdom:
    """The deck at one stamp (``deck/odom``): ENU position and velocity, attitude and rates."""

    t_s: float
    position_m: tuple[float, float, float]
    velocity_mps: tuple[float, float, float]       # world ENU
    attitude_valid: bool
    rpy_rad: tuple[float, float, float]            # deck FLU in ENU (zeros if not valid)
    rates_flu_radps: tuple[float, float, float]
    yaw_rate_radps: float


class DeckOdomAssembler:
    """Position and attitude samples (separate messages, separate rates) → one
    :class:`DeckOdom` per sample, at the newest stamp: the position carried forward with its
    velocity, the attitude with its Euler rates (over at most ``max_extrapolation_s``)."""

    def __init__(self, attitude_max_age_s: float = 0.5, max_extrapolation_s: float = 0.5) -> None:
        positive('DeckOdomAssembler.attitude_max_age_s', attitude_max_age_s)
        non_negative('DeckOdomAssembler.max_extrapolation_s', max_extrapolation_s)
        self.attitude_max_age_s = attitude_max_age_s
        self.max_extrapolation_s = max_extrapolation_s
        self._pos: DeckTelemetry | None = None
        self._att: DeckTelemetry | None = None

    def on_sample(self, s: DeckTelemetry) -> DeckOdom | None:
        """The deck at the newest stamp, or None while no position has arrived."""
        if s.kind == 'position':
            self._pos = s
        else:
            self._att = s
        p = self._pos
        if p is None:
            return None
        t = max(p.t_s, s.t_s)
        dt = min(t - p.t_s, self.max_extrapolation_s)
        v = p.velocity_mps
        pos = (p.position_m[0] + v[0] * dt, p.position_m[1] + v[1] * dt,
               p.position_m[2] + v[2] * dt)
        a = self._att
        if a is None or t - a.t_s > self.attitude_max_age_s:
            return DeckOdom(t, pos, v, False, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 0.0)
        roll, pitch, yaw = a.rpy_rad
        wp, wq, wr = a.rates_flu_radps
        da = min(t - a.t_s, self.max_extrapolation_s)
        cr, sr, tp = math.cos(roll), math.sin(roll), math.tan(pitch)
        roll_dot = wp + (wq * sr + wr * cr) * tp          # Z-Y-X Euler kinematics
        pitch_dot = wq * cr - wr * sr
        rpy = (roll + roll_dot * da, pitch + pitch_dot * da,
               math.remainder(yaw + a.yaw_rate_radps * da, 2.0 * math.pi))
        return DeckOdom(t, pos, v, True, rpy, a.rates_flu_radps, a.yaw_rate_radps)
