"""apron_estimator.inputs: the pure topic → estimator-input conversions (no ROS).

Expected values come from physics (a hovering / resting vehicle has zero acceleration, a
coordinated tilt accelerates at g·tanθ toward the nose) and from REP-117 / REP-145 and the
pixy/blocks layout of docs/interfaces.md, not from the implementation.
"""

import math
import random

from apron_estimator.inputs import (
    LocalPositionPairer,
    blocks_from_cloud,
    lidar_range,
    rotate_body_to_world,
    world_accel_from_specific_force,
)
from deckland_common.contract import PixyBlock
from deckland_common.frames import (
    attitude_from_quaternion,
    euler_to_quaternion,
    mat_t_vec,
    mat_vec,
    normalised_quaternion,
    rot_body_to_world,
)
import pytest

G = 9.81


def q_of(roll, pitch, yaw):
    return euler_to_quaternion(roll, pitch, yaw)


# --- specific force → world acceleration -----------------------------------------------------

@pytest.mark.parametrize('yaw', [0.0, 1.0, math.pi / 2, -2.5, math.pi])
def test_level_hover_reads_zero_acceleration(yaw):
    """Level and hovering: the accelerometer reads (0, 0, +g) in FLU (REP-145) → a = 0."""
    a = world_accel_from_specific_force(q_of(0.0, 0.0, yaw), (0.0, 0.0, G), G)
    assert a == pytest.approx((0.0, 0.0, 0.0), abs=1e-12)


def test_free_fall_reads_minus_g():
    """Specific force 0 (free fall) → a = (0, 0, −g) whatever the attitude."""
    a = world_accel_from_specific_force(q_of(0.3, -0.2, 2.0), (0.0, 0.0, 0.0), G)
    assert a == pytest.approx((0.0, 0.0, -G), abs=1e-12)


@pytest.mark.parametrize('theta_deg', [5.0, 10.0, 20.0])
def test_coordinated_pitch_accelerates_toward_the_nose(theta_deg):
    """Pitch θ (nose down, FLU positive), thrust T/m = g / cosθ along body z: the vertical
    components cancel and the vehicle accelerates at g·tanθ toward the nose. Nose east
    (yaw 0) → +x; nose north (yaw π/2) → +y."""
    th = math.radians(theta_deg)
    f = (0.0, 0.0, G / math.cos(th))
    east = world_accel_from_specific_force(q_of(0.0, th, 0.0), f, G)
    assert east == pytest.approx((G * math.tan(th), 0.0, 0.0), abs=1e-9)
    north = world_accel_from_specific_force(q_of(0.0, th, math.pi / 2), f, G)
    assert north == pytest.approx((0.0, G * math.tan(th), 0.0), abs=1e-9)


def test_coordinated_roll_accelerates_to_the_right():
    """Positive FLU roll lowers the right side: at yaw 0 the right is −y (south)."""
    ph = math.radians(12.0)
    a = world_accel_from_specific_force(q_of(ph, 0.0, 0.0), (0.0, 0.0, G / math.cos(ph)), G)
    assert a == pytest.approx((0.0, -G * math.tan(ph), 0.0), abs=1e-9)


def test_resting_tilted_vehicle_reads_zero_acceleration():
    """At rest on a slope the accelerometer reads Rᵀ (0, 0, g) (it has components along the
    body x and y axes), and the conversion must give a = 0 for any attitude."""
    rng = random.Random(7)
    for _ in range(500):
        r, p, y = rng.uniform(-0.6, 0.6), rng.uniform(-0.6, 0.6), rng.uniform(-math.pi, math.pi)
        f = mat_t_vec(rot_body_to_world(r, p, y), (0.0, 0.0, G))
        a = world_accel_from_specific_force(q_of(r, p, y), f, G)
        assert a == pytest.approx((0.0, 0.0, 0.0), abs=1e-9)


def test_quaternion_rotation_matches_the_zyx_matrix():
    rng = random.Random(11)
    for _ in range(500):
        r, p, y = (rng.uniform(-math.pi, math.pi), rng.uniform(-1.5, 1.5),
                   rng.uniform(-math.pi, math.pi))
        v = (rng.uniform(-5, 5), rng.uniform(-5, 5), rng.uniform(-5, 5))
        assert rotate_body_to_world(q_of(r, p, y), v) == pytest.approx(
            mat_vec(rot_body_to_world(r, p, y), v), abs=1e-9)


def test_non_finite_acceleration_is_refused():
    q = q_of(0.0, 0.0, 0.0)
    assert world_accel_from_specific_force(q, (math.nan, 0.0, G), G) is None
    assert world_accel_from_specific_force(q, (0.0, math.inf, G), G) is None
    assert world_accel_from_specific_force((math.nan, 0.0, 0.0, 0.0), (0.0, 0.0, G), G) is None
    assert world_accel_from_specific_force(q, (0.0, 0.0), G) is None  # wrong size


# --- orientation ---------------------------------------------------------------------------

def test_attitude_round_trip_and_normalisation():
    w, x, y, z = q_of(0.1, -0.2, 2.0)
    assert attitude_from_quaternion(w, x, y, z) == pytest.approx((0.1, -0.2, 2.0), abs=1e-12)
    # slightly off-norm (float32 telemetry) is normalised, not refused
    s = 1.03
    assert attitude_from_quaternion(s * w, s * x, s * y, s * z) == pytest.approx(
        (0.1, -0.2, 2.0), abs=1e-12)
    assert sum(c * c for c in normalised_quaternion(s * w, s * x, s * y, s * z)) == (
        pytest.approx(1.0))


def test_bad_quaternions_are_refused():
    assert attitude_from_quaternion(0.0, 0.0, 0.0, 0.0) is None     # the default message
    assert attitude_from_quaternion(2.0, 0.0, 0.0, 0.0) is None
    assert attitude_from_quaternion(math.nan, 0.0, 0.0, 1.0) is None
    assert attitude_from_quaternion(1.0, math.inf, 0.0, 0.0) is None


# --- lidar ---------------------------------------------------------------------------------

def test_lidar_range_rep117():
    assert lidar_range(2.5, 0.05, 40.0) == 2.5
    assert lidar_range(math.inf, 0.05, 40.0) is None     # no return
    assert lidar_range(-math.inf, 0.05, 40.0) is None    # too close
    assert lidar_range(41.0, 0.05, 40.0) is None         # beyond max
    assert lidar_range(0.01, 0.05, 40.0) is None         # below min
    assert lidar_range(40.0, 0.05, 40.0) == 40.0         # closed interval
    assert lidar_range(3.0, 0.0, 0.0) == 3.0             # limits unset: not applied
    assert lidar_range(3.0, math.nan, 40.0) == 3.0
    assert math.isnan(lidar_range(math.nan, 0.05, 40.0))  # passed on for the core to count


# --- point cloud ---------------------------------------------------------------------------

def test_blocks_from_cloud_layout():
    ch = {'signature': [1.0, 2.0], 'width': [10.0, 4.0], 'height': [8.0, 3.0]}
    blocks = blocks_from_cloud([100.0, 200.0], [50.0, 150.0], ch)
    assert blocks == [PixyBlock(1, 100.0, 50.0, 10.0, 8.0), PixyBlock(2, 200.0, 150.0, 4.0, 3.0)]
    assert isinstance(blocks[0].signature, int)
    assert blocks_from_cloud([], [], {'signature': [], 'width': [], 'height': []}) == []


def test_inconsistent_clouds_are_malformed():
    ok = {'signature': [1.0], 'width': [10.0], 'height': [8.0]}
    assert blocks_from_cloud([1.0], [2.0], ok) is not None
    assert blocks_from_cloud([1.0], [2.0], {'signature': [1.0], 'width': [10.0]}) is None
    assert blocks_from_cloud([1.0], [2.0], dict(ok, width=[1.0, 2.0])) is None
    assert blocks_from_cloud([1.0, 2.0], [2.0, 3.0], ok) is None
    assert blocks_from_cloud([1.0], [], ok) is None
    assert blocks_from_cloud([], [], {}) is None  # channels are required even when empty


def test_bad_signatures_match_no_beacon():
    ch = {'signature': [math.nan, 1.5, -3.0, 7.0], 'width': [1.0] * 4, 'height': [1.0] * 4}
    sigs = [b.signature for b in blocks_from_cloud([1.0] * 4, [1.0] * 4, ch)]
    assert sigs == [-1, -1, -1, 7]


# --- position / velocity pairing -------------------------------------------------------------

def test_pairer_joins_either_order_once():
    p = LocalPositionPairer(0.005)
    assert p.on_position(1.0, (1.0, 2.0, 3.0)) is None
    out = p.on_velocity(1.0, (0.1, 0.2, 0.3))
    assert (out.t_s, out.position_m, out.velocity_mps) == (1.0, (1.0, 2.0, 3.0), (0.1, 0.2, 0.3))
    assert p.on_velocity(1.0, (0.1, 0.2, 0.3)) is None          # never twice
    assert p.on_velocity(1.02, (0.5, 0.5, 0.5)) is None         # waits for its position
    out = p.on_position(1.02, (4.0, 5.0, 6.0))
    assert (out.t_s, out.velocity_mps) == (1.02, (0.5, 0.5, 0.5))
    out = p.on_position(1.043, (7.0, 7.0, 7.0))
    assert out is None                                          # 23 ms apart: not a pair
    assert p.on_velocity(1.041, (0.0, 0.0, 0.0)).t_s == 1.043   # 2 ms apart: later stamp


def test_pairer_ignores_old_and_non_finite_stamps():
    p = LocalPositionPairer(0.005)
    p.on_position(2.0, (0.0, 0.0, 0.0))
    assert p.on_velocity(2.0, (0.0, 0.0, 0.0)) is not None
    p.on_position(1.5, (0.0, 0.0, 0.0))
    assert p.on_velocity(1.5, (0.0, 0.0, 0.0)) is None          # older than the last pair
    assert p.on_position(math.nan, (0.0, 0.0, 0.0)) is None
    assert p.on_velocity(math.nan, (0.0, 0.0, 0.0)) is None
    with pytest.raises(ValueError, match='tolerance_s'):
        LocalPositionPairer(-1.0)


