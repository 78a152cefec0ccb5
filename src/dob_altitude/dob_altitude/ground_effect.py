"""Nominal ground-effect gain γ of the paper's (4) (Cheeseman–Bennett), pure and hot-path safe.

More in the package README, "Module notes" (`dob_altitude.ground_effect`).
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
