"""Fault injection for the simulated world (pure, deterministic from the run seed).

A scenario's ``faults:`` entries become frozen specs (:func:`parse_faults`, strict validation
naming the key path); :class:`FaultSet` answers at run time what each fault does to the camera,
the lidar, the GPS and the wind at time t, and holds the windows the MAVLink link model
(:mod:`deck_simulator.link`) applies. A fault draws from its own stream
``random.Random(f'{seed}:fault:{index}:{type}')``, so it never shifts the world's other noise;
without faults no ``FaultSet`` is built. A window is ``start_s <= t < end_s``, or opens when the
true height above the surface first drops under ``trigger_height_m``. See the package README.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
import math
import random
from typing import Any, ClassVar

from deckland_common.validate import in_range, is_finite_number, require

NODE_NAMES = ('apron_estimator', 'dob_altitude', 'landing_planner', 'mavlink_bridge',
              'pixy_driver')
# nodes on the command path: if one dies, no attitude/thrust commands reach the autopilot
COMMAND_PATH_NODES = ('apron_estimator', 'dob_altitude', 'landing_planner', 'mavlink_bridge')


# --- specs ---------------------------------------------------------------------------------

@dataclass(frozen=True, slots=True)
class FaultSpec:
    """Common window of every fault: active for start_s <= t < end_s (world time, s)."""

    type: ClassVar[str] = ''
    start_s: float = 0.0
    end_s: float = math.inf
    trigger_height_m: float | None = None   # open the window when height < this (after start_s)

    def __post_init__(self) -> None:
        require(is_finite_number(self.start_s) and self.start_s >= 0, 'start_s', 'must be >= 0',
                self.start_s)
        end_ok = (isinstance(self.end_s, int | float) and not isinstance(self.end_s, bool)
                  and not math.isnan(self.end_s) and self.end_s > self.start_s)
        require(end_ok, 'end_s', f'must be > start_s ({self.start_s})', self.end_s)
        if self.trigger_height_m is not None:
            require(is_finite_number(self.trigger_height_m) and self.trigger_height_m > 0,
                    'trigger_height_m', 'must be > 0', self.trigger_height_m)
        self._check()

    def _check(self) -> None:   # per-type parameter checks
        pass

    @property
    def duration_s(self) -> float:
        return self.end_s - self.start_s


@dataclass(frozen=True, slots=True)
class BeaconOcclusion(FaultSpec):
    """The beacon is not detected in any frame exposed in the window (glints still are)."""

    type: ClassVar[str] = 'beacon_occlusion'


@dataclass(frozen=True, slots=True)
class CameraDropout(FaultSpec):
    """Empty Pixy frames: every frame in the window (``window``) or random ``bursts``."""

    type: ClassVar[str] = 'camera_dropout'
    mode: str = 'window'            # window | bursts
    burst_rate_hz: float = 0.5      # bursts: Poisson rate of burst starts (bursts per second)
    burst_length_s: float = 0.3     # bursts: every frame empty for this long after a start

    def _check(self) -> None:
        require(self.mode in ('window', 'bursts'), 'mode', "must be 'window' or 'bursts'",
                self.mode)
        require(is_finite_number(self.burst_rate_hz) and self.burst_rate_hz > 0, 'burst_rate_hz',
                'must be > 0', self.burst_rate_hz)
        require(is_finite_number(self.burst_length_s) and self.burst_length_s > 0,
                'burst_length_s', 'must be > 0', self.burst_length_s)


@dataclass(frozen=True, slots=True)
class FalseBlobs(FaultSpec):
    """Sun glint / reflections with the beacon's signature.

    ``flicker``: a Poisson number of blobs per frame (mean ``rate_per_frame``), each lasting one
    frame, at uniform random pixels or, with ``near_beacon_m``, at random points on the pad-top
    plane within that radius of the beacon (projected, so they look like the beacon).
    ``persistent``: one blob at a fixed world point (``position_m``, or ``near_beacon_m`` from
    the apron centre at the deck's mean height, direction ``bearing_rad`` or drawn from the
    seed), shown in each frame with probability ``rate_per_frame``.
    """

    type: ClassVar[str] = 'false_blobs'
    mode: str = 'flicker'                       # flicker | persistent
    rate_per_frame: float = 1.0
    near_beacon_m: float | None = None
    bearing_rad: float | None = None            # ENU angle of the offset from the beacon
    position_m: tuple[float, float, float] | None = None
    size_m: float = 0.08                        # apparent size of a world-point blob

    def _check(self) -> None:
        require(self.mode in ('flicker', 'persistent'), 'mode',
                "must be 'flicker' or 'persistent'", self.mode)
        if self.mode == 'persistent':
            in_range('rate_per_frame', self.rate_per_frame, 0, 1)
            require(self.position_m is not None or self.near_beacon_m is not None, 'position_m',
                    'or near_beacon_m is required for a persistent blob',
                    self.position_m)
        else:
            require(is_finite_number(self.rate_per_frame) and 0 < self.rate_per_frame <= 10,
                    'rate_per_frame', 'must be in (0, 10] blobs per frame',
                    self.rate_per_frame)
            require(self.position_m is None, 'position_m', 'is only for mode persistent',
                    self.position_m)
        if self.near_beacon_m is not None:
            require(is_finite_number(self.near_beacon_m) and self.near_beacon_m >= 0,
                    'near_beacon_m', 'must be >= 0', self.near_beacon_m)
        if self.bearing_rad is not None:
            require(is_finite_number(self.bearing_rad), 'bearing_rad', 'must be finite',
                    self.bearing_rad)
        require(is_finite_number(self.size_m) and self.size_m > 0, 'size_m', 'must be > 0',
                self.size_m)


@dataclass(frozen=True, slots=True)
class LidarDropout(FaultSpec):
    """Lidar readings are None in the window with ``probability`` (1 = every reading)."""

    type: ClassVar[str] = 'lidar_dropout'
    probability: float = 1.0

    def _check(self) -> None:
        in_range('probability', self.probability, 0, 1)


@dataclass(frozen=True, slots=True)
class LidarOutliers(FaultSpec):
    """Spikes: a valid reading is moved by ±``magnitude_m`` with ``probability``."""

    type: ClassVar[str] = 'lidar_outliers'
    probability: float = 0.05
    magnitude_m: float = 2.0
    direction: str = 'both'          # short | long | both (sign drawn 50/50)

    def _check(self) -> None:
        in_range('probability', self.probability, 0, 1)
        require(is_finite_number(self.magnitude_m) and self.magnitude_m > 0, 'magnitude_m',
                'must be > 0', self.magnitude_m)
        require(self.direction in ('short', 'long', 'both'), 'direction',
                "must be 'short', 'long' or 'both'", self.direction)


@dataclass(frozen=True, slots=True)
class GpsJump(FaultSpec):
    """A step of ``magnitude_m`` in the horizontal GPS bias (plus ``vertical_m``) in the window."""

    type: ClassVar[str] = 'gps_jump'
    magnitude_m: float = 1.5
    bearing_rad: float | None = None     # ENU direction of the step; drawn from the seed if None
    vertical_m: float = 0.0

    def _check(self) -> None:
        require(is_finite_number(self.magnitude_m) and self.magnitude_m >= 0, 'magnitude_m',
                'must be >= 0', self.magnitude_m)
        if self.bearing_rad is not None:
            require(is_finite_number(self.bearing_rad), 'bearing_rad', 'must be finite',
                    self.bearing_rad)
        require(is_finite_number(self.vertical_m), 'vertical_m', 'must be finite', self.vertical_m)


@dataclass(frozen=True, slots=True)
class GustStep(FaultSpec):
    """A step of ``wind_mps`` (ENU, added to the mean wind and gusts) in the window."""

    type: ClassVar[str] = 'gust_step'
    wind_mps: tuple[float, float, float] = (4.0, 0.0, 0.0)

    def _check(self) -> None:
        require(len(self.wind_mps) == 3 and all(is_finite_number(w) for w in self.wind_mps),
                'wind_mps', 'must be 3 finite numbers', self.wind_mps)


@dataclass(frozen=True, slots=True)
class _LinkFault(FaultSpec):
    """Shared failsafe parameters of the faults that cut the command link."""

    loss_timeout_s: float = 1.0      # PX4 COM_OF_LOSS_T: no command for this long → failsafe
    hold_s: float = 5.0              # failsafe hold, then the action below
    action: str = 'land'             # COM_OBL_RC_ACT after the hold: 'land' here | 'return'
    land_speed_mps: float = 0.7      # MPC_LAND_SPEED (PX4 default 0.7)
    min_alt_m: float = 0.0           # hold/return climb to at least this world altitude first
    climb_speed_mps: float = 0.5     # ... at this rate (MPC_Z_VEL_MAX_UP-like, kept gentle)
    return_speed_mps: float = 1.0    # 'return': horizontal speed toward home (RTL)
    reengage_offboard: bool = True   # a command arriving ends the failsafe (the bridge asks
    #                                  for OFFBOARD again); False: PX4 stays in its failsafe

    def _check(self) -> None:
        require(is_finite_number(self.loss_timeout_s) and self.loss_timeout_s > 0,
                'loss_timeout_s', 'must be > 0', self.loss_timeout_s)
        require(is_finite_number(self.hold_s) and self.hold_s >= 0, 'hold_s', 'must be >= 0',
                self.hold_s)
        require(self.action in ('land', 'return'), 'action', "must be 'land' or 'return'",
                self.action)
        for name in ('land_speed_mps', 'climb_speed_mps', 'return_speed_mps'):
            v = getattr(self, name)
            require(is_finite_number(v) and 0 < v <= 5.0, name, 'must be in (0, 5] m/s', v)
        require(is_finite_number(self.min_alt_m) and self.min_alt_m >= 0, 'min_alt_m',
                'must be >= 0', self.min_alt_m)
        require(isinstance(self.reengage_offboard, bool), 'reengage_offboard',
                'must be true or false', self.reengage_offboard)


@dataclass(frozen=True, slots=True)
class MavlinkLoss(_LinkFault):
    """Each command packet is lost with ``probability`` (the world keeps the previous one)."""

    type: ClassVar[str] = 'mavlink_loss'
    probability: float = 0.2

    def _check(self) -> None:
        _LinkFault._check(self)
        in_range('probability', self.probability, 0, 1)


@dataclass(frozen=True, slots=True)
class MavlinkLatency(_LinkFault):
    """Commands sent in the window are applied ``latency_s`` later."""

    type: ClassVar[str] = 'mavlink_latency'
    latency_s: float = 0.2

    def _check(self) -> None:
        _LinkFault._check(self)
        require(is_finite_number(self.latency_s) and 0 < self.latency_s <= 10, 'latency_s',
                'must be in (0, 10]', self.latency_s)


@dataclass(frozen=True, slots=True)
class MavlinkLinkLoss(_LinkFault):
    """No command arrives in the window (offboard-loss failsafe after ``loss_timeout_s``)."""

    type: ClassVar[str] = 'mavlink_link_loss'


@dataclass(frozen=True, slots=True)
class NodeKill(_LinkFault):
    """``node`` dies at start_s (back at end_s if finite). In-process: a command-path node ⇒
    link loss; ``pixy_driver`` ⇒ empty camera frames."""

    type: ClassVar[str] = 'node_kill'
    node: str = ''

    def _check(self) -> None:
        _LinkFault._check(self)
        require(self.node in NODE_NAMES, 'node', f'must be one of {list(NODE_NAMES)}', self.node)


FAULT_TYPES: dict[str, type[FaultSpec]] = {c.type: c for c in (
    BeaconOcclusion, CameraDropout, FalseBlobs, LidarDropout, LidarOutliers, GpsJump, GustStep,
    MavlinkLoss, MavlinkLatency, MavlinkLinkLoss, NodeKill)}
LINK_TYPES = ('mavlink_loss', 'mavlink_latency', 'mavlink_link_loss', 'node_kill')
_TUPLE_FIELDS = {'position_m': 3, 'wind_mps': 3}
_STR_FIELDS = {'mode', 'direction', 'node', 'action'}
_BOOL_FIELDS = {'reengage_offboard'}
_OPTIONAL = {'trigger_height_m', 'near_beacon_m', 'bearing_rad', 'position_m'}


def _value(key: str, value: Any, where: str) -> Any:
    if value is None and key in _OPTIONAL:
        return None
    if key in _BOOL_FIELDS:
        if not isinstance(value, bool):
            raise ValueError(f'{where} must be true or false, got {value!r}')
        return value
    if key in _STR_FIELDS:
        if not isinstance(value, str):
            raise ValueError(f'{where} must be a string, got {value!r}')
        return value
    if key in _TUPLE_FIELDS:
        n = _TUPLE_FIELDS[key]
        if not isinstance(value, list | tuple) or not all(is_finite_number(v) for v in value):
            raise ValueError(f'{where} must be a list of finite numbers, got {value!r}')
        if key == 'wind_mps' and len(value) == 2:
            value = (*value, 0.0)
        if len(value) != n:
            raise ValueError(f'{where} must have {n} entries, got {value!r}')
        return tuple(float(v) for v in value)
    if key == 'end_s' and isinstance(value, int | float) and value == math.inf:
        return math.inf
    if not is_finite_number(value):
        raise ValueError(f'{where} must be a finite number, got {value!r}')
    return float(value)


def parse_fault(entry: Any, path: str = 'faults[0]') -> FaultSpec:
    """One ``faults:`` entry (a mapping, or an already built spec) → its validated spec."""
    if isinstance(entry, FaultSpec):
        return entry
    if not isinstance(entry, dict):
        raise ValueError(f'{path} must be a mapping with a type, got {entry!r}')
    kind = entry.get('type')
    if kind not in FAULT_TYPES:
        raise ValueError(f'{path}.type must be one of {sorted(FAULT_TYPES)}, got {kind!r}')
    cls = FAULT_TYPES[kind]
    allowed = {f.name for f in fields(cls)} | {'type', 'duration_s'}
    kwargs: dict[str, Any] = {}
    for key, value in entry.items():
        if key == 'type':
            continue
        if key not in allowed:
            raise ValueError(f'unknown key {path + "." + str(key)!r} for a {kind} fault '
                             f'(allowed: {sorted(allowed)})')
        kwargs[key] = _value(key, value, f'{path}.{key}')
    if 'duration_s' in kwargs:
        d = kwargs.pop('duration_s')
        if 'end_s' in kwargs:
            raise ValueError(f'{path}: give end_s or duration_s, not both')
        if d <= 0:
            raise ValueError(f'{path}.duration_s must be > 0, got {d!r}')
        kwargs['end_s'] = kwargs.get('start_s', 0.0) + d
    try:
        return cls(**kwargs)
    except ValueError as exc:
        raise ValueError(f'{path}.{exc}') from None


def parse_faults(entries: Any, path: str = 'faults') -> tuple[FaultSpec, ...]:
    """The ``faults:`` list → a tuple of validated specs (ValueError names the entry)."""
    if entries is None:
        return ()
    if not isinstance(entries, list | tuple):
        raise ValueError(f'{path} must be a list of fault entries, got {entries!r}')
    return tuple(parse_fault(e, f'{path}[{i}]') for i, e in enumerate(entries))


# --- run time ------------------------------------------------------------------------------

class _Active:
    """One fault at run time: its resolved window [on, off) and its own random stream."""

    __slots__ = ('bursts', 'index', 'name', 'off', 'on', 'point', 'rng', 'spec', 'step')

    def __init__(self, spec: FaultSpec, index: int, seed: int) -> None:
        # typed Any: each list of FaultSet holds one spec type, read by the code for that type
        self.spec: Any = spec
        self.index = index
        self.name = spec.type
        self.rng = random.Random(f'{seed}:fault:{index}:{spec.type}')
        if spec.trigger_height_m is None:
            self.on, self.off = spec.start_s, spec.end_s
        else:   # resolved by FaultSet.update_height
            self.on = self.off = math.inf
        self.bursts: tuple[tuple[float, float], ...] = ()
        self.point: tuple[float, float, float] | None = None
        self.step: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def is_on(self, t: float) -> bool:
        return self.on <= t < self.off


class FaultSet:
    """Run-time faults of one world. Built only when the scenario has faults.

    ``apron_xy``/``deck_mean_m`` place persistent glints; all draws that do not depend on the
    flight (burst times, jump and glint directions) are made here, at construction.
    """

    def __init__(self, specs: tuple[FaultSpec, ...], seed: int,
                 apron_xy: tuple[float, float] = (0.0, 0.0), deck_mean_m: float = 0.0) -> None:
        self.specs = specs
        self._t0_s = 0.0          # scenario times count from here (start_at)
        self.all = [_Active(s, i, seed) for i, s in enumerate(specs)]
        self.pending = [a for a in self.all if a.spec.trigger_height_m is not None]
        by: dict[str, list[_Active]] = {}
        for a in self.all:
            by.setdefault(a.name, []).append(a)
            s = a.spec
            if isinstance(s, CameraDropout) and s.mode == 'bursts':
                a.bursts = self._bursts(a, s)
            elif isinstance(s, FalseBlobs) and s.mode == 'persistent':
                if s.position_m is not None:
                    a.point = s.position_m
                else:
                    b = s.bearing_rad if s.bearing_rad is not None else a.rng.uniform(
                        -math.pi, math.pi)
                    r = s.near_beacon_m or 0.0
                    a.point = (apron_xy[0] + r * math.cos(b), apron_xy[1] + r * math.sin(b),
                               deck_mean_m)
            elif isinstance(s, GpsJump):
                b = s.bearing_rad if s.bearing_rad is not None else a.rng.uniform(
                    -math.pi, math.pi)
                a.step = (s.magnitude_m * math.cos(b), s.magnitude_m * math.sin(b),
                          s.vertical_m)
            elif isinstance(s, GustStep):
                a.step = s.wind_mps
        g = by.get
        self.occlusion = g('beacon_occlusion', [])
        self.dropout = g('camera_dropout', []) + [
            a for a in g('node_kill', []) if a.spec.node == 'pixy_driver']
        self.blobs = g('false_blobs', [])
        self.lidar_drop = g('lidar_dropout', [])
        self.lidar_spikes = g('lidar_outliers', [])
        self.gps = g('gps_jump', [])
        self.wind = g('gust_step', [])
        self.link_cut = g('mavlink_link_loss', []) + [
            a for a in g('node_kill', []) if a.spec.node in COMMAND_PATH_NODES]
        self.link_loss = g('mavlink_loss', [])
        self.link_latency = g('mavlink_latency', [])
        self.has_camera = bool(self.occlusion or self.dropout or self.blobs)
        self.has_lidar = bool(self.lidar_drop or self.lidar_spikes)
        self.has_link = bool(self.link_cut or self.link_loss or self.link_latency)
        link = self.link_cut + self.link_loss + self.link_latency
        # the autopilot's failsafe settings (deck_simulator.autopilot): the first link fault's
        self.link_spec: _LinkFault = link[0].spec if link else MavlinkLinkLoss()

    @staticmethod
    def _bursts(a: _Active, s: CameraDropout) -> tuple[tuple[float, float], ...]:
        """Burst start offsets from the window opening (Poisson, rate burst_rate_hz)."""
        out = []
        horizon = min(s.duration_s, 3600.0)
        t = a.rng.expovariate(s.burst_rate_hz)
        while t < horizon:
            out.append((t, t + s.burst_length_s))
            t += a.rng.expovariate(s.burst_rate_hz)
        return tuple(out)

    # --- windows ---------------------------------------------------------------------------

    def start_at(self, t0_s: float | None) -> None:
        """Scenario fault times count from ``t0_s`` (world time) instead of 0; None holds
        every fault off until a later call. For a world that runs before the mission starts
        (PX4 SITL: its boot and take-off before the landing trigger); height triggers are
        re-armed."""
        self._t0_s = math.inf if t0_s is None else float(t0_s)
        for a in self.all:
            s = a.spec
            if s.trigger_height_m is None:
                a.on, a.off = s.start_s + self._t0_s, s.end_s + self._t0_s
            else:
                a.on = a.off = math.inf
        self.pending = [a for a in self.all if a.spec.trigger_height_m is not None]

    def update_height(self, t: float, height_m: float) -> None:
        """Open height-triggered windows (called by the world each physics sub-step)."""
        for a in self.pending:
            s = a.spec
            if t >= s.start_s + self._t0_s and height_m < s.trigger_height_m:
                a.on = t
                a.off = t + s.duration_s
        self.pending = [a for a in self.pending if a.on == math.inf]

    def active(self, t: float) -> tuple[str, ...]:
        """Types of the faults whose window contains t (for logs)."""
        return tuple(a.name for a in self.all if a.on <= t < a.off)

    # --- camera ----------------------------------------------------------------------------

    def camera_empty(self, t: float) -> bool:
        for a in self.dropout:
            if a.on <= t < a.off:
                if not a.bursts:
                    return True
                dt = t - a.on
                for b0, b1 in a.bursts:
                    if b0 <= dt < b1:
                        return True
                    if b0 > dt:
                        break
        return False

    def beacon_hidden(self, t: float) -> bool:
        return any(a.on <= t < a.off for a in self.occlusion)

    def false_blobs(self, t: float, camera, cam_position_m, r_body_to_world,
                    beacon_m: tuple[float, float, float]) -> list[tuple[int, int, int, int, int]]:
        """Glint blocks for a frame exposed at t (projected through ``camera``)."""
        out: list[tuple[int, int, int, int, int]] = []
        p = camera.params
        for a in self.blobs:
            if not a.on <= t < a.off:
                continue
            s: FalseBlobs = a.spec
            rng = a.rng
            if s.mode == 'persistent':
                if rng.random() < s.rate_per_frame:
                    b = camera.project_blob(cam_position_m, r_body_to_world, a.point, s.size_m,
                                            rng)
                    if b is not None:
                        out.append(b)
                continue
            n = _poisson(rng, s.rate_per_frame)
            for _ in range(n):
                if s.near_beacon_m is None:
                    out.append((p.signature, rng.randrange(p.width_px),
                                rng.randrange(p.height_px), rng.randint(1, 4),
                                rng.randint(1, 4)))
                    continue
                rad = s.near_beacon_m * math.sqrt(rng.random())
                ang = rng.uniform(-math.pi, math.pi)
                pt = (beacon_m[0] + rad * math.cos(ang), beacon_m[1] + rad * math.sin(ang),
                      beacon_m[2])
                b = camera.project_blob(cam_position_m, r_body_to_world, pt, s.size_m, rng)
                if b is not None:
                    out.append(b)
        return out

    # --- lidar, gps, wind ------------------------------------------------------------------

    def lidar(self, t: float, reading: float | None, min_range_m: float,
              max_range_m: float) -> float | None:
        for a in self.lidar_drop:
            if a.on <= t < a.off and a.rng.random() < a.spec.probability:
                return None
        if reading is None:
            return None
        for a in self.lidar_spikes:
            if a.on <= t < a.off:
                s: LidarOutliers = a.spec
                if a.rng.random() < s.probability:
                    sign = (-1.0 if s.direction == 'short' else 1.0 if s.direction == 'long'
                            else (1.0 if a.rng.random() < 0.5 else -1.0))
                    reading = min(max_range_m, max(min_range_m, reading + sign * s.magnitude_m))
        return reading

    def gps_offset(self, t: float) -> tuple[float, float, float] | None:
        dx = dy = dz = 0.0
        hit = False
        for a in self.gps:
            if a.on <= t < a.off:
                hit = True
                dx += a.step[0]
                dy += a.step[1]
                dz += a.step[2]
        return (dx, dy, dz) if hit else None

    def wind_step(self, t: float) -> tuple[float, float, float] | None:
        wx = wy = wz = 0.0
        hit = False
        for a in self.wind:
            if a.on <= t < a.off:
                hit = True
                wx += a.step[0]
                wy += a.step[1]
                wz += a.step[2]
        return (wx, wy, wz) if hit else None


def _poisson(rng: random.Random, lam: float) -> int:
    """Knuth's Poisson sampler (lam <= 10 here)."""
    thresh = math.exp(-lam)
    n = 0
    prod = rng.random()
    while prod > thresh and n < 50:
        n += 1
        prod *= rng.random()
    return n
