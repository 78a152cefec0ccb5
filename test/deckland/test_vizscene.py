"""The live view's scene (deckland.graph.vizscene, deckland.graph.viz conversions): geometry
against the camera model and the covariance, the SceneUpdate, inputs decoded from messages,
the PNG."""

import math

from apron_estimator.camera import CameraParams
from deckland.graph import viz, vizscene
from deckland.graph.vizscene import SceneState, build_scene
from deckland_common.frames import euler_to_quaternion
import pytest

PINHOLE = CameraParams(k1=0.0, k2=0.0)   # the geometry tests: the 60°x47° pinhole


def test_level_camera_footprint_is_the_fov_rectangle_on_the_deck():
    """Straight down from 2 m above a deck at 0.5 m: half-widths h tan(30°) and h tan(23.5°),
    the 60°x47° field of view (the image's long side across the vehicle: FLU y)."""
    fp = vizscene.camera_footprint((1.0, 2.0, 2.5), (1.0, 0.0, 0.0, 0.0), 0.5, PINHOLE)
    xs = sorted(p[0] - 1.0 for p in fp)
    ys = sorted(p[1] - 2.0 for p in fp)
    assert all(p[2] == 0.5 for p in fp)
    assert xs[-1] == pytest.approx(2.0 * math.tan(math.radians(23.5)), rel=1e-9)
    assert xs[0] == pytest.approx(-xs[-1], rel=1e-9)
    assert ys[-1] == pytest.approx(2.0 * math.tan(math.radians(30.0)), rel=1e-9)


def test_yaw_rotates_and_pitch_shifts_the_footprint():
    q = euler_to_quaternion(0.0, 0.0, math.pi / 2)
    fp = vizscene.camera_footprint((0.0, 0.0, 2.0), q, 0.0, PINHOLE)
    # nose north: the forward half-width (tan 23.5°) now lies along y
    assert max(p[1] for p in fp) == pytest.approx(2.0 * math.tan(math.radians(23.5)))
    nose_down = euler_to_quaternion(0.0, math.radians(10.0), 0.0)
    fp = vizscene.camera_footprint((0.0, 0.0, 2.0), nose_down, 0.0, PINHOLE)
    # pitched 10° nose down, the camera looks back: the far edge is h tan(23.5° + 10°) behind
    assert min(p[0] for p in fp) == pytest.approx(-2.0 * math.tan(math.radians(33.5)))
    assert max(p[0] for p in fp) == pytest.approx(2.0 * math.tan(math.radians(13.5)))


def test_the_pixy_lens_widens_the_footprint_beyond_the_pinhole_fov():
    """The default camera is the estimator's, with the Pixy's barrel (decision 14): the
    image corners see farther out than the pinhole 60°x47°."""
    level = (1.0, 0.0, 0.0, 0.0)
    pin = vizscene.camera_footprint((0.0, 0.0, 2.0), level, 0.0, PINHOLE)
    lens = vizscene.camera_footprint((0.0, 0.0, 2.0), level, 0.0)
    for a, b in zip(pin, lens, strict=True):
        assert math.hypot(b[0], b[1]) > 1.1 * math.hypot(a[0], a[1])


def test_no_footprint_below_the_deck_or_looking_at_the_horizon():
    assert vizscene.camera_footprint((0.0, 0.0, 0.4), (1.0, 0.0, 0.0, 0.0), 0.5) is None
    side = euler_to_quaternion(math.radians(80.0), 0.0, 0.0)
    assert vizscene.camera_footprint((0.0, 0.0, 2.0), side, 0.0) is None


def test_covariance_ellipse_axes_are_the_eigenvalues():
    major, minor, ang = vizscene.covariance_ellipse((0.04, 0.0, 0.0, 0.01))
    assert (major, minor, ang) == pytest.approx((0.4, 0.2, 0.0))     # 2σ
    # rotated 30°: R diag(0.04, 0.01) Rᵀ
    c, s = math.cos(math.radians(30)), math.sin(math.radians(30))
    cov = (0.04 * c * c + 0.01 * s * s, 0.03 * c * s, 0.03 * c * s, 0.04 * s * s + 0.01 * c * c)
    major, minor, ang = vizscene.covariance_ellipse(cov)
    assert (major, minor) == pytest.approx((0.4, 0.2))
    assert ang == pytest.approx(math.radians(30))
    pts = vizscene.ellipse_points((1.0, 1.0, 0.5), cov)
    far = max(pts, key=lambda p: math.hypot(p[0] - 1.0, p[1] - 1.0))
    assert math.hypot(far[0] - 1.0, far[1] - 1.0) == pytest.approx(0.4, rel=1e-3)
    assert vizscene.covariance_ellipse((-1.0, 0.0, 0.0, -1.0)) == (0.0, 0.0, 0.0)


def test_pad_outline_follows_the_deck_tilt():
    q = euler_to_quaternion(math.radians(5.0), 0.0, 0.0)   # rolled 5°: y edges rise / fall
    corners = vizscene.rectangle((0.0, 0.0, 1.0), (1.0, 0.8), q)
    zs = sorted(p[2] for p in corners)
    assert zs[-1] - 1.0 == pytest.approx(0.4 * math.sin(math.radians(5.0)))
    assert zs[0] - 1.0 == pytest.approx(-0.4 * math.sin(math.radians(5.0)))


def full_state():
    return SceneState(beacon_m=(-3.2, -2.0, 0.6), vehicle_m=(-3.0, -2.0, 1.8),
                      estimate_m=(-3.18, -2.01, 0.61), estimate_cov_m2=(4e-4, 0.0, 0.0, 1e-4),
                      tracked=True, setpoint_m=(-3.18, -2.01, 1.5), mode='DESCEND')


def test_scene_has_every_entity_once_known():
    assert build_scene(SceneState()) == []          # nothing received: nothing drawn
    items = build_scene(full_state())
    kinds = {(i.entity, i.kind) for i in items}
    assert kinds == {('deck', 'cube'), ('deck', 'line'), ('beacon', 'sphere'),
                     ('estimate', 'sphere'), ('estimate', 'line'), ('vehicle', 'cube'),
                     ('vehicle', 'arrow'), ('vehicle', 'text'), ('footprint', 'line'),
                     ('setpoint', 'sphere')}
    untracked = full_state()
    untracked.tracked = False
    assert 'estimate' not in {i.entity for i in build_scene(untracked)}


def test_scene_update_converts_every_item():
    from foxglove.messages import SceneUpdate
    upd = viz.scene_update(build_scene(full_state()), 1_700_000_000.25)
    assert isinstance(upd, SceneUpdate)
    assert len(upd.encode()) > 500      # protobuf with every primitive
    assert SceneUpdate.get_schema().name == 'foxglove.SceneUpdate'


def test_inputs_are_decoded_from_the_graph_messages():
    from deckland_common.contract import ApronState, VerticalState
    from deckland_common.messages import fill_apron_state
    from geometry_msgs.msg import PoseStamped
    from nav_msgs.msg import Odometry

    from deckland_interfaces.msg import ApronState as ApronStateMsg
    from deckland_interfaces.msg import PlannerStatus

    s = SceneState()
    od = Odometry()
    od.pose.pose.position.x, od.pose.pose.position.z = 1.0, 2.0
    od.pose.pose.orientation.w = 1.0
    vizscene.apply(s, 'vehicle/odom', od)
    truth = Odometry()
    truth.pose.pose.position.x, truth.pose.pose.orientation.w = 9.0, 1.0
    vizscene.apply(s, 'sim/truth/vehicle', truth)       # the stack's estimate wins
    assert s.vehicle_m == (1.0, 0.0, 2.0)
    v = VerticalState(True, 1.4, 0.0, 2.0, 0.0, 0.6, 0.0, 0.0, 0, 0.0)
    st = ApronState(5.0, True, True, 0.0, (0.1, 0.0), (0.0, 0.0), (4e-4, 1e-4), (0.1, 0.0),
                    (0.0, 0.0), (1.1, 0.0), (0.0, 0.0), v)
    vizscene.apply(s, 'apron/state', fill_apron_state(ApronStateMsg(), st))
    assert s.estimate_m == (1.1, 0.0, 0.6) and s.tracked
    assert s.estimate_cov_m2 == (4e-4, 0.0, 0.0, 1e-4)
    bad = fill_apron_state(ApronStateMsg(), st)
    bad.apron_position_m = (math.nan, 0.0)
    vizscene.apply(s, 'apron/state', bad)              # refused: the last good value stays
    assert s.estimate_m == (1.1, 0.0, 0.6)
    sp = PoseStamped()
    sp.pose.position.z = 1.5
    vizscene.apply(s, 'planner/setpoint', sp)
    vizscene.apply(s, 'planner/status', PlannerStatus(mode=PlannerStatus.MODE_FINAL))
    assert s.setpoint_m == (0.0, 0.0, 1.5) and s.mode == 'FINAL'
    assert vizscene.relative_name('/uav1/apron/state') == 'apron/state'
    assert vizscene.relative_name('/apron/statex') is None


def test_png_of_a_scene(tmp_path):
    out = tmp_path / 'scene.png'
    vizscene.render_png(full_state(), str(out), 'test')
    assert out.read_bytes()[:8] == b'\x89PNG\r\n\x1a\n' and out.stat().st_size > 20_000


def test_bad_server_options_are_refused():
    for kw, needle in (({'port': 70000}, 'port'), ({'rate_hz': 0.0}, 'rate_hz'),
                       ({'host': ' '}, 'host')):
        with pytest.raises(ValueError, match=needle):
            viz.LiveView(**kw)
    assert viz.DEFAULT_HOST == '127.0.0.1'         # loopback unless asked
    assert CameraParams().fov_x_deg == 60.0


LAYOUT = __import__('pathlib').Path(__file__).resolve().parents[2] / 'docs' / 'foxglove' / \
    'deckland-layout.json'
#: the type of each topic the layout names (as the graph publishes them)
LAYOUT_TYPES = {'/apron/state': 'deckland_interfaces/msg/ApronState',
                '/altitude/state': 'deckland_interfaces/msg/AltitudeState',
                '/planner/status': 'deckland_interfaces/msg/PlannerStatus',
                '/sim/truth/vehicle': 'nav_msgs/msg/Odometry',
                '/sim/truth/apron': 'nav_msgs/msg/Odometry',
                '/vehicle/range': 'sensor_msgs/msg/Range',
                '/control/thrust': 'geometry_msgs/msg/WrenchStamped'}


def _resolve(store, msgtype, fields):
    """Walk ``fields`` (``a.b[0].c``) through the typestore's definitions; the leaf type."""
    import re
    typ = msgtype
    for part in fields:
        name = re.sub(r'\[\d+\]$', '', part)
        defs = dict(store.fielddefs[typ][1])
        assert name in defs, (msgtype, part)
        kind, spec = defs[name]
        if kind.name in ('ARRAY', 'SEQUENCE'):
            kind, spec = spec[0]
        typ = spec if kind.name == 'NAME' else spec[0]
    assert typ not in store.fielddefs, (msgtype, fields)     # a number, plottable
    return typ


def test_layout_shows_the_scene_figures_and_mode_on_real_fields():
    import json

    from deckland.ros import rosio
    cfg = json.loads(LAYOUT.read_text())['configById']
    assert cfg['3D!scene']['topics'] == {viz.SCENE_TOPIC: {'visible': True}}
    assert cfg['StateTransitions!mode']['paths'][0]['value'] == '/planner/status.mode'
    store = rosio.typestore()
    paths = [p['value'] for k, c in cfg.items() if k.startswith(('Plot', 'StateTrans'))
             for p in c['paths']]
    assert len(paths) >= 14
    for path in paths:
        topic, *fields = path.split('.')
        _resolve(store, LAYOUT_TYPES[topic], fields)


def test_a_snapshot_rebuilds_the_scene_from_the_golden_bag():
    import pathlib

    from deckland.graph.vizscene import scene_from_bag
    bag_dir = pathlib.Path(__file__).parents[1] / 'fixtures' / 'golden_paper'
    scene, t = scene_from_bag(str(bag_dir), pad_size_m=(1.05, 0.85))
    assert t > 0.0 and scene.vehicle_m is not None
    assert all(math.isfinite(c) for c in scene.vehicle_m)
    assert scene.estimate_m is not None and all(math.isfinite(c) for c in scene.estimate_m)
