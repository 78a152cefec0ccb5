"""Sensor truth geometry (camera pinhole through the tilted body, lidar ray) and noise."""

import math
import random
import statistics

from deck_simulator.sensors import (
    Camera,
    CameraParams,
    Gps,
    GpsParams,
    Lidar,
    LidarParams,
    lidar_true_range,
    project_point,
)
from deckland_common.frames import rot_body_to_world
import pytest

EXACT = CameraParams(pixel_noise_px=0.0, dropout_prob=0.0)
FX = 160.0 / math.tan(math.radians(30.0))
FY = 100.0 / math.tan(math.radians(23.5))


def frame(params, pos, rpy, beacon, seed=0, t=0.0):
    return Camera(params, random.Random(seed)).frame(t, pos, rot_body_to_world(*rpy), beacon)


def test_focal_lengths_from_full_fov():
    assert EXACT.fx_px == pytest.approx(FX) and EXACT.fy_px == pytest.approx(FY)


def test_beacon_straight_below_is_image_centre():
    assert frame(EXACT, (1.0, 2.0, 3.0), (0, 0, 0.7), (1.0, 2.0, 0.5)) == [
        (1, 160, 100, round(FX * 0.08 / 2.5), round(FY * 0.08 / 2.5))]


@pytest.mark.parametrize('yaw', [0.0, math.pi / 2, -2.0])
def test_known_offsets_give_hand_computed_pixels(yaw):
    fwd, left, depth = 0.4, -0.3, 2.0     # beacon ahead and to the right in the heading frame
    c, s = math.cos(yaw), math.sin(yaw)
    beacon = (5.0 + c * fwd - s * left, -1.0 + s * fwd + c * left, 3.0 - depth)
    u, v, z = project_point(EXACT, (5.0, -1.0, 3.0), rot_body_to_world(0, 0, yaw), beacon)
    assert z == pytest.approx(depth)
    assert u == pytest.approx(160.0 + FX * (-left) / depth)     # right of the centre
    assert v == pytest.approx(100.0 + FY * (-fwd) / depth)      # ahead = toward the image top
    (_, ui, vi, _, _), = frame(EXACT, (5.0, -1.0, 3.0), (0, 0, yaw), beacon)
    assert (ui, vi) == (round(u), round(v))


def test_tilt_shifts_the_image_the_right_way():
    pos, beacon = (0.0, 0.0, 2.0), (0.0, 0.0, 0.0)
    th = 0.1
    # nose down (positive pitch) → camera looks back → beacon below moves toward the top
    u, v, _ = project_point(EXACT, pos, rot_body_to_world(0.0, th, 0.0), beacon)
    assert (u, v) == pytest.approx((160.0, 100.0 - FY * math.tan(th)))
    # right side down (positive roll) → camera looks left → beacon moves right
    u, v, _ = project_point(EXACT, pos, rot_body_to_world(th, 0.0, 0.0), beacon)
    assert (u, v) == pytest.approx((160.0 + FX * math.tan(th), 100.0))


def test_visibility_frame_range_and_dropout():
    pos = (0.0, 0.0, 2.0)
    # 1.5 m ahead at 2 m depth: v = 100 − FY·0.75 < 0 → outside the 47° FOV
    assert frame(EXACT, pos, (0, 0, 0), (1.5, 0.0, 0.0)) == []
    assert frame(EXACT, pos, (0, 0, 0), (0.5, 0.0, 0.0)) != []
    far = CameraParams(pixel_noise_px=0.0, dropout_prob=0.0, max_range_m=1.5)
    assert frame(far, pos, (0, 0, 0), (0.0, 0.0, 0.0)) == []
    gone = CameraParams(pixel_noise_px=0.0, dropout_prob=1.0)
    assert frame(gone, pos, (0, 0, 0), (0.0, 0.0, 0.0)) == []
    # beacon above the camera (behind the image plane)
    assert frame(EXACT, pos, (0, 0, 0), (0.0, 0.0, 3.0)) == []


def test_pixel_noise_is_unbiased_and_quantised():
    cam = Camera(CameraParams(pixel_noise_px=0.5, dropout_prob=0.0), random.Random(4))
    r = rot_body_to_world(0, 0, 0)
    xs = []
    for k in range(3000):
        (_, x, y, _, _), = cam.frame(k * 0.02, (0.0, 0.0, 2.0), r, (0.1, 0.0, 0.0))
        assert isinstance(x, int) and isinstance(y, int)
        xs.append(y)
    exact = 100.0 - FY * 0.1 / 2.0
    assert statistics.fmean(xs) == pytest.approx(exact, abs=0.05)
    # rounding adds 1/12 px² to the variance of N(0, 0.5²)
    assert statistics.pstdev(xs) == pytest.approx(math.sqrt(0.25 + 1 / 12), rel=0.1)


def test_false_blobs_poisson_rate_and_lifetime():
    p = CameraParams(dropout_prob=1.0, false_blob_rate_hz=10.0, false_blob_lifetime_s=0.06)
    cam = Camera(p, random.Random(9))
    r = rot_body_to_world(0, 0, 0)
    counts = [len(cam.frame(k * 0.02, (0, 0, 2.0), r, (0, 0, 0))) for k in range(20000)]
    # glints born in the last 3 frame intervals are alive: mean = rate · 3 · 0.02
    assert statistics.fmean(counts) == pytest.approx(10.0 * 0.06, rel=0.1)
    assert max(counts) < 10


def test_lidar_hits_pad_or_ground_along_tilted_ray():
    half = (0.525, 0.425)
    level = rot_body_to_world(0, 0, 0)
    assert lidar_true_range((0, 0, 2.0), level, (5.0, 5.0), 0.6, half) == pytest.approx(2.0)
    assert lidar_true_range((5, 5, 2.0), level, (5.0, 5.0), 0.6, half) == pytest.approx(1.4)
    th = 0.2
    tilted = rot_body_to_world(0, th, 0)     # ray goes backward (−x)
    assert lidar_true_range((0, 0, 2.0), tilted, (5, 5), 0.6, half) == pytest.approx(
        2.0 / math.cos(th))
    # centre over the pad's −x edge region, ray tilted back off the pad → ground
    assert lidar_true_range((4.6, 5.0, 2.0), tilted, (5, 5), 0.6, half) == pytest.approx(
        2.0 / math.cos(th))
    # centre just outside the +x edge, ray tilted back onto the pad → pad top
    assert lidar_true_range((5.6, 5.0, 2.0), tilted, (5, 5), 0.6, half) == pytest.approx(
        1.4 / math.cos(th))
    assert lidar_true_range((0, 0, 2.0), rot_body_to_world(math.pi, 0, 0), (5, 5), 0.6,
                            half) is None


def test_lidar_noise_limits_and_no_return():
    lid = Lidar(LidarParams(noise_m=0.02), random.Random(2))
    xs = [lid.read(3.0) for _ in range(4000)]
    assert statistics.fmean(xs) == pytest.approx(3.0, abs=0.002)
    assert statistics.pstdev(xs) == pytest.approx(0.02, rel=0.1)
    assert lid.read(None) is None and lid.read(41.0) is None and lid.read(0.01) is None


def test_gps_bias_statistics_across_seeds_and_ou_decay():
    p = GpsParams(bias_std_m=0.7, bias_tau_s=90.0)
    b0 = [Gps(p, random.Random(s)).bx for s in range(2000)]
    assert statistics.pstdev(b0) == pytest.approx(0.7, rel=0.08)
    # the bias decorrelates with τ: corr(b(0), b(τ)) ≈ e^-1
    pairs = []
    for s in range(2000):
        g = Gps(p, random.Random(s))
        x0 = g.bx
        g.read(0.0, (0, 0, 0), (0, 0, 0))
        g.read(90.0, (0, 0, 0), (0, 0, 0))
        pairs.append((x0, g.bx))
    a = [x for x, _ in pairs]
    b = [y for _, y in pairs]
    assert statistics.correlation(a, b) == pytest.approx(math.exp(-1.0), abs=0.06)
    assert statistics.pstdev(b) == pytest.approx(0.7, rel=0.08)   # stationary


def test_camera_params_validation():
    with pytest.raises(ValueError, match='fov_x_deg'):
        CameraParams(fov_x_deg=0.0)
    with pytest.raises(ValueError, match='dropout_prob'):
        CameraParams(dropout_prob=1.5)
    with pytest.raises(ValueError, match='min_range_m'):
        LidarParams(min_range_m=50.0)
