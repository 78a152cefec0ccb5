"""Partial ground effect per rotor: the multirotor image model (pure, plain floats).

Sanchez-Cuevas, Heredia, Ollero (Int. J. Aerospace Eng. 2017) add to Cheeseman–Bennett's own
image of a rotor the images of its neighbours and of the body (:func:`multirotor_gain_level`).
Here each image is a source at in-plane distance D: for rotor i at height z_i and source j at
z_j, w_j (R²/4)(z_i+z_j)/(D²+(z_i+z_j)²)^(3/2), w = 1 for a rotor and 4 K_b for the body — the
published formula when all heights are equal. Heights are perpendicular to the surface below
each rotor (deck or ground, tilted); only sources over that same surface count, so rotors off
the pad gain nothing from it and unequal gains make a torque. Clamped as (4). Model, numbers
and sources: docs/world/contact.md.
"""

from __future__ import annotations

from dataclasses import dataclass
import math

from deckland_common.frames import Vec3
from deckland_common.validate import in_range, integer_at_least, non_negative, positive, require

from deck_simulator.contact import Surface
from deck_simulator.rigid_body import RigidBody


@dataclass(frozen=True, slots=True)
class RotorGroundEffectParams:
    """Defaults: the paper's vehicle (Table 2: 10-inch props) and Sanchez-Cuevas et al.'s
    K_b; the clamps are those of (4) (``VehicleParams``)."""

    prop_radius_m: float = 0.127
    body_coeff: float = 2.0          # K_b
    min_height_m: float = 0.05
    max_gain: float = 1.5
    # above this (every rotor), update only every `far_update_every` calls: γ changes by
    # < 1e-3 in that time at closing speeds up to 1 m/s (docs/world/contact.md)
    full_rate_below_m: float = 0.8
    far_update_every: int = 8

    def __post_init__(self) -> None:
        positive('prop_radius_m', self.prop_radius_m)
        non_negative('body_coeff', self.body_coeff)
        positive('min_height_m', self.min_height_m)
        in_range('max_gain', self.max_gain, 1.0, 10.0)
        positive('full_rate_below_m', self.full_rate_below_m)
        integer_at_least('far_update_every', self.far_update_every, 1)


def multirotor_gain_level(z_m: float, prop_radius_m: float, rotor_spacing_m: float,
                          body_distance_m: float, body_coeff: float) -> float:
    """The published formula for a level quadrotor, unclamped (for checks and the docs)."""
    r2 = prop_radius_m * prop_radius_m
    d2, b2, z4 = rotor_spacing_m ** 2, body_distance_m ** 2, 4.0 * z_m * z_m
    s = ((prop_radius_m / (4.0 * z_m)) ** 2 + r2 * z_m / (d2 + z4) ** 1.5
         + 0.5 * r2 * z_m / (2.0 * d2 + z4) ** 1.5
         + 2.0 * r2 * z_m * body_coeff / (b2 + z4) ** 1.5)
    return 1.0 / (1.0 - s)


class RotorGroundEffect:
    """Per-rotor thrust gains γ_i; :meth:`update` from the body pose and the surfaces."""

    __slots__ = ('_bd2', '_d2', '_every', '_full_below', '_rot', '_skip', 'body_coeff', 'centre',
                 'gain', 'height_m', 'max_gain', 'min_h', 'n', 'q_max', 'r2', 'surface_index')

    def __init__(self, params: RotorGroundEffectParams, rotors_body_m: tuple[Vec3, ...],
                 centre_body_m: Vec3 = (0.0, 0.0, 0.0)) -> None:
        require(len(rotors_body_m) >= 1, 'rotors_body_m', 'must name at least one rotor',
                rotors_body_m)
        self.n = len(rotors_body_m)
        self._rot = [float(c) for r in rotors_body_m for c in r]
        self.centre = (float(centre_body_m[0]), float(centre_body_m[1]),
                       float(centre_body_m[2]))
        cx, cy = self.centre[0], self.centre[1]
        # horizontal (body-plane) distances between rotors and from each rotor to the centre
        d2: list[float] = []
        for i in range(self.n):
            for j in range(self.n):
                d2.append((self._rot[3 * i] - self._rot[3 * j]) ** 2
                          + (self._rot[3 * i + 1] - self._rot[3 * j + 1]) ** 2)
        self._d2 = d2
        self._bd2 = [(self._rot[3 * i] - cx) ** 2 + (self._rot[3 * i + 1] - cy) ** 2
                     for i in range(self.n)]
        self.r2 = params.prop_radius_m * params.prop_radius_m
        self.body_coeff = params.body_coeff
        self.min_h = params.min_height_m
        self.max_gain = params.max_gain
        self.q_max = 1.0 - 1.0 / params.max_gain
        self.gain = [1.0] * self.n
        self.height_m = [math.inf] * self.n
        self.surface_index = [-1] * self.n
        self._full_below = params.full_rate_below_m
        self._every = params.far_update_every
        self._skip = 0

    def update(self, body: RigidBody, surfaces: list[Surface]) -> None:
        """γ_i of every rotor now (``gain``), with its height and surface (−1: none below);
        called once per physics tick. Far from every surface, every ``far_update_every``-th
        call only (the gains are held in between)."""
        if self._skip > 0:
            self._skip -= 1
            return
        n = self.n
        rot = self._rot
        hts = self.height_m
        idx = self.surface_index
        for i in range(n):
            qx, qy, qz = body.point_world(rot[3 * i], rot[3 * i + 1], rot[3 * i + 2])
            best = -1
            best_h = math.inf
            for si in range(len(surfaces)):
                a, b, h = surfaces[si].local(qx, qy, qz)
                s = surfaces[si]
                if h >= 0.0 and abs(a) <= s.half_u and abs(b) <= s.half_w and h < best_h:
                    best, best_h = si, h
            idx[i] = best
            hts[i] = best_h if best_h > self.min_h else self.min_h
        low = math.inf
        for i in range(n):
            if hts[i] < low:
                low = hts[i]
        if low > self._full_below:
            self._skip = self._every - 1
        cx, cy, cz = self.centre
        qx, qy, qz = body.point_world(cx, cy, cz)
        r2q = 0.25 * self.r2
        kb = self.body_coeff * self.r2
        for i in range(n):
            si = idx[i]
            if si < 0:
                self.gain[i] = 1.0
                continue
            zi = hts[i]
            s_sum = 0.0
            for j in range(n):
                if idx[j] != si:
                    continue
                z = zi + hts[j]
                q = self._d2[i * n + j] + z * z
                s_sum += r2q * z / (q * math.sqrt(q))
            if kb > 0.0:
                a, b, hc = surfaces[si].local(qx, qy, qz)
                if hc > 0.0 and abs(a) <= surfaces[si].half_u and abs(b) <= surfaces[si].half_w:
                    z = zi + (hc if hc > self.min_h else self.min_h)
                    q = self._bd2[i] + z * z
                    s_sum += kb * z / (q * math.sqrt(q))
            self.gain[i] = self.max_gain if s_sum >= self.q_max else 1.0 / (1.0 - s_sum)
