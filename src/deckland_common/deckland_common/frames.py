"""Frame conventions shared by every deckland package (pure, no rclpy).

World ``map`` ENU, body ``base_link`` FLU (REP-103); attitude the intrinsic Z-Y-X sequence,
``R = Rz(ψ) Ry(θ) Rx(φ)`` body → world, whose third column is the thrust direction of the
paper's model (2): positive pitch noses down and accelerates forward, positive roll lowers the
right side (accelerates to −y), yaw 0 points east. NED/FRD only at the MAVLink boundary
(:func:`euler_enu_flu_to_ned_frd` and friends). Received orientations → Euler angles with the
norm check: :func:`attitude_from_quaternion`. The conventions in full, with the camera's
optical frame: docs/interfaces.md, "Frames".
"""

from __future__ import annotations

import math

Vec3 = tuple[float, float, float]
Mat3 = tuple[Vec3, Vec3, Vec3]


def rot_body_to_world(roll_rad: float, pitch_rad: float, yaw_rad: float) -> Mat3:
    """Rotation matrix R = Rz(ψ) Ry(θ) Rx(φ) taking FLU body vectors to ENU world vectors."""
    cr, sr = math.cos(roll_rad), math.sin(roll_rad)
    cp, sp = math.cos(pitch_rad), math.sin(pitch_rad)
    cy, sy = math.cos(yaw_rad), math.sin(yaw_rad)
    return (
        (cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr),
        (sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr),
        (-sp, cp * sr, cp * cr),
    )


def mat_vec(m: Mat3, v: Vec3) -> Vec3:
    """m · v for a 3×3 tuple matrix."""
    return (
        m[0][0] * v[0] + m[0][1] * v[1] + m[0][2] * v[2],
        m[1][0] * v[0] + m[1][1] * v[1] + m[1][2] * v[2],
        m[2][0] * v[0] + m[2][1] * v[1] + m[2][2] * v[2],
    )


def mat_t_vec(m: Mat3, v: Vec3) -> Vec3:
    """mᵀ · v (world-to-body when m is body-to-world)."""
    return (
        m[0][0] * v[0] + m[1][0] * v[1] + m[2][0] * v[2],
        m[0][1] * v[0] + m[1][1] * v[1] + m[2][1] * v[2],
        m[0][2] * v[0] + m[1][2] * v[1] + m[2][2] * v[2],
    )


def world_to_body_xy(x: float, y: float, yaw_rad: float) -> tuple[float, float]:
    """Rotate a horizontal ENU vector into the yaw-only (heading) frame, FLU axes."""
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    return c * x + s * y, -s * x + c * y


def body_to_world_xy(x: float, y: float, yaw_rad: float) -> tuple[float, float]:
    """Rotate a horizontal heading-frame (FLU) vector into ENU."""
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    return c * x - s * y, s * x + c * y


def euler_to_quaternion(roll_rad: float, pitch_rad: float, yaw_rad: float) -> tuple[
        float, float, float, float]:
    """Z-Y-X Euler angles to a unit quaternion (w, x, y, z) of the same rotation."""
    cr, sr = math.cos(roll_rad / 2.0), math.sin(roll_rad / 2.0)
    cp, sp = math.cos(pitch_rad / 2.0), math.sin(pitch_rad / 2.0)
    cy, sy = math.cos(yaw_rad / 2.0), math.sin(yaw_rad / 2.0)
    return (
        cr * cp * cy + sr * sp * sy,
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
    )


def quaternion_to_euler(w: float, x: float, y: float, z: float) -> Vec3:
    """Unit quaternion (w, x, y, z) to Z-Y-X Euler angles (roll, pitch, yaw) in radians."""
    roll = math.atan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y))
    sinp = max(-1.0, min(1.0, 2.0 * (w * y - z * x)))
    pitch = math.asin(sinp)
    yaw = math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    return roll, pitch, yaw


#: Largest accepted | |q| − 1 | of a received orientation quaternion before it is refused.
QUATERNION_NORM_TOLERANCE = 0.05


def normalised_quaternion(w: float, x: float, y: float, z: float,
                          tolerance: float = QUATERNION_NORM_TOLERANCE
                          ) -> tuple[float, float, float, float] | None:
    """(w, x, y, z) scaled to unit norm, or None if not finite or | |q| − 1 | > tolerance."""
    if not (math.isfinite(w) and math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
        return None
    n = math.sqrt(w * w + x * x + y * y + z * z)
    if abs(n - 1.0) > tolerance:
        return None
    return w / n, x / n, y / n, z / n


def attitude_from_quaternion(w: float, x: float, y: float, z: float,
                             tolerance: float = QUATERNION_NORM_TOLERANCE) -> Vec3 | None:
    """A received orientation (``base_link`` in ``map``) → Z-Y-X (roll, pitch, yaw) in rad.

    None when the quaternion is not finite or not (nearly) unit
    (:func:`normalised_quaternion`); otherwise it is normalised first.
    """
    q = normalised_quaternion(w, x, y, z, tolerance)
    if q is None:
        return None
    return quaternion_to_euler(q[0], q[1], q[2], q[3])


def wrap_pi(angle_rad: float) -> float:
    """Wrap an angle to [−π, π)."""
    return (angle_rad + math.pi) % (2.0 * math.pi) - math.pi


# --- MAVLink boundary only -------------------------------------------------------------------

def enu_to_ned(x: float, y: float, z: float) -> Vec3:
    """ENU vector → NED vector (positions, velocities, accelerations)."""
    return y, x, -z


def ned_to_enu(n: float, e: float, d: float) -> Vec3:
    """NED vector → ENU vector."""
    return e, n, -d


def flu_to_frd(x: float, y: float, z: float) -> Vec3:
    """FLU body vector → FRD body vector."""
    return x, -y, -z


def frd_to_flu(x: float, y: float, z: float) -> Vec3:
    """FRD body vector → FLU body vector."""
    return x, -y, -z


def euler_enu_flu_to_ned_frd(roll_rad: float, pitch_rad: float, yaw_rad: float) -> Vec3:
    """Attitude of FLU in ENU → attitude of FRD in NED (Z-Y-X Euler both sides)."""
    return roll_rad, -pitch_rad, wrap_pi(math.pi / 2.0 - yaw_rad)


def euler_ned_frd_to_enu_flu(roll_rad: float, pitch_rad: float, yaw_rad: float) -> Vec3:
    """Attitude of FRD in NED → attitude of FLU in ENU (Z-Y-X Euler both sides)."""
    return roll_rad, -pitch_rad, wrap_pi(math.pi / 2.0 - yaw_rad)
