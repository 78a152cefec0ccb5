"""Brown–Conrady lens distortion on normalised optical coordinates (pure, no rclpy).

x_d = x (1 + k1 r² + k2 r⁴) + 2 p1 x y + p2 (r² + 2 x²),
y_d = y (1 + k1 r² + k2 r⁴) + p1 (r² + 2 y²) + 2 p2 x y, r² = x² + y² (x = x_o / z_o).
The simulator's camera distorts with it, the estimator undistorts with it (one model).
"""

from __future__ import annotations

#: The Pixy's lens (radial k1, k2), fitted to ArduPilot AP_IRLock's lens characterisation
#: (docs/world/sensors.md, "Lens"): what a user of the standard Pixy lens configures.
PIXY_K1 = -0.491
PIXY_K2 = 0.306


def distort(x: float, y: float, k1: float, k2: float, p1: float,
            p2: float) -> tuple[float, float]:
    """Normalised undistorted (x, y) → distorted (x_d, y_d)."""
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + k2 * r2)
    return (x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
            y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y)


def undistort(xd: float, yd: float, k1: float, k2: float, p1: float, p2: float,
              iterations: int = 20) -> tuple[float, float]:
    """Inverse of :func:`distort` by fixed-point iteration (the OpenCV scheme)."""
    x, y = xd, yd
    for _ in range(iterations):
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + k2 * r2)
        dx = 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
        dy = p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        x, y = (xd - dx) / radial, (yd - dy) / radial
    return x, y
