"""Sensor faults: each does what it says in the camera, lidar and GPS streams, and only that."""

import dataclasses
import math

from deck_simulator.scenario import HeaveSpec, load_scenario
from deck_simulator.sensor_suite import ideal_sensors
from deck_simulator.sensors import project_point
from deck_simulator.world import SENSOR_STREAMS, World
from deckland_common.frames import rot_body_to_world
import pytest

DT = 1.0 / 400.0


def calm(faults=(), heave=None, glint_rate_hz=0.0):
    sc = load_scenario('paper_calm')
    rz = dataclasses.replace(sc.randomize, start_offset_m=0.0, start_yaw_rad=0.0,
                             heave_phase=False)
    ap = dataclasses.replace(sc.apron, heave=heave or HeaveSpec(model='none'))
    cam = dataclasses.replace(sc.sensors.camera, dropout_prob=0.0,
                              false_blob_rate_hz=glint_rate_hz)
    # ideal sensors (truth at their rates, no delay): what is left is the fault
    return dataclasses.replace(sc, randomize=rz, apron=ap, faults=faults,
                               sensors=ideal_sensors(dataclasses.replace(sc.sensors,
                                                                         camera=cam)))


class Hover:
    """A world held above the beacon at 2 m by a P loop on truth; sensor reads at their rates."""

    def __init__(self, faults=(), seed=1, **kw):
        self.w = World(calm(faults, **kw), seed)
        cx, cy, _ = self.w.truth().beacon_position_m
        v = self.w.vehicle
        v.x, v.y, v.z = cx, cy, 2.0
        self.z_ref = 2.0
        for name in SENSOR_STREAMS:   # drop the samples delivered before the vehicle moved
            self.w.delivered(name)

    def run(self, seconds, camera=True, lidar=True, gps=False):
        """(frames, ranges, fixes) as delivered, each (stamp, value), over ``seconds``."""
        w, p = self.w, self.w.params
        w.queued = frozenset(('camera', 'lidar', 'local_position'))
        frames, ranges, fixes = [], [], []
        for k in range(round(seconds / DT)):
            if k % 4 == 0:
                v = w.vehicle
                w.set_command(0.0, 0.0, 0.0, p.mass_kg * (p.gravity_mps2 + 4.0 * (
                    self.z_ref - v.z) - 3.0 * v.vz) / w.truth().gamma)
            w.step(DT)
            ranges.extend(w.delivered('lidar'))
            fixes.extend((t, pv[0]) for t, pv in w.delivered('local_position'))
            frames.extend(w.delivered('camera'))
        return frames if camera else [], ranges if lidar else [], fixes if gps else []


def idle_reads(w, n, dt_s, read):
    """``read()`` after each of n clock moves of ``dt_s`` without physics."""
    out = []
    for _ in range(n):
        w.idle_to(w.t_s + dt_s)
        out.append(read())
    return out


def beacon_blocks(blocks):
    return [b for b in blocks if abs(b[1] - 160) <= 4 and abs(b[2] - 100) <= 4]


def test_occlusion_removes_the_beacon_only_inside_the_window():
    faults = [{'type': 'beacon_occlusion', 'start_s': 2.0, 'end_s': 4.0}]
    frames, _, _ = Hover(faults).run(6.0, lidar=False)
    ref, _, _ = Hover().run(6.0, lidar=False)
    inside = [b for t, b in frames if 2.0 <= t < 4.0]
    outside = [(t, b) for t, b in frames if not 2.0 <= t < 4.0]
    assert len(inside) == pytest.approx(100, abs=2)
    assert all(b == [] for b in inside)
    assert all(len(beacon_blocks(b)) == 1 for _, b in outside)
    # outside the window the frames are exactly the fault-free ones (noise streams aligned)
    assert outside == [(t, b) for t, b in ref if not 2.0 <= t < 4.0]


def test_occlusion_keeps_glints_but_dropout_window_empties_every_frame():
    occl = [{'type': 'beacon_occlusion', 'start_s': 1.0, 'end_s': 3.0}]
    frames, _, _ = Hover(occl, glint_rate_hz=40.0).run(3.0, lidar=False)
    inside = [b for t, b in frames if 1.0 <= t < 3.0]
    assert sum(len(b) for b in inside) > 20            # glints are not occluded
    assert all(not beacon_blocks(b) or len(b) > 1 for b in inside)
    drop = [{'type': 'camera_dropout', 'start_s': 1.0, 'end_s': 3.0}]
    frames, _, _ = Hover(drop, glint_rate_hz=40.0).run(4.0, lidar=False)
    assert all(b == [] for t, b in frames if 1.0 <= t < 3.0)
    assert all(beacon_blocks(b) for t, b in frames if not 1.0 <= t < 3.0)


def test_dropout_bursts_cover_the_expected_fraction_in_runs_of_the_burst_length():
    rate, length = 0.5, 0.3
    faults = [{'type': 'camera_dropout', 'mode': 'bursts', 'burst_rate_hz': rate,
               'burst_length_s': length}]
    w = World(calm(faults), 3)
    cx, cy, _ = w.truth().beacon_position_m
    w.vehicle.x, w.vehicle.y = cx, cy
    # 300 s of frames at 50 Hz; the camera is read without physics
    empty = [f[1] == [] for f in idle_reads(w, 15000, 0.02, w.read_camera)]
    frac = sum(empty) / len(empty)
    # Poisson bursts of fixed length: covered fraction 1 − exp(−λ L)
    assert frac == pytest.approx(1.0 - math.exp(-rate * length), abs=0.035)
    runs, n = [], 0
    for e in empty:          # a run still open at the end is cut short: not counted
        if e:
            n += 1
        elif n:
            runs.append(n)
            n = 0
    # a run is one burst (15 frames) or overlapping bursts (longer)
    assert min(runs) >= round(length / 0.02) - 1
    assert sorted(runs)[len(runs) // 2] == pytest.approx(length / 0.02, abs=1)
    assert len(runs) == pytest.approx(rate * 300 * math.exp(-rate * length), rel=0.25)


def test_persistent_glint_sits_at_its_fixed_world_point_while_the_deck_heaves():
    faults = [{'type': 'false_blobs', 'mode': 'persistent', 'near_beacon_m': 0.6,
               'bearing_rad': 0.0, 'rate_per_frame': 0.9}]
    h = Hover(faults, seed=4, heave=HeaveSpec(model='sine', amplitude_m=0.2, period_s=4.0))
    frames, _, _ = h.run(8.0, lidar=False)
    w = h.w
    point = w.faults.all[0].point
    cx0, cy0 = load_scenario('paper_calm').apron.position_m
    assert point == pytest.approx((cx0 + 0.6, cy0, w.deck_mean_m))
    cam = w.scenario.sensors.camera
    tr = w.truth()
    expected = project_point(cam, tr.position_m, rot_body_to_world(0.0, 0.0, 0.0), point)
    glints = [b for _, b in frames for b in b if not beacon_blocks([b])]
    assert len(glints) / len(frames) == pytest.approx(0.9, abs=0.05)
    # fixed in the world: the same pixel (± noise and the hover's wobble) in every frame,
    # beacon-like size
    for g in glints:
        assert g[1] == pytest.approx(expected[0], abs=3) and g[2] == pytest.approx(
            expected[1], abs=3)
        assert abs(g[3] - cam.fx_px * 0.08 / expected[2]) <= 1.0
    # while the beacon blob follows the heave (depth changes by ±0.2 m → size changes)
    sizes = {b[3] for _, f in frames for b in beacon_blocks(f)}
    assert len(sizes) >= 2


def test_flickering_glints_have_the_given_rate_and_stay_near_the_beacon():
    faults = [{'type': 'false_blobs', 'rate_per_frame': 0.5}]
    w = World(calm(faults), 6)
    cx, cy, top = w.truth().beacon_position_m
    w.vehicle.x, w.vehicle.y, w.vehicle.z = cx, cy, 2.0
    counts = [len(f[1]) - 1 for f in idle_reads(w, 4000, 0.02, w.read_camera)]
    assert sum(counts) / len(counts) == pytest.approx(0.5, abs=0.04)
    # Poisson: P(0) = exp(−0.5)
    assert counts.count(0) / len(counts) == pytest.approx(math.exp(-0.5), abs=0.03)
    near = [{'type': 'false_blobs', 'rate_per_frame': 2.0, 'near_beacon_m': 0.3}]
    w = World(calm(near), 6)
    w.vehicle.x, w.vehicle.y, w.vehicle.z = cx, cy, 2.0
    cam = w.scenario.sensors.camera
    depth = 2.0 - top
    r_px = cam.fx_px * 0.3 / depth
    n = 0
    for frame in idle_reads(w, 500, 0.02, w.read_camera):
        for b in frame[1]:
            n += 1
            assert math.hypot(b[1] - 160, (b[2] - 100) * cam.fx_px / cam.fy_px) <= r_px + 3
    assert n > 900


def test_lidar_dropout_window_and_probability():
    faults = [{'type': 'lidar_dropout', 'start_s': 1.0, 'duration_s': 1.0}]
    _, ranges, _ = Hover(faults).run(3.0, camera=False)
    assert all(r is None for t, r in ranges if 1.0 <= t < 2.0)
    assert all(r == pytest.approx(2.0 - 0.6, abs=0.1) for t, r in ranges
               if not 1.0 <= t < 2.0)
    faults = [{'type': 'lidar_dropout', 'probability': 0.3}]
    w = World(calm(faults), 2)
    reads = idle_reads(w, 5000, 0.01, w.read_lidar)
    assert sum(r is None for r in reads) / len(reads) == pytest.approx(0.3, abs=0.025)


@pytest.mark.parametrize('direction', ['short', 'long', 'both'])
def test_lidar_outliers_at_the_given_rate_and_magnitude(direction):
    faults = [{'type': 'lidar_outliers', 'probability': 0.1, 'magnitude_m': 0.8,
               'direction': direction}]
    a, b = World(calm(), 9), World(calm(faults), 9)
    diffs = [rb - ra for ra, rb in zip(idle_reads(a, 4000, 0.01, a.read_lidar),
                                       idle_reads(b, 4000, 0.01, b.read_lidar), strict=True)]
    spikes = [d for d in diffs if d != 0.0]
    assert len(spikes) / len(diffs) == pytest.approx(0.1, abs=0.015)
    assert all(abs(abs(d) - 0.8) < 1e-9 for d in spikes)
    ups = sum(d > 0 for d in spikes) / len(spikes)
    assert ups == pytest.approx({'short': 0.0, 'long': 1.0, 'both': 0.5}[direction], abs=0.08)


def test_gps_jump_is_a_step_of_the_given_size_from_start_s():
    faults = [{'type': 'gps_jump', 'start_s': 1.0, 'end_s': 2.0, 'magnitude_m': 1.5,
               'bearing_rad': math.pi / 2, 'vertical_m': -0.2}]
    _, _, a = Hover(seed=7).run(3.0, camera=False, lidar=False, gps=True)
    _, _, b = Hover(faults, seed=7).run(3.0, camera=False, lidar=False, gps=True)
    for (t, pa), (_, pb) in zip(a, b, strict=True):
        d = tuple(y - x for x, y in zip(pa, pb, strict=True))
        want = (0.0, 1.5, -0.2) if 1.0 <= t < 2.0 else (0.0, 0.0, 0.0)
        assert d == pytest.approx(want, abs=1e-9)
    # bearing drawn from the seed: the size is the magnitude, the direction varies by seed
    dirs = set()
    for seed in range(5):
        w = World(calm([{'type': 'gps_jump', 'magnitude_m': 1.5}]), seed)
        dx, dy, dz = w.faults.gps_offset(0.0)
        assert math.hypot(dx, dy) == pytest.approx(1.5) and dz == 0.0
        dirs.add(round(math.atan2(dy, dx), 3))
    assert len(dirs) == 5


def test_bad_times_never_raise_or_leak_nan():
    faults = [{'type': 'lidar_outliers', 'probability': 1.0},
              {'type': 'false_blobs', 'rate_per_frame': 3.0, 'near_beacon_m': 0.3},
              {'type': 'gps_jump'}, {'type': 'camera_dropout', 'mode': 'bursts'}]
    w = World(calm(faults), 1)
    w.step(float('nan'))
    w.set_command(float('nan'), 0.0, 0.0, 1.0)
    assert w.rejected == {'nan': 1, 'bad_dt': 1, 'out_of_order': 0}
    for _ in range(50):
        w.step(0.01)
        _, blocks = w.read_camera()
        r = w.read_lidar()
        pos, vel = w.read_local_position()
        assert all(math.isfinite(x) for b in blocks for x in b)
        assert r is None or math.isfinite(r)
        assert all(math.isfinite(x) for x in pos + vel)
