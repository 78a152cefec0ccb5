"""Nominal ground-effect gain γ of the paper's (4) (Cheeseman–Bennett), pure and hot-path safe.

    γ = 1 / (1 − ρ r² / (4 z_p)²)                                                  (4)

with ρ the (nominal ρ̄ in the controller, true ρ in the simulator) coefficient, r the propeller
radius and z_p the height of the rotor plane above the surface. (4) diverges at
z_p = r √ρ / 4 and is meaningless below it, so the height is clamped from below and the gain
from above, as every implementation does near contact.

Edge cases (decided here, tested in ``test/dob_altitude/test_ground_effect.py``):

* ``rotor_height_m`` below ``min_height_m`` (including negative: lidar noise at contact, a
  rotor plane estimated below the deck) → clamped to ``min_height_m``, i.e. *near* the ground.
* NaN → treated like the clamp (near the ground). A missing height is most likely close to
  the deck (short-range lidar dropouts), and assuming "far" there would under-estimate γ and
  command the ballooning the ground effect causes. The controllers never reach this branch:
  they reject a NaN input before computing γ̄.
* −inf → clamp (it is below every height); +inf → 1.0, the exact limit of (4) for z_p → ∞
  (REP-117 reports "no return / out of range" as +inf, which means far from any surface).
* The result is always in ``[1, max_gain]`` (ρ ≤ 0 gives 1).
"""

from __future__ import annotations

import math


def ground_effect_gain(rho: float, prop_radius_m: float, rotor_height_m: float,
                       min_height_m: float = 0.05, max_gain: float = 1.5) -> float:
    """γ of (4) for a rotor plane ``rotor_height_m`` above the surface, clamped to [1, max_gain].

    Args:
        rho: ρ of (4) (≥ 0; the classic value is 1).
        prop_radius_m: propeller radius r (m).
        rotor_height_m: z_p, rotor plane above the surface (m); see the module docstring for
            negative, NaN and infinite values.
        min_height_m: lower clamp of z_p (m, > 0).
        max_gain: upper clamp of γ (≥ 1).
    """
    z_p = rotor_height_m
    if not z_p >= min_height_m:  # also catches NaN and −inf
        z_p = min_height_m
    elif z_p == math.inf:
        return 1.0
    ratio = prop_radius_m / (4.0 * z_p)
    q = rho * ratio * ratio  # ρ r² / (4 z_p)²
    if q <= 0.0:
        return 1.0
    if q >= 1.0 - 1.0 / max_gain:  # 1/(1 − q) ≥ max_gain (also guards q ≥ 1)
        return max_gain
    return 1.0 / (1.0 - q)  # (4)
