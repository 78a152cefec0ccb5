"""Building blocks of the honest sensor models (pure): named streams, error processes, timing.

Every model (:mod:`~deck_simulator.sensor_imu`, :mod:`~deck_simulator.sensor_ekf`,
:mod:`~deck_simulator.sensor_lidar`, :mod:`~deck_simulator.sensor_camera`, bundled by
:mod:`~deck_simulator.sensor_suite`) draws its per-seed constants from a ``draw`` stream, its
per-sample Gaussian noise from a ``normal`` source and its timing jitter from a ``timing``
stream, each named after the seed and the sensor (:func:`model_streams`), so a sensor's draws
depend only on how many samples *it* produced. :class:`SensorTiming` is the sensor's own clock
plus a FIFO delay line: a sample taken at t is delivered at t + latency and carries a stamp
with a small error. Defaults and their sources: docs/world/sensors.md.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
import math
import random
from typing import Generic, TypeVar

from deckland_common.frames import Mat3, Vec3

from deck_simulator.sensors import Normal, normal_stream
from deckland_common import validate as chk

T = TypeVar('T')

STAMP_MODES = ('sample', 'arrival')


@dataclass(frozen=True, slots=True)
class ModelStreams:
    """The three independent random sources of one sensor model."""

    draw: random.Random      # per-seed constants: turn-on biases, calibration errors
    normal: Normal           # per-sample N(0, 1) noise
    timing: random.Random    # per-seed clock phase, clock rate error, stamp offset
    timing_normal: Normal    # per-sample latency and stamp jitter


def model_streams(seed: int, name: str) -> ModelStreams:
    """Streams ``f'{seed}:{name}:draw'``, ``...:noise`` (normal), ``...:timing`` and
    ``...:timing_noise`` (normal).

    The names differ from those :class:`~deck_simulator.world.World` uses today
    (``'{seed}:imu'``, ``'{seed}:imu:normal'``), so adding a model never shifts them.
    """
    return ModelStreams(random.Random(f'{seed}:{name}:draw'),
                        normal_stream(f'{seed}:{name}:noise'),
                        random.Random(f'{seed}:{name}:timing'),
                        normal_stream(f'{seed}:{name}:timing_noise'))


def gauss_normal(rng: random.Random) -> Normal:
    """A ``Normal`` drawn from ``rng.gauss`` (tests and callers without numpy streams)."""
    gauss = rng.gauss
    return lambda: gauss(0.0, 1.0)


def _row(r: Vec3, b: Mat3) -> Vec3:
    return (r[0] * b[0][0] + r[1] * b[1][0] + r[2] * b[2][0],
            r[0] * b[0][1] + r[1] * b[1][1] + r[2] * b[2][1],
            r[0] * b[0][2] + r[1] * b[1][2] + r[2] * b[2][2])


def mat_mul(a: Mat3, b: Mat3) -> Mat3:
    """a · b for 3×3 tuple matrices."""
    return _row(a[0], b), _row(a[1], b), _row(a[2], b)


# --- error processes: exact discretisations ------------------------------------------------

def white_sigma(density: float, dt_s: float) -> float:
    """σ of one sample averaging white noise of density N over dt: N / √dt (the Allan
    deviation of the sequence is then N / √τ, i.e. N at τ = 1 s, as data sheets quote it)."""
    return density / math.sqrt(dt_s)


def ou_coefficients(dt_s: float, tau_s: float, sigma: float) -> tuple[float, float]:
    """First-order Gauss–Markov x ← a x + q n with a = exp(−dt/τ), q = σ √(1 − a²) (exact,
    stationary σ, autocorrelation exp(−|lag|/τ))."""
    a = math.exp(-dt_s / tau_s)
    return a, sigma * math.sqrt(1.0 - a * a)


def random_walk_from_instability(instability: float, density: float) -> float:
    """Rate-random-walk coefficient K (units/√s) whose Allan curve with the white noise N,
    σ(τ)² = N²/τ + K²τ/3, has its minimum at the data sheet's bias instability B:
    the minimum is 2NK/√3 at τ* = √3 N / K, so K = √3 B² / (2N). Zero if B or N is zero."""
    if instability <= 0.0 or density <= 0.0:
        return 0.0
    return math.sqrt(3.0) * instability * instability / (2.0 * density)


# --- timing -------------------------------------------------------------------------------

@dataclass(frozen=True, slots=True)
class TimingParams:
    """A sensor's own sample clock, its delivery latency and the error of its stamps.

    ``stamp_mode``: ``'sample'`` — the sensor stamps the sample in its own clock, translated
    to the receiver's with a per-seed offset (σ ``stamp_offset_std_s``) and a per-sample jitter
    (σ ``stamp_jitter_s``); ``'arrival'`` — the receiver stamps at arrival minus the latency it
    assumes (``assumed_latency_s``), so the stamp error is the latency's own error (plus the same
    offset and jitter terms, for the receiver's clock).
    """

    rate_hz: float
    latency_s: float = 0.0           # mean of sample → delivery
    latency_jitter_s: float = 0.0    # σ of the per-sample latency (log-normal, > 0, FIFO)
    stamp_mode: str = 'sample'
    assumed_latency_s: float = 0.0   # 'arrival': subtracted from the arrival time
    stamp_offset_std_s: float = 0.0  # per seed, constant
    stamp_jitter_s: float = 0.0      # per sample
    clock_ppm_std: float = 0.0       # per seed rate error of the sample clock (ppm)
    random_phase: bool = True        # first sample uniformly within one period (per seed)

    def __post_init__(self) -> None:
        chk.positive('rate_hz', self.rate_hz)
        for name in ('latency_s', 'latency_jitter_s', 'assumed_latency_s', 'stamp_offset_std_s',
                     'stamp_jitter_s', 'clock_ppm_std'):
            chk.non_negative(name, getattr(self, name))
        chk.require(self.latency_jitter_s == 0.0 or self.latency_s > 0.0, 'latency_jitter_s',
                    'must be 0 when latency_s is 0 (the latency is log-normal, > 0)',
                    self.latency_jitter_s)
        chk.require(self.latency_jitter_s <= self.latency_s, 'latency_jitter_s',
                    'must be <= latency_s', self.latency_jitter_s)
        chk.require(self.latency_s < 10.0, 'latency_s', 'must be < 10 s', self.latency_s)
        chk.require(self.clock_ppm_std < 1e4, 'clock_ppm_std', 'must be < 1e4 ppm',
                    self.clock_ppm_std)
        chk.one_of('stamp_mode', self.stamp_mode, STAMP_MODES)
        chk.require(isinstance(self.random_phase, bool), 'random_phase', 'must be a bool',
                    self.random_phase)


class SensorTiming(Generic[T]):
    """Sample clock + FIFO delay line of one sensor, deterministic for its timing streams.

    Per seed (at construction, from ``rng``, in this order): clock phase, clock rate error,
    stamp offset. Per sample (at :meth:`push`, from ``normal``): latency, then stamp jitter.
    The draws depend only on the number of samples pushed, never on how often the consumer
    polls. The latency is log-normal with the configured mean and σ (positive, right-skewed
    like scheduling delays); a sample never overtakes the one before it.

    Use: ``while timing.next_sample_s <= t: ts = timing.take(); timing.push(ts, model(ts))``,
    then ``timing.pop(t)`` → ``[(stamp, value), ...]`` delivered by ``t`` in order.
    """

    __slots__ = ('_assumed', '_k', '_last_deliver', '_latency', '_ln_mu', '_ln_sigma',
                 '_normal', '_queue', '_stamp_jitter', '_t0', 'arrival', 'next_sample_s',
                 'params', 'period_s', 'stamp_offset_s')

    def __init__(self, params: TimingParams, rng: random.Random, normal: Normal,
                 start_s: float = 0.0) -> None:
        self.params = params
        self._normal = normal
        p = params
        phase = rng.random() if p.random_phase else 0.0
        ppm = rng.gauss(0.0, p.clock_ppm_std) if p.clock_ppm_std > 0.0 else 0.0
        self.stamp_offset_s = (rng.gauss(0.0, p.stamp_offset_std_s)
                               if p.stamp_offset_std_s > 0.0 else 0.0)
        self.period_s = (1.0 / p.rate_hz) * (1.0 + ppm * 1e-6)
        self._t0 = start_s + phase * self.period_s
        self._k = 0
        self.next_sample_s = self._t0
        self._latency = p.latency_s
        j = p.latency_jitter_s
        # log-normal with mean L and σ J: s² = ln(1 + J²/L²), μ = ln L − s²/2
        s2 = math.log1p((j / p.latency_s) ** 2) if j > 0.0 else 0.0
        self._ln_sigma = math.sqrt(s2)
        self._ln_mu = math.log(p.latency_s) - 0.5 * s2 if j > 0.0 else 0.0
        self._stamp_jitter = p.stamp_jitter_s
        self.arrival = p.stamp_mode == 'arrival'
        self._assumed = p.assumed_latency_s
        self._last_deliver = -math.inf
        self._queue: deque[tuple[float, float, T]] = deque()

    def take(self) -> float:
        """The next sample time (``next_sample_s``); advances the clock."""
        t = self.next_sample_s
        self._k += 1
        self.next_sample_s = self._t0 + self._k * self.period_s
        return t

    def push(self, sample_s: float, value: T) -> tuple[float, float]:
        """Queue ``value`` sampled at ``sample_s``; returns its (delivery time, stamp)."""
        lat = (math.exp(self._ln_mu + self._ln_sigma * self._normal()) if self._ln_sigma > 0.0
               else self._latency)
        deliver = sample_s + lat
        if deliver < self._last_deliver:       # a serial link does not reorder
            deliver = self._last_deliver
        self._last_deliver = deliver
        base = deliver - self._assumed if self.arrival else sample_s
        stamp = base + self.stamp_offset_s
        if self._stamp_jitter > 0.0:
            stamp += self._stamp_jitter * self._normal()
        self._queue.append((deliver, stamp, value))
        return deliver, stamp

    def pop(self, t_s: float) -> list[tuple[float, T]]:
        """Every ``(stamp, value)`` delivered by ``t_s``, oldest first (removed from the line)."""
        q = self._queue
        out: list[tuple[float, T]] = []
        while q and q[0][0] <= t_s:
            d = q.popleft()
            out.append((d[1], d[2]))
        return out

    def next_delivery_s(self) -> float:
        """When the oldest queued sample is delivered (inf: none queued)."""
        q = self._queue
        return q[0][0] if q else math.inf

    def pending(self) -> int:
        """Samples taken but not yet delivered."""
        return len(self._queue)
