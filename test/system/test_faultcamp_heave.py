"""False blobs on a heaving deck (issue 6): the estimator tells the beacon from a glint by the
surface under each hypothesis, and neither the deck's heave nor the camera's scale change at a
deck edge may fool it (README of apron_estimator, "False blobs").

The world here is built from physics, independent of deck_simulator: a 1.05 x 0.85 m pad whose
top heaves as a triangle wave, the beacon at its centre, a glint at a fixed world point, a level
vehicle at a fixed altitude that flies toward the track (as the planner does) and hovers there.
The lidar sees the surface under the vehicle; the camera sees each blob at the height *of that
blob* (the estimator only knows the height above the surface under the vehicle).
"""

from __future__ import annotations

import math

from apron_estimator.camera import CameraParams
from apron_estimator.estimator import ApronEstimator
from apron_estimator.vertical import VerticalFilter
from deckland_common.contract import PixyBlock
import pytest

DT = 0.01                    # sensors at 100 Hz, camera at 50 Hz
HALF = (0.525, 0.425)        # pad half sizes (m)
DECK_MEAN_M = 0.6
ALTITUDE_M = 2.3             # vehicle, world
CAM = CameraParams()


def _triangle(t: float, stroke: float, speed: float, phase: float) -> float:
    """Deck top height: triangle wave of the given stroke and speed around DECK_MEAN_M."""
    period = 2.0 * stroke / speed
    u = ((t / period + phase) % 1.0) * 2.0          # 0..2
    up = u if u <= 1.0 else 2.0 - u                  # 0..1..0
    return DECK_MEAN_M + stroke * (up - 0.5)


def _on_pad(x: float, y: float) -> bool:
    return abs(x) <= HALF[0] and abs(y) <= HALF[1]


class _World:
    """Heaving pad, beacon at (0, 0) on it, a glint at ``glint_xy`` (on the pad top if it lies
    on the pad, else on the ground); a level vehicle following the estimator's track."""

    def __init__(self, glint_xy: tuple[float, float], stroke: float, speed: float,
                 phase: float) -> None:
        self.glint = glint_xy
        self.deck = lambda t: _triangle(t, stroke, speed, phase)
        self.est = ApronEstimator()
        self.t = 0.0
        self.x = self.y = 0.0
        self.vx = self.vy = 0.0

    def _block(self, bx: float, by: float, bz: float, size: float) -> PixyBlock | None:
        d = ALTITUDE_M - bz                    # the blob's true depth below the camera
        # default mount, level, yaw 0: rel_x = −v·d, rel_y = −u·d (CameraModel.ray_body)
        px = CAM.cx_px - CAM.fx_px * (by - self.y) / d
        py = CAM.cy_px - CAM.fy_px * (bx - self.x) / d
        if not (0.0 <= px <= CAM.width_px and 0.0 <= py <= CAM.height_px):
            return None
        return PixyBlock(1, px, py, size, size)

    def step(self, speed_mps: float = 0.4) -> None:
        t = self.t
        deck = self.deck(t)
        est = self.est
        est.on_attitude(t, 0.0, 0.0, 0.0)
        est.on_local_position(t, (self.x, self.y, ALTITUDE_M), (self.vx, self.vy, 0.0))
        surface = deck if _on_pad(self.x, self.y) else 0.0
        est.on_lidar(t, ALTITUDE_M - surface)
        if round(t / DT) % 2 == 0:
            gz = deck if _on_pad(*self.glint) else 0.0
            blocks = [self._block(0.0, 0.0, deck, 12.0),
                      self._block(self.glint[0], self.glint[1], gz, 10.0)]
            est.on_camera(t, [b for b in blocks if b is not None])
        # fly toward the track like the planner's ALIGN slew, first-order velocity loop
        st = est.state(t)
        rx, ry = st.rel_position_m if st.tracked else (0.0, 0.0)
        n = math.hypot(rx, ry)
        cx, cy = (rx, ry) if n <= speed_mps else (rx * speed_mps / n, ry * speed_mps / n)
        ax, ay = (cx - self.vx) / 0.3, (cy - self.vy) / 0.3
        est.on_accel(t, (ax, ay, 0.0))
        self.vx += ax * DT
        self.vy += ay * DT
        self.x += self.vx * DT
        self.y += self.vy * DT
        self.t = round(t + DT, 9)

    def run(self, seconds: float) -> None:
        for _ in range(round(seconds / DT)):
            self.step()

    @property
    def tracker(self):
        return self.est.horizontal

    def track_error(self, world_xy: tuple[float, float]) -> float:
        st = self.est.state(self.t)
        return math.hypot(st.rel_position_m[0] - (world_xy[0] - self.x),
                          st.rel_position_m[1] - (world_xy[1] - self.y))


PHASES = [k / 8 for k in range(8)]


@pytest.mark.parametrize('phase', PHASES)
def test_a_glint_on_the_heaving_deck_never_rejects_the_beacon(phase):
    """Beacon and glint on the same (deck) surface: no lidar evidence tells them apart, so
    the target must stay ambiguous (the planner holds). Before, surfaces sampled seconds
    apart on a deck heaving 0.6 m at 0.3 m/s differed by more than ``deck_rise_m``: at some
    heave phases the beacon's sample (trough) lost to the glint's (crest) and the beacon was
    rejected."""
    w = _World((-0.3, 0.2), stroke=0.6, speed=0.3, phase=phase)
    w.run(25.0)
    tr = w.tracker
    assert tr.events['probes'] >= 1                   # the glint was visited
    assert tr.events['rivals_rejected'] == 0, 'a hypothesis on the same surface was rejected'
    assert tr.ambiguous


@pytest.mark.parametrize('phase', PHASES)
def test_a_glint_beside_the_heaving_deck_is_rejected_and_the_track_ends_on_the_beacon(phase):
    """Glint on the ground 5 cm off the pad's long edge (like campaign seed 300020): the
    lidar over it sees the ground (0.45-0.75 m below the deck top, heave or not), so it is
    rejected once, and the track returns to the beacon and stays there. Before, the rivals'
    offsets were not rescaled when the surface under the vehicle changed (the camera offsets
    scale with the height above it): the beacon seen from over the ground no longer matched
    its own rival, became a new unvisited 'rival' and was probed again and again."""
    w = _World((0.2, -(HALF[1] + 0.05)), stroke=0.3, speed=0.09, phase=phase)
    w.run(30.0)
    tr = w.tracker
    assert not tr.ambiguous
    assert tr.events['rivals_rejected'] >= 1
    assert tr.events['probes'] <= 2, f"endless probing: {tr.events['probes']} probes"
    assert w.track_error((0.0, 0.0)) < 0.1
    assert math.hypot(w.x, w.y) < 0.15                # the vehicle hovers over the beacon


def test_the_surface_level_ignores_the_heave_and_counts_the_deck_edge():
    """VerticalFilter.surface_level_m: constant while a deck heaves 0.3 m under a hovering
    vehicle; it changes by the deck's height when the lidar crosses the edge onto the
    ground. The absolute surface estimate follows the heave (what fooled the rival test)."""
    vf = VerticalFilter()
    t = 0.0
    levels, surfaces = [], []
    for k in range(1500):                             # 15 s over the deck
        deck = _triangle(t, 0.3, 0.09, 0.0)
        vf.on_accel(t, 0.0)
        vf.on_altitude(t, ALTITUDE_M, 0.0)
        vf.on_lidar(t, ALTITUDE_M - deck)
        if k > 100:
            levels.append(vf.surface_level_m)
            surfaces.append(vf.state(t).surface_height_m)
        t = round(t + DT, 9)
    assert max(levels) - min(levels) < 0.02
    assert max(surfaces) - min(surfaces) > 0.25
    before = vf.surface_level_m
    deck = _triangle(t, 0.3, 0.09, 0.0)
    for _ in range(100):                              # now over the ground
        vf.on_accel(t, 0.0)
        vf.on_altitude(t, ALTITUDE_M, 0.0)
        vf.on_lidar(t, ALTITUDE_M)
        t = round(t + DT, 9)
    assert vf.surface_level_m - before == pytest.approx(-deck, abs=0.05)


def test_rescale_scales_the_rivals_with_the_track():
    """A surface re-base changes the scale of every camera offset measured from then on:
    the rivals' offsets are such measurements, so they scale with the track's state."""
    from apron_estimator.horizontal import HorizontalTracker
    tr = HorizontalTracker()
    t = 0.0
    for _ in range(20):
        t += 0.02
        tr.update(t, [(0.0, 0.0), (0.6, 0.0)], 1.5, 0.0)
    assert len(tr.rivals) == 1
    dx = tr.rivals[0].dx
    tr.rescale(1.4)
    assert tr.rivals[0].dx == pytest.approx(1.4 * dx)


# --- where the surface is seen: the lowest level, at the lidar spot -------------------------

def _hover_track(tr, t, seconds, rel_glint, surface, spot=(0.0, 0.0), vehicle=(0.0, 0.0),
                 start=None):
    """Frames at 50 Hz: beacon at the origin, glint at rel_glint (world); the vehicle flies
    at constant speed from ``start`` (default: already there) to ``vehicle``."""
    n = round(seconds / 0.02)
    a = start if start is not None else vehicle
    for k in range(1, n + 1):
        t += 0.02
        f = k / n
        vx, vy = a[0] + f * (vehicle[0] - a[0]), a[1] + f * (vehicle[1] - a[1])
        tr.on_accel(t, 0.0, 0.0)
        tr.update(t, [(-vx, -vy), (rel_glint[0] - vx, rel_glint[1] - vy)], 1.4, surface,
                  spot)
    return t


def test_ground_seen_near_a_hypothesis_marks_it_even_if_the_deck_follows():
    """Campaign seed 100058: hovering over a glint 0.1 m beside the pad the lidar saw the
    ground; leaving it (still within verify_radius_m) it saw the deck. A running average took
    the glint's level up to 0.44 m (deck 0.59 m): no decision, the vehicle held until the
    timeout. A beacon has deck all around it: the lowest level seen near a hypothesis counts."""
    from apron_estimator.horizontal import HorizontalTracker
    tr = HorizontalTracker()
    glint = (0.6, 0.0)
    t = _hover_track(tr, 0.0, 1.2, glint, 0.6)                 # over the beacon: deck level
    assert tr.events['probes'] == 1                            # the track is on the glint now
    t = _hover_track(tr, t, 3.0, glint, 0.6, vehicle=(0.5, 0.0), start=(0.0, 0.0))
    t = _hover_track(tr, t, 0.4, glint, 0.0, vehicle=glint, start=(0.5, 0.0))
    t = _hover_track(tr, t, 1.0, glint, 0.0, vehicle=glint)    # over the glint: ground
    t = _hover_track(tr, t, 0.3, glint, 0.6, vehicle=(0.5, 0.0), start=glint)  # deck, near
    t = _hover_track(tr, t, 1.0, glint, 0.6, vehicle=(0.3, 0.0), start=(0.5, 0.0))
    assert tr.events['rivals_rejected'] == 1 and not tr.ambiguous
    x, y, *_ = tr.state(t)
    assert math.hypot(x + 0.3, y) < 0.05                       # the track is the beacon


def test_the_surface_is_attributed_where_the_lidar_hits_not_below_the_vehicle():
    """A tilted vehicle's lidar hits the surface h·tan(tilt) away from below it. Over a glint
    0.1 m beside the pad, leaning toward the pad, the lidar sees the deck: that sample belongs
    to the point it hit, not to the glint (campaign seed 300073: a glint beside the pad was
    sampled as deck, beacon and glint compared equal, the vehicle held until the timeout)."""
    from apron_estimator.horizontal import HorizontalTracker
    tr = HorizontalTracker()
    glint = (0.625, 0.0)                                       # pad edge at 0.525
    t = _hover_track(tr, 0.0, 1.2, glint, 0.6)
    assert tr.events['probes'] == 1
    # over the glint, leaning toward the pad: the lidar spot is 0.2 m back, on the deck
    t = _hover_track(tr, t, 3.0, glint, 0.6, spot=(-0.2, 0.0), vehicle=glint, start=(0.0, 0.0))
    t = _hover_track(tr, t, 1.5, glint, 0.6, spot=(-0.2, 0.0), vehicle=glint)
    assert tr.ambiguous and tr.events['rivals_rejected'] == 0  # no evidence about the glint
    # level again: the spot is on the glint, the ground
    t = _hover_track(tr, t, 1.0, glint, 0.0, vehicle=glint)
    assert tr.events['rivals_rejected'] == 1 and not tr.ambiguous


def test_the_estimator_passes_the_lidar_spot_of_a_tilted_vehicle():
    """range · (−R e3), horizontally: pitch θ (nose down, yaw 0: the thrust axis leans
    forward) at height h hits h·tan θ behind (−x); roll φ (right side down) hits h·tan φ to
    the left (+y) — the lidar points along −z body, the opposite of the lean."""
    seen = []
    est = ApronEstimator()
    est.horizontal.update = (lambda t, c, h, s=None, spot=(0.0, 0.0), top=None,
                             prior=(0.0, 0.0): seen.append(spot))
    h = 1.5
    for k, (roll, pitch) in enumerate(((0.0, 0.1), (0.1, 0.0))):
        t = 1.0 + k
        est.on_attitude(t - 0.01, roll, pitch, 0.0)
        est.on_attitude(t, roll, pitch, 0.0)
        est.on_local_position(t, (0.0, 0.0, h), (0.0, 0.0, 0.0))
        est.on_lidar(t, h / (math.cos(roll) * math.cos(pitch)))
        est.on_camera(t, [PixyBlock(1, 160.0, 100.0, 10.0, 10.0)])
    assert seen[0] == pytest.approx((-h * math.tan(0.1), 0.0), abs=1e-9)
    assert seen[1] == pytest.approx((0.0, h * math.tan(0.1)), abs=1e-9)


def test_a_probe_stays_ambiguous_while_the_verified_beacon_is_out_of_view():
    """Campaign seed 100052: the tracker probed a glint beside the pad; over it (on the
    ground) the beacon left the image and its rival timed out after ``rival_timeout_s`` while
    the glint had no sample yet: the glint became the only, unambiguous hypothesis and the
    planner descended on it (edge strike). A rival with a surface sample is evidence: kept
    while the track is unverified."""
    from apron_estimator.horizontal import HorizontalTracker
    tr = HorizontalTracker()
    glint = (0.65, 0.0)
    t = _hover_track(tr, 0.0, 1.2, glint, 0.6)                 # beacon verified: deck
    assert tr.events['probes'] == 1 and tr.ambiguous
    t = _hover_track(tr, t, 3.0, glint, 0.6, vehicle=glint, start=(0.0, 0.0),
                     spot=(-0.3, 0.0))                         # leaning: spot off the glint
    for _ in range(150):                                       # 3 s: only the glint in view
        t += 0.02
        tr.on_accel(t, 0.0, 0.0)
        tr.update(t, [(0.0, 0.0)], 1.9, 0.6, (-0.3, 0.0))
    assert tr.tracked and tr.ambiguous                         # no descent on the glint
    _, _, _, _, var_x, var_y, _, _ = tr.state(t)
    assert var_x + var_y > 0.2 ** 2


@pytest.mark.parametrize('seed', range(6))
def test_random_flickers_never_confirm_a_rival(seed):
    """One random blob per frame anywhere within ±1 m (50 Hz, 10 s): some fall into a
    rival's gate now and then (~3 % of frames), which confirmed a 'rival' within seconds
    and made the tracker probe empty places. A persistent glint is seen in most frames."""
    import random

    from apron_estimator.horizontal import HorizontalTracker
    rng = random.Random(seed)
    tr = HorizontalTracker()
    t = 0.0
    for _ in range(500):
        t += 0.02
        tr.update(t, [(rng.gauss(0, 0.01), rng.gauss(0, 0.01)),
                      (rng.uniform(-1, 1), rng.uniform(-1, 1))], 1.5, 0.6)
        assert not tr.ambiguous
    assert tr.tracked and tr.events['probes'] == 0


def test_readings_saturated_at_the_range_limit_never_re_base_the_surface():
    """`fault_lidar_outliers` seed 300086: 0.3 m above the deck in FINAL, three −1 m outliers
    in a row were clipped to the lidar's minimum range, 0.05 m: mutually consistent, they
    re-based the surface 0.28 m up; the planner shifted the reference down with it, the
    thrust was cut and the vehicle hit the deck at 1.10 m/s. A reading at a range limit is
    the sensor's saturated output, not a surface."""
    vf = VerticalFilter()
    t = 0.0
    for _ in range(100):
        vf.on_accel(t, 0.0)
        vf.on_altitude(t, 0.9, 0.0)
        vf.on_lidar(t, 0.3)
        t = round(t + DT, 9)
    epoch, surface = vf.surface_epoch, vf.state(t).surface_height_m
    for _ in range(5):
        vf.on_accel(t, 0.0)
        vf.on_lidar(t, vf.params.range_min_m)
        t = round(t + DT, 9)
    assert vf.surface_epoch == epoch
    assert vf.state(t).surface_height_m == pytest.approx(surface, abs=0.01)
    assert vf.rejected['range'] == 5


def test_an_unverified_track_keeps_its_confirmed_rival_out_of_view():
    """Campaign seed 300054: the track restarted on the glint (the blob in view), the beacon
    became a confirmed but unsampled rival; hovering over the glint, the beacon left the
    image, its rival timed out, the glint was the only hypothesis and the planner descended
    on it (edge strike). An unverified track keeps its confirmed rivals."""
    from apron_estimator.horizontal import HorizontalTracker
    tr = HorizontalTracker()
    t = 0.0
    for _ in range(60):                      # glint acquired first, beacon 0.6 m away
        t += 0.02
        tr.on_accel(t, 0.0, 0.0)
        tr.update(t, [(0.0, 0.0), (-0.6, 0.0)], 1.8, 0.0, (-0.3, 0.0))
    assert tr.ambiguous and tr.surface is None
    for _ in range(150):                     # 3 s: the beacon out of view, spot off the track
        t += 0.02
        tr.on_accel(t, 0.0, 0.0)
        tr.update(t, [(0.0, 0.0)], 1.8, 0.0, (-0.3, 0.0))
    assert tr.tracked and tr.ambiguous


def test_a_transient_blob_beside_a_verified_beacon_is_not_probed_after_it_vanished():
    from apron_estimator.horizontal import HorizontalTracker
    tr = HorizontalTracker()
    t = 0.0
    for k in range(150):                     # beacon verified; a reflection for 0.4 s only
        t += 0.02
        tr.on_accel(t, 0.0, 0.0)
        blobs = [(0.0, 0.0)] + ([(0.5, 0.3)] if 10 <= k < 30 else [])
        tr.update(t, blobs, 1.4, 0.6)
    assert tr.surface is not None and tr.events['probes'] <= 1
    assert not tr.ambiguous
    x, y, *_ = tr.state(t)
    assert math.hypot(x, y) < 0.05
