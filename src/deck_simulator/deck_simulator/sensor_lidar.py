"""Garmin LIDAR-Lite v3 range: beam footprint against the surfaces below, and its errors (pure).

:meth:`LidarLiteModel.footprint_return` samples the 12 mm, 8 mrad beam with a fixed pattern
of sub-rays against the facing :class:`Surface` patches (pad top, deck, ground), weights the
returns by reflectivity · cos(incidence) / range², blends returns closer than the merge
distance and keeps the strongest group (the footprint is sampled only near an edge).
:meth:`LidarLiteModel.measure` adds the data sheet's errors: per-unit offset and scale, noise
by range tier, a non-linear bias below 1 m, 1 cm resolution, range limits. Sources and
assumptions: docs/world/sensors.md.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
import math

from deckland_common.frames import Vec3

from deck_simulator.sensor_models import ModelStreams, TimingParams
from deckland_common import validate as chk

_GOLDEN_ANGLE = math.pi * (3.0 - math.sqrt(5.0))


class Surface:
    """A reflecting plane patch: a rectangle centred at ``center_m`` with unit ``normal``
    (only its normal side reflects), in-plane unit axis ``u_axis`` (v = normal × u), half
    extents ``half_u_m``/``half_v_m`` (``math.inf``: unbounded) and 905 nm reflectivity.

    Built per sample from the world's truth, so construction does not validate (it costs
    ~50 µs); :meth:`check` does, for surfaces from configuration and for tests.
    """

    __slots__ = ('center_m', 'half_u_m', 'half_v_m', 'normal', 'reflectivity', 'u_axis')

    def __init__(self, center_m: Vec3, normal: Vec3, u_axis: Vec3, half_u_m: float,
                 half_v_m: float, reflectivity: float) -> None:
        self.center_m = center_m
        self.normal = normal
        self.u_axis = u_axis
        self.half_u_m = half_u_m
        self.half_v_m = half_v_m
        self.reflectivity = reflectivity

    def check(self) -> Surface:
        """Validate (ValueError naming the field); returns self."""
        chk.finite_tuple('center_m', self.center_m, 3)
        chk.finite_tuple('normal', self.normal, 3)
        chk.finite_tuple('u_axis', self.u_axis, 3)
        n, u = self.normal, self.u_axis
        chk.require(abs(n[0] ** 2 + n[1] ** 2 + n[2] ** 2 - 1.0) < 1e-6, 'normal',
                    'must be a unit vector', n)
        chk.require(abs(u[0] ** 2 + u[1] ** 2 + u[2] ** 2 - 1.0) < 1e-6
                    and abs(u[0] * n[0] + u[1] * n[1] + u[2] * n[2]) < 1e-6, 'u_axis',
                    'must be a unit vector normal to the normal', u)
        for name, v in (('half_u_m', self.half_u_m), ('half_v_m', self.half_v_m)):
            chk.require(v > 0.0 and not math.isnan(v), name, 'must be > 0 (inf: unbounded)', v)
        chk.in_range('reflectivity', self.reflectivity, 0.0, 1.0)
        return self


def horizontal_rectangle(cx: float, cy: float, z: float, half_x: float, half_y: float,
                         reflectivity: float) -> Surface:
    """An upward-facing, axis-aligned rectangle (e.g. the pad top) at height ``z``."""
    return Surface((cx, cy, z), (0.0, 0.0, 1.0), (1.0, 0.0, 0.0), half_x, half_y, reflectivity)


def ground_plane(reflectivity: float, z: float = 0.0) -> Surface:
    """The unbounded, upward-facing ground at height ``z``."""
    return Surface((0.0, 0.0, z), (0.0, 0.0, 1.0), (1.0, 0.0, 0.0), math.inf, math.inf,
                   reflectivity)


def _timing() -> TimingParams:
    return TimingParams(rate_hz=100.0, latency_s=0.006, latency_jitter_s=0.002,
                        stamp_mode='arrival', assumed_latency_s=0.0, clock_ppm_std=20.0)


@dataclass(frozen=True, slots=True)
class LidarLiteParams:
    """LIDAR-Lite v3 (Garmin operation manual) plus the assumptions marked in docs/world."""

    beam_divergence_rad: float = 0.008     # full angle (data sheet: 8 mrad)
    aperture_diameter_m: float = 0.012     # beam diameter at the aperture (12 ± 2 mm)
    footprint_rays: int = 32
    merge_distance_m: float = 0.3          # returns closer than this blend (assumption)
    reference_reflectivity: float = 0.7    # 40 m range at a 70 % target (data sheet) ...
    max_range_m: float = 40.0              # ... sets the detection threshold
    min_range_m: float = 0.05              # shorter readings are refused
    resolution_m: float = 0.01
    offset_std_m: float = 0.005            # per unit
    scale_std: float = 0.001               # per unit (data sheet: mean error ≤ 1 % of range)
    noise_std_m: float = 0.007             # per sample, 1 m … far_range_m
    far_range_m: float = 5.0
    noise_std_far_m: float = 0.04          # per sample beyond far_range_m (±10 cm typical)
    near_range_m: float = 1.0              # non-linear below (data sheet footnote)
    near_bias_m: float = 0.0               # bias at zero range: none stated (data sheet)
    near_bias_spread: float = 0.5          # per-unit relative σ of near_bias_m
    near_noise_gain: float = 1.0           # σ × (1 + gain (1 − r / near_range_m)) below it
    dropout_prob: float = 0.0              # per sample, no reading
    mount_offset_m: tuple[float, float, float] = (0.0, 0.0, 0.0)   # beam origin, body FLU
    pad_reflectivity: float = 0.8          # 905 nm: white-painted pad
    deck_reflectivity: float = 0.25        # grey deck paint around the pad
    ground_reflectivity: float = 0.3       # concrete
    timing: TimingParams = field(default_factory=_timing)

    def __post_init__(self) -> None:
        for name in ('beam_divergence_rad', 'aperture_diameter_m', 'offset_std_m', 'scale_std',
                     'noise_std_m', 'noise_std_far_m', 'near_bias_spread', 'near_noise_gain',
                     'min_range_m'):
            chk.non_negative(name, getattr(self, name))
        for name in ('merge_distance_m', 'max_range_m', 'resolution_m', 'far_range_m',
                     'near_range_m'):
            chk.positive(name, getattr(self, name))
        chk.integer_at_least('footprint_rays', self.footprint_rays, 1)
        chk.require(0.0 < self.reference_reflectivity <= 1.0, 'reference_reflectivity',
                    'must be in (0, 1]', self.reference_reflectivity)
        chk.require(self.min_range_m < self.max_range_m, 'min_range_m', 'must be < max_range_m',
                    self.min_range_m)
        chk.require(self.near_range_m <= self.far_range_m, 'near_range_m',
                    'must be <= far_range_m', self.near_range_m)
        chk.finite('near_bias_m', self.near_bias_m)
        chk.in_range('dropout_prob', self.dropout_prob, 0.0, 1.0)
        chk.finite_tuple('mount_offset_m', self.mount_offset_m, 3)
        for name in ('pad_reflectivity', 'deck_reflectivity', 'ground_reflectivity'):
            chk.in_range(name, getattr(self, name), 0.0, 1.0)
        chk.require(isinstance(self.timing, TimingParams), 'timing', 'must be TimingParams',
                    self.timing)


def _hit(o0: float, o1: float, o2: float, d0: float, d1: float, d2: float,
         s: Surface) -> tuple[float, float]:
    """(distance along the ray, cos incidence) to surface ``s``, or (−1, 0) if missed."""
    n = s.normal
    dn = d0 * n[0] + d1 * n[1] + d2 * n[2]
    if dn >= -1e-9:                     # parallel, or seen from behind
        return -1.0, 0.0
    c = s.center_m
    t = ((c[0] - o0) * n[0] + (c[1] - o1) * n[1] + (c[2] - o2) * n[2]) / dn
    if t <= 0.0:
        return -1.0, 0.0
    if s.half_u_m != math.inf or s.half_v_m != math.inf:
        h0, h1, h2 = o0 + t * d0 - c[0], o1 + t * d1 - c[1], o2 + t * d2 - c[2]
        u = s.u_axis
        hu = h0 * u[0] + h1 * u[1] + h2 * u[2]
        # v = n × u
        v0, v1, v2 = (n[1] * u[2] - n[2] * u[1], n[2] * u[0] - n[0] * u[2],
                      n[0] * u[1] - n[1] * u[0])
        hv = h0 * v0 + h1 * v1 + h2 * v2
        if abs(hu) > s.half_u_m or abs(hv) > s.half_v_m:
            return -1.0, 0.0
    return t, -dn


def _edge_distance(o0: float, o1: float, o2: float, d0: float, d1: float, d2: float,
                   s: Surface) -> float:
    """In-plane distance from the centre ray's intersection with the plane of ``s`` to the
    rectangle's boundary (inf for an unbounded surface or no intersection ahead)."""
    if s.half_u_m == math.inf and s.half_v_m == math.inf:
        return math.inf
    n = s.normal
    dn = d0 * n[0] + d1 * n[1] + d2 * n[2]
    if abs(dn) < 1e-9:
        return 0.0                      # grazing: sample the footprint
    c = s.center_m
    t = ((c[0] - o0) * n[0] + (c[1] - o1) * n[1] + (c[2] - o2) * n[2]) / dn
    if t <= 0.0:
        return math.inf
    h0, h1, h2 = o0 + t * d0 - c[0], o1 + t * d1 - c[1], o2 + t * d2 - c[2]
    u = s.u_axis
    v0, v1, v2 = (n[1] * u[2] - n[2] * u[1], n[2] * u[0] - n[0] * u[2],
                  n[0] * u[1] - n[1] * u[0])
    du = abs(h0 * u[0] + h1 * u[1] + h2 * u[2]) - s.half_u_m
    dv = abs(h0 * v0 + h1 * v1 + h2 * v2) - s.half_v_m
    if du <= 0.0 and dv <= 0.0:           # inside: distance to the nearest edge
        return min(-du, -dv)
    return math.hypot(max(du, 0.0), max(dv, 0.0))


class LidarLiteModel:
    """One LIDAR-Lite v3 unit: per-unit constants drawn at construction from ``draw``."""

    __slots__ = ('_pattern', '_threshold', 'draw', 'near_bias_m', 'normal', 'offset_m',
                 'params', 'rejected', 'scale')

    def __init__(self, params: LidarLiteParams, streams: ModelStreams) -> None:
        self.params = params
        self.normal = streams.normal
        d = streams.draw
        self.draw = d
        p = params
        self.offset_m = d.gauss(0.0, p.offset_std_m) if p.offset_std_m > 0.0 else 0.0
        self.scale = d.gauss(0.0, p.scale_std) if p.scale_std > 0.0 else 0.0
        self.near_bias_m = p.near_bias_m * (
            1.0 + (d.gauss(0.0, p.near_bias_spread) if p.near_bias_spread > 0.0 else 0.0))
        n = p.footprint_rays
        pattern: list[tuple[float, float]] = []
        for i in range(n):                 # sunflower: uniform over the unit disc
            r = math.sqrt((i + 0.5) / n)
            a = i * _GOLDEN_ANGLE
            pattern.append((r * math.cos(a), r * math.sin(a)))
        self._pattern = pattern
        self._threshold = p.reference_reflectivity / (p.max_range_m * p.max_range_m)
        self.rejected = 0                  # non-finite ranges handed to measure()

    # --- geometry ---------------------------------------------------------------------------

    def footprint_radius_m(self, range_m: float) -> float:
        """Radius of the beam footprint at ``range_m`` (normal incidence)."""
        p = self.params
        return 0.5 * p.aperture_diameter_m + math.tan(0.5 * p.beam_divergence_rad) * range_m

    def footprint_return(self, origin_m: Vec3, direction: Vec3,
                         surfaces: Sequence[Surface]) -> tuple[float, float] | None:
        """Geometric return (range m, strength) of a beam from ``origin_m`` along the unit
        ``direction`` against ``surfaces``; None when nothing strong enough comes back.

        ``strength`` is Σ reflectivity · cos(incidence) / range² over the footprint (1 = a
        perfect Lambertian target at 1 m, normal incidence)."""
        p = self.params
        o0, o1, o2 = origin_m
        d0, d1, d2 = direction
        # the centre ray: nearest facing surface
        best_t, best_c, best_r = math.inf, 0.0, 0.0
        for s in surfaces:
            t, c = _hit(o0, o1, o2, d0, d1, d2, s)
            if 0.0 < t < best_t:
                best_t, best_c, best_r = t, c, s.reflectivity
        if best_t < math.inf:
            # the whole footprint lies on that surface unless some edge is within reach
            margin = 1.05 * self.footprint_radius_m(best_t) / max(best_c, 0.05) + 1e-6
            whole = True
            for s in surfaces:
                if _edge_distance(o0, o1, o2, d0, d1, d2, s) <= margin:
                    whole = False
                    break
            if whole:
                w = best_r * best_c / (best_t * best_t)
                return (best_t, w) if w >= self._threshold else None
        return self._sampled(o0, o1, o2, d0, d1, d2, surfaces, p)

    def _sampled(self, o0: float, o1: float, o2: float, d0: float, d1: float, d2: float,
                 surfaces: Sequence[Surface], p: LidarLiteParams) -> tuple[float, float] | None:
        # unit vectors e1, e2 normal to d
        if abs(d2) < 0.9:
            a0, a1, a2 = d1, -d0, 0.0            # d × e_z
        else:
            a0, a1, a2 = 0.0, d2, -d1            # d × e_x
        na = math.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
        e10, e11, e12 = a0 / na, a1 / na, a2 / na
        e20, e21, e22 = d1 * e12 - d2 * e11, d2 * e10 - d0 * e12, d0 * e11 - d1 * e10
        ra = 0.5 * p.aperture_diameter_m
        tb = math.tan(0.5 * p.beam_divergence_rad)
        per_ray = 1.0 / len(self._pattern)
        hits: list[tuple[float, float]] = []
        for xi, eta in self._pattern:
            q0, q1, q2 = xi * e10 + eta * e20, xi * e11 + eta * e21, xi * e12 + eta * e22
            s0, s1, s2 = o0 + ra * q0, o1 + ra * q1, o2 + ra * q2
            r0, r1, r2 = d0 + tb * q0, d1 + tb * q1, d2 + tb * q2
            nr = math.sqrt(r0 * r0 + r1 * r1 + r2 * r2)
            r0, r1, r2 = r0 / nr, r1 / nr, r2 / nr
            bt, bw = math.inf, 0.0
            for s in surfaces:
                t, c = _hit(s0, s1, s2, r0, r1, r2, s)
                if 0.0 < t < bt:
                    bt, bw = t, s.reflectivity * c
            if bt < math.inf:
                hits.append((bt, per_ray * bw / (bt * bt)))
        if not hits:
            return None
        hits.sort()
        # group returns closer than merge_distance_m; the strongest group wins
        best_range, best_strength = 0.0, -1.0
        g_start, g_w, g_wt = hits[0][0], 0.0, 0.0
        for t, w in hits:
            if t - g_start > p.merge_distance_m:
                if g_w > best_strength:
                    best_range, best_strength = g_wt / g_w, g_w
                g_start, g_w, g_wt = t, 0.0, 0.0
            g_w += w
            g_wt += w * t
        if g_w > best_strength:
            best_range, best_strength = g_wt / g_w, g_w
        if best_strength < self._threshold:
            return None
        return best_range, best_strength

    # --- errors -------------------------------------------------------------------------------

    def bias_m(self, range_m: float) -> float:
        """This unit's systematic error at ``range_m``."""
        p = self.params
        b = self.offset_m + self.scale * range_m
        if range_m < p.near_range_m:
            x = 1.0 - range_m / p.near_range_m
            b += self.near_bias_m * x * x
        return b

    def noise_std_m(self, range_m: float) -> float:
        """Per-sample σ of the white error at ``range_m``."""
        p = self.params
        if range_m >= p.far_range_m:
            return p.noise_std_far_m
        if range_m < p.near_range_m:
            return p.noise_std_m * (1.0 + p.near_noise_gain * (1.0 - range_m / p.near_range_m))
        return p.noise_std_m

    def measure(self, true_range_m: float | None) -> float | None:
        """One reading (m, multiple of the resolution) of a geometric return, or None.

        Draws one normal and one uniform per call whatever the outcome, so the streams stay
        aligned across returns and misses. A non-finite range is refused (``rejected``)."""
        p = self.params
        n = self.normal()
        u = self.draw.random()
        if true_range_m is None or u < p.dropout_prob:
            return None
        if not math.isfinite(true_range_m):
            self.rejected += 1
            return None
        r = true_range_m + self.bias_m(true_range_m) + self.noise_std_m(true_range_m) * n
        r = round(r / p.resolution_m) * p.resolution_m
        if r < p.min_range_m or r > p.max_range_m:
            return None
        return r

    def sample(self, origin_m: Vec3, direction: Vec3,
               surfaces: Sequence[Surface]) -> float | None:
        """Geometry then errors: the reading the autopilot gets for this beam."""
        ret = self.footprint_return(origin_m, direction, surfaces)
        return self.measure(None if ret is None else ret[0])
