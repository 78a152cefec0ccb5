"""apron_estimator.loop: the estimator node's gating, pairing and withholding, without ROS.

What is checked is the contract of the node (package README N2, N3, N8, N10): inputs outside
the stamp window never reach the core, implausible readings are refused and counted, no state
is published without a fresh attitude and position, and the quaternion path of the node gives
the same estimate as the Euler path of the in-process runner.
"""

import math

from apron_estimator.estimator import ApronEstimator
from apron_estimator.loop import MAX_SPECIFIC_FORCE_MPS2, EstimatorLoop
from deckland_common.contract import PixyBlock
from deckland_common.frames import euler_to_quaternion
import pytest

G = 9.81
LEVEL = (1.0, 0.0, 0.0, 0.0)
AT_REST = (0.0, 0.0, G)


def fresh_loop(**kw) -> EstimatorLoop:
    return EstimatorLoop(ApronEstimator(), **kw)


def feed_vehicle(loop, t, now=None, z=1.5):
    now = t if now is None else now
    loop.on_imu(now, t, LEVEL, AT_REST)
    loop.on_position(now, t, (0.0, 0.0, z))
    loop.on_velocity(now, t, (0.0, 0.0, 0.0))
    loop.on_range(now, t, z, 0.05, 40.0)


def test_stale_and_future_stamps_never_reach_the_core():
    loop = fresh_loop(input_timeout_s=0.5)
    assert not loop.on_imu(10.0, 9.4, LEVEL, AT_REST)     # 0.6 s old
    assert not loop.on_imu(10.0, 10.6, LEVEL, AT_REST)    # 0.6 s ahead
    assert not loop.on_range(10.0, 9.0, 1.0, 0.05, 40.0)
    assert not loop.on_blocks(10.0, 11.0, [], [], {'signature': [], 'width': [], 'height': []})
    assert loop.rejected['stale_stamp'] == 2 and loop.rejected['future_stamp'] == 2
    assert loop.last_stamp == dict.fromkeys(('imu', 'odom', 'velocity', 'range', 'camera'))
    assert not loop.estimator._att               # the core saw no attitude at all
    assert loop.on_imu(10.0, 9.6, LEVEL, AT_REST)  # inside the window
    assert loop.last_stamp['imu'] == 9.6


def test_implausible_imu_readings_are_refused_and_counted():
    loop = fresh_loop()
    assert not loop.on_imu(1.0, 1.0, LEVEL, AT_REST, has_orientation=False)   # REP-145
    assert not loop.on_imu(1.0, 1.0, (2.0, 0.0, 0.0, 0.0), AT_REST)           # |q| = 2
    assert not loop.on_imu(1.0, 1.0, (math.nan, 0.0, 0.0, 1.0), AT_REST)
    assert loop.rejected['no_orientation'] == 1
    assert loop.rejected['bad_quaternion'] == 1 and loop.rejected['non_finite'] == 1
    # a 20 g reading: the attitude is fine and used, the acceleration is not
    big = (0.0, 0.0, 20.0 * 9.80665)
    assert big[2] > MAX_SPECIFIC_FORCE_MPS2
    assert loop.on_imu(1.0, 1.0, LEVEL, big)
    assert loop.rejected['implausible'] == 1
    assert loop.last_stamp['imu'] == 1.0
    assert loop.on_imu(1.01, 1.01, LEVEL, (0.0, math.inf, G))   # attitude kept, accel refused
    assert loop.rejected['non_finite'] == 2


def test_no_state_without_a_fresh_attitude_and_position():
    loop = fresh_loop(input_timeout_s=0.5)
    assert loop.publish(1.0) is None and loop.withheld_reason == 'no_attitude'
    loop.on_imu(1.0, 1.0, LEVEL, AT_REST)
    assert loop.publish(1.01) is None and loop.withheld_reason == 'no_position'
    loop.on_position(1.0, 1.0, (0.0, 0.0, 1.5))
    assert loop.publish(1.02) is None               # a position without its velocity: no pair
    loop.on_velocity(1.0, 1.0, (0.0, 0.0, 0.0))
    st = loop.publish(1.03)
    assert st is not None and st.t_s == 1.03 and loop.withheld_reason == ''
    assert loop.publish(1.03) is None and loop.withheld_reason == 'clock_not_advancing'
    assert loop.publish(1.6) is None and loop.withheld_reason == 'no_attitude'  # 0.6 s later
    assert loop.withheld == {'no_attitude': 2, 'no_position': 2, 'non_finite_output': 0,
                             'clock_not_advancing': 1}
    assert loop.published == 1 and loop.triggers['loop'] == 1


def test_position_and_velocity_are_paired_by_stamp():
    loop = fresh_loop(position_pair_tolerance_s=0.005)
    loop.on_position(2.0, 2.0, (1.0, 2.0, 3.0))
    loop.on_velocity(2.0, 2.02, (0.1, 0.2, 0.3))     # 20 ms apart: no pair
    assert loop.t_position_s == -math.inf and loop.estimator._pos is None
    loop.on_position(2.03, 2.022, (1.0, 2.0, 3.0))   # 2 ms from the velocity: paired, once
    assert loop.t_position_s == 2.022
    assert loop.estimator._pos == (2.022, (1.0, 2.0, 3.0), (0.1, 0.2, 0.3))
    loop.on_velocity(2.03, 2.01, (0.0, 0.0, 0.0))    # older than the last pair
    assert loop.rejected['out_of_order'] == 1 and loop.t_position_s == 2.022


def test_imu_clock_thins_to_the_minimum_spacing():
    loop = fresh_loop(imu_min_spacing_s=0.005)
    feed_vehicle(loop, 1.0)
    assert loop.publish_on_imu(1.000) is not None
    assert loop.publish_on_imu(1.002) is None         # 2 ms after the last: thinned
    assert loop.publish_on_imu(1.006) is not None
    assert loop.triggers == {'imu': 2, 'camera': 0, 'imu_thinned': 1, 'loop': 0}


def test_malformed_block_cloud_is_refused_whole():
    loop = fresh_loop()
    feed_vehicle(loop, 1.0)
    assert not loop.on_blocks(1.0, 0.98, [160.0], [100.0], {'signature': [1.0]})
    assert loop.rejected['malformed_cloud'] == 1 and loop.last_stamp['camera'] is None
    ok = loop.on_blocks(1.0, 0.98, [160.0], [100.0],
                        {'signature': [1.0], 'width': [8.0], 'height': [8.0]})
    assert ok and loop.last_stamp['camera'] == 0.98


def test_quaternion_path_equals_the_euler_path():
    """The node (orientation quaternion, specific force) and the runner (Euler angles, world
    acceleration) feed one estimator the same inputs: their states agree to rounding."""
    node, runner = fresh_loop(), fresh_loop()
    roll, pitch, yaw = 0.05, -0.08, 1.2
    q = euler_to_quaternion(roll, pitch, yaw)
    for i in range(60):
        t = 1.0 + 0.01 * i
        # hovering, tilted: the specific force is R^T (0, 0, g) and the world accel is zero
        cr, sr, cp, sp = math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch)
        f = (-sp * G, cp * sr * G, cp * cr * G)
        node.on_imu(t, t, q, f)
        runner.on_attitude(t, t, roll, pitch, yaw)
        runner.on_accel(t, t, (0.0, 0.0, 0.0))
        for loop in (node, runner):
            loop.on_range(t, t, 1.5 / (math.cos(roll) * math.cos(pitch)), 0.05, 40.0)
        node.on_position(t, t, (0.3, -0.2, 1.5))
        node.on_velocity(t, t, (0.0, 0.0, 0.0))
        runner.on_local_position(t, t, (0.3, -0.2, 1.5), (0.0, 0.0, 0.0))
        if i % 2 == 0:
            blocks = [PixyBlock(1, 170.0, 95.0, 6.0, 6.0)]
            node.on_camera(t, t - 0.02, blocks)
            runner.on_camera(t, t - 0.02, blocks)
    a, b = node.publish(1.6), runner.publish(1.6)
    assert a is not None and b is not None and a.tracked and b.tracked
    for x, y in zip(a.to_array(), b.to_array(), strict=True):
        assert x == pytest.approx(y, abs=1e-9)


def test_odom_variances_are_the_filters_or_unknown():
    from apron_estimator.loop import UNKNOWN_VAR

    loop = fresh_loop()
    feed_vehicle(loop, 1.0)
    st = loop.publish(1.0)
    assert not st.tracked
    var = loop.odom_variances(st, 1.0)
    vp = loop.estimator.params.vertical
    assert var[:2] == (UNKNOWN_VAR, UNKNOWN_VAR) and var[3:5] == (UNKNOWN_VAR, UNKNOWN_VAR)
    assert st.vertical.valid   # one lidar sample: the surface is known to altitude + lidar
    assert var[2] == pytest.approx(vp.sigma_altitude_m ** 2 + vp.sigma_lidar_m ** 2)
    assert var[5] == pytest.approx(vp.sigma_vz_mps ** 2)
    values = loop.diagnostic_values(1.5)
    assert values['age_imu_s'] == '0.500' and values['age_camera_s'] == 'inf'
    assert values['published'] == '1'
