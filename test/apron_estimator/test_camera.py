"""Camera model (27)-(30) and our (35): round trips against an independent forward projection."""

import math
import random

from apron_estimator.camera import CameraModel, CameraParams
from deckland_common.frames import mat_t_vec, rot_body_to_world, world_to_body_xy
import pytest

#: the pinhole of (29)-(30): these tests are about the geometry (the lens: test_lens_*)
PINHOLE = {'k1': 0.0, 'k2': 0.0}
FX = 160.0 / math.tan(math.radians(30.0))   # (W/2) / tan(fov_x / 2)
FY = 100.0 / math.tan(math.radians(23.5))


def project(rel_world, roll, pitch, yaw, offset=(0.0, 0.0, 0.0), mount=(0.0, 0.0, 0.0)):
    """Independent forward model: world offset of the beacon from the body origin → pixels.

    world → body with R(φ,θ,ψ)ᵀ, minus the camera offset, → mount frame with R_mountᵀ, →
    optical (x = −y_b, y = −x_b, z = −z_b), → pinhole. Returns None behind the lens.
    """
    b = mat_t_vec(rot_body_to_world(roll, pitch, yaw), rel_world)
    b = (b[0] - offset[0], b[1] - offset[1], b[2] - offset[2])
    b = mat_t_vec(rot_body_to_world(*mount), b)
    ox, oy, oz = -b[1], -b[0], -b[2]
    if oz <= 0.0:
        return None
    return 160.0 + FX * ox / oz, 100.0 + FY * oy / oz


def in_image(pix):
    return pix is not None and 0.0 <= pix[0] <= 319.0 and 0.0 <= pix[1] <= 199.0


def test_focal_length_uses_half_of_the_full_fov():
    p = CameraParams(**PINHOLE)
    assert p.fx_px == pytest.approx(FX)
    assert p.fy_px == pytest.approx(FY)
    # the image edge is at half the full FOV
    cam = CameraModel(p)
    _dx, dy = cam.relative_position(319.9999, 100.0, 1.0, 0.0, 0.0, 0.0)
    assert math.degrees(math.atan2(-dy, 1.0)) == pytest.approx(30.0, abs=1e-3)


def test_default_mount_image_top_is_the_nose():
    cam = CameraModel(CameraParams(**PINHOLE))
    # beacon straight ahead of the nose (yaw 0 = east) appears above the centre
    pix = project((1.0, 0.0, -2.0), 0.0, 0.0, 0.0)
    assert pix[1] < 100.0 and pix[0] == pytest.approx(160.0)
    # beacon to the left (north at yaw 0) appears left of the centre
    pix = project((0.0, 1.0, -2.0), 0.0, 0.0, 0.0)
    assert pix[0] < 160.0 and pix[1] == pytest.approx(100.0)
    assert cam.relative_position(*pix, 2.0, 0.0, 0.0, 0.0) == pytest.approx((0.0, 1.0))


def test_round_trip_many_attitudes_and_heights():
    rng = random.Random(1234)
    cam = CameraModel(CameraParams(**PINHOLE))
    n = 0
    worst = 0.0
    while n < 3000:
        h = rng.uniform(0.3, 5.0)
        roll = math.radians(rng.uniform(-15.0, 15.0))
        pitch = math.radians(rng.uniform(-15.0, 15.0))
        yaw = rng.uniform(-math.pi, math.pi)
        truth = (rng.uniform(-0.6, 0.6) * h, rng.uniform(-0.6, 0.6) * h)
        pix = project((truth[0], truth[1], -h), roll, pitch, yaw)
        if not in_image(pix):
            continue
        n += 1
        got = cam.relative_position(pix[0], pix[1], h, roll, pitch, yaw)
        assert got is not None
        worst = max(worst, math.hypot(got[0] - truth[0], got[1] - truth[1]))
    assert worst < 1e-9
    # and every quadrant of yaw was exercised on a fixed case
    for yaw_deg in (10.0, 100.0, -170.0, -80.0):
        yaw = math.radians(yaw_deg)
        pix = project((0.4, -0.3, -1.2), 0.1, -0.12, yaw)
        got = cam.relative_position(pix[0], pix[1], 1.2, 0.1, -0.12, yaw)
        assert got == pytest.approx((0.4, -0.3), abs=1e-9)


def test_round_trip_with_mount_offset_and_rotation():
    rng = random.Random(7)
    offset = (0.08, -0.03, -0.05)
    mount = (0.02, -0.05, 0.1)
    cam = CameraModel(CameraParams(**PINHOLE, mount_x_m=offset[0], mount_y_m=offset[1],
                                   mount_z_m=offset[2], mount_roll_rad=mount[0],
                                   mount_pitch_rad=mount[1], mount_yaw_rad=mount[2]))
    n = 0
    while n < 500:
        h = rng.uniform(0.3, 5.0)
        att = (math.radians(rng.uniform(-15, 15)), math.radians(rng.uniform(-15, 15)),
               rng.uniform(-math.pi, math.pi))
        truth = (rng.uniform(-0.5, 0.5) * h, rng.uniform(-0.5, 0.5) * h)
        pix = project((truth[0], truth[1], -h), *att, offset=offset, mount=mount)
        if not in_image(pix):
            continue
        n += 1
        got = cam.relative_position(pix[0], pix[1], h, *att)
        assert got == pytest.approx(truth, abs=1e-9)


def test_mount_pitch_acts_like_vehicle_pitch():
    tilted = CameraModel(CameraParams(**PINHOLE, mount_pitch_rad=0.2))
    level = CameraModel(CameraParams(**PINHOLE))
    for px, py in ((30.0, 20.0), (160.0, 100.0), (300.0, 180.0)):
        assert tilted.relative_position(px, py, 2.0, 0.0, 0.0, 0.0) == pytest.approx(
            level.relative_position(px, py, 2.0, 0.0, 0.2, 0.0), abs=1e-12)


def test_quantised_pixels_give_mm_to_cm_level_errors():
    rng = random.Random(99)
    cam = CameraModel(CameraParams(**PINHOLE))
    errs = []
    while len(errs) < 500:
        h = rng.uniform(0.3, 5.0)
        att = (math.radians(rng.uniform(-15, 15)), math.radians(rng.uniform(-15, 15)),
               rng.uniform(-math.pi, math.pi))
        truth = (rng.uniform(-0.5, 0.5) * h, rng.uniform(-0.5, 0.5) * h)
        pix = project((truth[0], truth[1], -h), *att)
        if not in_image(pix):
            continue
        got = cam.relative_position(round(pix[0]), round(pix[1]), h, *att)
        errs.append(math.hypot(got[0] - truth[0], got[1] - truth[1]) / h)
    # half a pixel is 0.5 / 230 ≈ 2.2 mm per metre of height (plus obliquity)
    assert max(errs) < 0.004


def test_paper_exact_matches_29_30_at_zero_tilt():
    paper = CameraModel(CameraParams(paper_exact=True))
    ours = CameraModel(CameraParams(**PINHOLE))
    tan_ax = math.tan(math.radians(30.0))
    tan_ay = math.tan(math.radians(23.5))
    for px, py, z, yaw in ((40.0, 30.0, 1.5, 0.0), (250.0, 170.0, 3.0, 2.0),
                           (160.0, 100.0, 0.5, -1.0)):
        y_paper = z * tan_ax / 160.0 * (px - 160.0)        # (29), body y to the right
        x_paper = -z * tan_ay / 100.0 * (py - 100.0)       # (30)
        rel = paper.relative_position(px, py, z, 0.0, 0.0, yaw)
        assert world_to_body_xy(rel[0], rel[1], yaw) == pytest.approx((x_paper, -y_paper))
        assert rel == pytest.approx(ours.relative_position(px, py, z, 0.0, 0.0, yaw))


def test_paper_exact_is_off_by_about_26_cm_at_10_deg_and_1p5_m():
    paper = CameraModel(CameraParams(paper_exact=True))
    ours = CameraModel(CameraParams(**PINHOLE))
    h = 1.5
    for roll, pitch in ((0.0, math.radians(10.0)), (math.radians(10.0), 0.0)):
        for yaw in (0.0, 1.0, -2.5):
            pix = project((0.0, 0.0, -h), roll, pitch, yaw)  # beacon straight below
            lidar_range = h / (math.cos(roll) * math.cos(pitch))   # the paper's z
            err_paper = math.hypot(*paper.relative_position(*pix, lidar_range, roll, pitch, yaw))
            err_ours = math.hypot(*ours.relative_position(*pix, h, roll, pitch, yaw))
            assert 0.25 < err_paper < 0.28   # ≈ range · tan 10° = 0.269 m
            assert err_ours < 1e-9


def test_printed_35_versus_ours():
    """Printed (35) = rotation of a body vector with y to the *left* by a compass heading ψ_c
    (clockwise from north) into ENU. Fed with (29)'s y to the right it mirrors the lateral
    axis; our rel_ENU = Rz(ψ) (x, −y_paper) is right."""
    def printed_35(x, y, psi):
        s, c = math.sin(psi), math.cos(psi)
        return s * x - c * y, c * x + s * y

    rng = random.Random(3)
    cam = CameraModel(CameraParams(**PINHOLE))
    for _ in range(50):
        yaw = rng.uniform(-math.pi, math.pi)
        truth = (rng.uniform(-1, 1), rng.uniform(-1, 1))
        pix = project((truth[0], truth[1], -2.0), 0.0, 0.0, yaw)
        z = 2.0
        y_paper = z * math.tan(math.radians(30.0)) / 160.0 * (pix[0] - 160.0)
        x_paper = -z * math.tan(math.radians(23.5)) / 100.0 * (pix[1] - 100.0)
        compass = math.pi / 2.0 - yaw
        assert printed_35(x_paper, -y_paper, compass) == pytest.approx(truth, abs=1e-9)
        assert cam.relative_position(*pix, z, 0.0, 0.0, yaw) == pytest.approx(truth, abs=1e-9)
    # as printed with y_paper the lateral axis is mirrored (unless the beacon is dead ahead)
    yaw = 0.3
    pix = project((0.2, 0.9, -2.0), 0.0, 0.0, yaw)
    y_paper = 2.0 * math.tan(math.radians(30.0)) / 160.0 * (pix[0] - 160.0)
    x_paper = -2.0 * math.tan(math.radians(23.5)) / 100.0 * (pix[1] - 100.0)
    wrong = printed_35(x_paper, y_paper, math.pi / 2.0 - yaw)
    assert math.hypot(wrong[0] - 0.2, wrong[1] - 0.9) > 0.5


def test_ray_missing_the_deck_returns_none():
    cam = CameraModel(CameraParams(**PINHOLE))
    # rolled 80°: the top-left pixel looks above the horizon
    assert cam.relative_position(0.0, 0.0, 1.0, math.radians(80.0), 0.0, 0.0) is None


@pytest.mark.parametrize('kwargs', [
    {'fov_x_deg': 0.0}, {'fov_y_deg': float('nan')}, {'width_px': -1.0},
    {'cx_px': 400.0}, {'mount_pitch_rad': 4.0}, {'paper_exact': 1}, {'k1': float('inf')},
    {'p2': 0.5}])
def test_bad_params_raise_naming_the_field(kwargs):
    with pytest.raises(ValueError, match=next(iter(kwargs))):
        CameraParams(**kwargs)


def test_lens_the_default_is_the_pixy_lens_and_undistorts_its_pixels_exactly():
    """A pixel imaged through the Pixy lens (deckland_common.lens.distort, the simulator's
    model) comes back to the true offset to 1e-9, over the image and at any attitude."""
    from deckland_common.lens import PIXY_K1, PIXY_K2, distort
    cam = CameraModel()
    assert (cam.params.k1, cam.params.k2) == (PIXY_K1, PIXY_K2)
    rng = random.Random(7)
    n = worst = 0
    while n < 2000:
        h = rng.uniform(0.2, 5.0)
        roll, pitch = (math.radians(rng.uniform(-15.0, 15.0)) for _ in range(2))
        yaw = rng.uniform(-math.pi, math.pi)
        truth = (rng.uniform(-0.6, 0.6) * h, rng.uniform(-0.6, 0.6) * h)
        pix = project((truth[0], truth[1], -h), roll, pitch, yaw)
        if not in_image(pix):
            continue
        xd, yd = distort((pix[0] - 160.0) / FX, (pix[1] - 100.0) / FY, PIXY_K1, PIXY_K2,
                         0.0, 0.0)
        got = cam.relative_position(160.0 + FX * xd, 100.0 + FY * yd, h, roll, pitch, yaw)
        n += 1
        worst = max(worst, math.hypot(got[0] - truth[0], got[1] - truth[1]))
    assert worst < 1e-9


def test_lens_ignored_the_pixy_barrel_pulls_edge_offsets_in_by_a_tenth():
    """Why the estimator undistorts: the pinhole reading of a Pixy pixel near the image edge
    is ~10 % short (13 % at the wide edge): a loop gain below one, a drift at touchdown."""
    from deckland_common.lens import PIXY_K1, PIXY_K2, distort
    pinhole = CameraModel(CameraParams(**PINHOLE))
    xd, yd = distort(0.0, -0.5, PIXY_K1, PIXY_K2, 0.0, 0.0)   # 0.5 m ahead at 1 m (optical y = −x)
    short = pinhole.relative_position(160.0 + FX * xd, 100.0 + FY * yd, 1.0, 0.0, 0.0, 0.0)
    assert short[0] == pytest.approx(0.5 * (1.0 + PIXY_K1 * 0.25 + PIXY_K2 * 0.0625))
    assert 0.08 < 1.0 - short[0] / 0.5 < 0.12
    assert CameraModel().relative_position(160.0 + FX * xd, 100.0 + FY * yd, 1.0, 0.0, 0.0,
                                           0.0) == pytest.approx((0.5, 0.0), abs=1e-9)
