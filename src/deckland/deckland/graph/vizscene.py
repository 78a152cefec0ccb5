"""The 3-D scene of the live view as plain geometry (pure: no rclpy, no foxglove).

:class:`SceneState` holds the latest value of each input (decoded from the graph's topics by
:mod:`deckland.graph.viz`, or from a bag for a snapshot); :func:`build_scene` turns it into
:class:`Item` s in ``map`` (ENU): the deck plane with its tilt and pad outline, the beacon, the
vehicle, the estimated apron with its 2-σ covariance ellipse, the planner setpoint and the
camera footprint on the deck plane. :mod:`deckland.graph.viz` converts the items to a Foxglove
``SceneUpdate``; :func:`render_png` draws the same items with matplotlib.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import math
from typing import Any

from apron_estimator.camera import CameraModel, CameraParams
from deckland_common.frames import mat_vec, quaternion_to_euler, rot_body_to_world

Vec3 = tuple[float, float, float]
Quat = tuple[float, float, float, float]   # (w, x, y, z)
Rgba = tuple[float, float, float, float]

#: Colours of the scene (RGBA in [0, 1]).
COLORS: dict[str, Rgba] = {
    'deck': (0.45, 0.50, 0.55, 0.6), 'pad': (1.0, 0.85, 0.1, 1.0),
    'beacon': (1.0, 0.2, 0.1, 1.0), 'vehicle': (0.2, 0.5, 1.0, 0.9),
    'estimate': (0.1, 0.9, 0.3, 1.0), 'setpoint': (0.9, 0.2, 0.9, 1.0),
    'footprint': (0.2, 0.9, 0.9, 1.0)}
#: The deck plane drawn around the pad (m beyond each pad edge).
DECK_MARGIN_M = 0.5
#: Vehicle box (paper's quadcopter, ~0.55 m across the rotors; 0.15 m high).
VEHICLE_SIZE_M: Vec3 = (0.55, 0.55, 0.15)
BEACON_DIAMETER_M = 0.08
#: Covariance ellipses drawn at this many standard deviations.
ELLIPSE_SIGMAS = 2.0
ELLIPSE_POINTS = 36


@dataclass
class SceneState:
    """The latest value of each scene input (None = not received yet)."""

    pad_size_m: tuple[float, float] = (1.05, 0.85)     # scenario apron size (Table 3)
    beacon_m: Vec3 | None = None                       # pad centre on the pad top (truth)
    deck_orientation: Quat = (1.0, 0.0, 0.0, 0.0)      # deck attitude (level unless known)
    vehicle_m: Vec3 | None = None
    vehicle_orientation: Quat = (1.0, 0.0, 0.0, 0.0)
    vehicle_source: str = ''                           # topic the vehicle pose came from
    estimate_m: Vec3 | None = None                     # apron position + surface height
    estimate_cov_m2: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    tracked: bool = False
    setpoint_m: Vec3 | None = None
    mode: str = ''
    camera: CameraParams = field(default_factory=CameraParams)


@dataclass(frozen=True)
class Item:
    """One primitive in ``map``: ``kind`` 'cube' (pose + size), 'sphere' (pose + size),
    'line' (closed loop through ``points``), 'arrow' (pose, +x, length = size[0]) or 'text'."""

    entity: str
    kind: str
    color: Rgba
    position: Vec3 = (0.0, 0.0, 0.0)
    orientation: Quat = (1.0, 0.0, 0.0, 0.0)
    size: Vec3 = (0.0, 0.0, 0.0)
    points: tuple[Vec3, ...] = ()
    text: str = ''


def rotate(q: Quat, v: Vec3) -> Vec3:
    """``v`` rotated by the unit quaternion ``q`` (w, x, y, z)."""
    roll, pitch, yaw = quaternion_to_euler(*q)
    return mat_vec(rot_body_to_world(roll, pitch, yaw), v)


def rectangle(center: Vec3, size: tuple[float, float], q: Quat) -> tuple[Vec3, ...]:
    """The four corners of a ``size`` rectangle centred on ``center`` in the plane of ``q``."""
    hx, hy = size[0] / 2.0, size[1] / 2.0
    out = []
    for dx, dy in ((hx, hy), (-hx, hy), (-hx, -hy), (hx, -hy)):
        r = rotate(q, (dx, dy, 0.0))
        out.append((center[0] + r[0], center[1] + r[1], center[2] + r[2]))
    return tuple(out)


def covariance_ellipse(cov: tuple[float, float, float, float], n_sigma: float = ELLIPSE_SIGMAS
                       ) -> tuple[float, float, float]:
    """Semi-axes (major, minor) and the major axis' angle from +x of the ``n_sigma`` ellipse
    of a 2×2 covariance (row-major); negative variances count as zero."""
    a, b, d = cov[0], 0.5 * (cov[1] + cov[2]), cov[3]
    mean, diff = 0.5 * (a + d), 0.5 * (a - d)
    r = math.hypot(diff, b)
    l1, l2 = max(mean + r, 0.0), max(mean - r, 0.0)
    angle = 0.5 * math.atan2(2.0 * b, a - d)
    return n_sigma * math.sqrt(l1), n_sigma * math.sqrt(l2), angle


def ellipse_points(center: Vec3, cov: tuple[float, float, float, float],
                   n: int = ELLIPSE_POINTS) -> tuple[Vec3, ...]:
    """Points of the 2-σ ellipse of ``cov`` around ``center``, horizontal."""
    major, minor, ang = covariance_ellipse(cov)
    ca, sa = math.cos(ang), math.sin(ang)
    pts = []
    for i in range(n):
        t = 2.0 * math.pi * i / n
        ex, ey = major * math.cos(t), minor * math.sin(t)
        pts.append((center[0] + ca * ex - sa * ey, center[1] + sa * ex + ca * ey, center[2]))
    return tuple(pts)


def camera_footprint(position: Vec3, q: Quat, plane_z_m: float,
                     camera: CameraParams | None = None) -> tuple[Vec3, ...] | None:
    """Where the image corners' rays meet the horizontal plane ``z = plane_z_m`` (the camera
    at the body origin, the estimator's camera model); None when a corner ray misses it."""
    cam = CameraModel(camera)
    p = cam.params
    roll, pitch, yaw = quaternion_to_euler(*q)
    out = []
    for px, py in ((0.0, 0.0), (p.width_px, 0.0), (p.width_px, p.height_px), (0.0, p.height_px)):
        d = cam.ray_world(px, py, roll, pitch, yaw)
        if d[2] >= -1e-6 or position[2] <= plane_z_m:
            return None
        s = (plane_z_m - position[2]) / d[2]
        out.append((position[0] + s * d[0], position[1] + s * d[1], plane_z_m))
    return tuple(out)


def build_scene(s: SceneState) -> list[Item]:
    """The scene items for the current state (only what is known is drawn)."""
    c = COLORS
    items: list[Item] = []
    deck_z = None
    if s.beacon_m is not None:
        b = s.beacon_m
        deck_z = b[2]
        sx, sy = s.pad_size_m
        items.append(Item('deck', 'cube', c['deck'], position=(b[0], b[1], b[2] - 0.01),
                          orientation=s.deck_orientation,
                          size=(sx + 2 * DECK_MARGIN_M, sy + 2 * DECK_MARGIN_M, 0.02)))
        items.append(Item('deck', 'line', c['pad'],
                          points=rectangle((b[0], b[1], b[2] + 0.002), s.pad_size_m,
                                           s.deck_orientation)))
        d = BEACON_DIAMETER_M
        items.append(Item('beacon', 'sphere', c['beacon'], position=b, size=(d, d, d)))
    if s.estimate_m is not None and s.tracked:
        e = s.estimate_m
        if deck_z is None:
            deck_z = e[2]
        items.append(Item('estimate', 'sphere', c['estimate'], position=e,
                          size=(0.05, 0.05, 0.05)))
        items.append(Item('estimate', 'line', c['estimate'],
                          points=ellipse_points((e[0], e[1], e[2] + 0.004), s.estimate_cov_m2)))
    if s.vehicle_m is not None:
        v, q = s.vehicle_m, s.vehicle_orientation
        items.append(Item('vehicle', 'cube', c['vehicle'], position=v, orientation=q,
                          size=VEHICLE_SIZE_M))
        items.append(Item('vehicle', 'arrow', c['vehicle'], position=v, orientation=q,
                          size=(0.45, 0.03, 0.0)))
        if s.mode:
            items.append(Item('vehicle', 'text', (1.0, 1.0, 1.0, 1.0),
                              position=(v[0], v[1], v[2] + 0.35), text=s.mode))
        fp = camera_footprint(v, q, deck_z if deck_z is not None else 0.0, s.camera)
        if fp is not None:
            items.append(Item('footprint', 'line', c['footprint'], points=fp))
    if s.setpoint_m is not None:
        items.append(Item('setpoint', 'sphere', c['setpoint'], position=s.setpoint_m,
                          size=(0.1, 0.1, 0.1)))
    return items


# --- scene state from the graph's messages (rclpy or rosbags objects alike) ---------------

#: Scene inputs: relative topic name → SceneState field it updates (see :func:`apply`).
SCENE_INPUTS = ('sim/truth/apron', 'sim/truth/vehicle', 'vehicle/odom', 'apron/state',
                'planner/setpoint', 'planner/status')


def _quat(o: Any) -> tuple[float, float, float, float]:
    return (float(o.w), float(o.x), float(o.y), float(o.z))


def _xyz(p: Any) -> tuple[float, float, float]:
    return (float(p.x), float(p.y), float(p.z))


def apply(state: SceneState, rel: str, msg: Any) -> None:
    """Update ``state`` from one decoded message of scene input ``rel`` (rclpy or rosbags
    messages alike; non-finite values are ignored, the last good value stays)."""
    from deckland_common.messages import mode_name

    if rel == 'sim/truth/apron':
        p = _xyz(msg.pose.pose.position)
        if all(map(math.isfinite, p)):
            state.beacon_m = p
            state.deck_orientation = _quat(msg.pose.pose.orientation)
    elif rel in ('vehicle/odom', 'sim/truth/vehicle'):
        if rel == 'sim/truth/vehicle' and state.vehicle_source == 'vehicle/odom':
            return      # the stack's own estimate wins; the truth only without one
        p, q = _xyz(msg.pose.pose.position), _quat(msg.pose.pose.orientation)
        if all(map(math.isfinite, (*p, *q))) and any(q):
            state.vehicle_m, state.vehicle_orientation = p, q
            state.vehicle_source = rel
    elif rel == 'apron/state':
        from deckland_common.messages import apron_state_from_msg
        st, _, _ = apron_state_from_msg(msg)
        if st is None:
            return
        v = st.vertical
        z = v.surface_height_m if v.valid else (state.beacon_m[2] if state.beacon_m else 0.0)
        state.estimate_m = (st.apron_position_m[0], st.apron_position_m[1], z)
        cov = msg.rel_position_cov_m2
        state.estimate_cov_m2 = (float(cov[0]), float(cov[1]), float(cov[2]), float(cov[3]))
        state.tracked = st.tracked
        if msg.deck_attitude_valid:
            state.deck_orientation = _quat(msg.deck_orientation)
    elif rel == 'planner/setpoint':
        p = _xyz(msg.pose.position)
        if all(map(math.isfinite, p)):
            state.setpoint_m = p
    elif rel == 'planner/status':
        state.mode = mode_name(int(msg.mode))


def relative_name(topic: str) -> str | None:
    """The scene input a (possibly namespaced) topic is, or None."""
    for rel in SCENE_INPUTS:
        if topic == '/' + rel or topic.endswith('/' + rel):
            return rel
    return None


def apply_latest(state: SceneState, latest: dict[str, Any], decode: Any) -> None:
    """Apply the latest raw message of each scene input (``latest``: relative name → raw,
    ``decode(raw)`` → message) in :data:`SCENE_INPUTS` order (the truth apron before the
    estimate); one that cannot be decoded or applied is skipped (a bad message never stops
    the view or the snapshot)."""
    for rel in SCENE_INPUTS:
        if rel in latest:
            try:
                apply(state, rel, decode(latest[rel]))
            except Exception:
                continue


def render_png(scene: SceneState, out: str, title: str = '') -> None:
    """Draw the scene items (3-D, matplotlib) into ``out``."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    fig = plt.figure(figsize=(8, 6.5))
    ax = fig.add_subplot(projection='3d')
    for it in build_scene(scene):
        if it.kind == 'cube' and it.entity == 'deck':
            corners = rectangle(it.position, (it.size[0], it.size[1]), it.orientation)
            ax.add_collection3d(Poly3DCollection([corners], color=it.color[:3], alpha=0.35))
        elif it.kind == 'cube':     # the vehicle: its outline and its heading
            corners = rectangle(it.position, (it.size[0], it.size[1]), it.orientation)
            xs, ys, zs = zip(*(*corners, corners[0]), strict=True)
            ax.plot(xs, ys, zs, color=it.color[:3], lw=2.5, label='vehicle (vehicle/odom)')
        elif it.kind == 'line':
            xs, ys, zs = zip(*(*it.points, it.points[0]), strict=True)
            label = {'deck': 'pad outline', 'estimate': 'estimated apron, 2σ',
                     'footprint': 'camera footprint'}[it.entity]
            ax.plot(xs, ys, zs, color=it.color[:3], lw=1.5, label=label)
        elif it.kind == 'sphere':
            label = {'beacon': 'beacon (truth)', 'estimate': 'apron estimate',
                     'setpoint': 'planner setpoint'}[it.entity]
            ax.scatter(*([c] for c in it.position), color=it.color[:3], s=40, label=label)
        elif it.kind == 'arrow':
            d = mat_vec(rot_body_to_world(*quaternion_to_euler(*it.orientation)),
                        (it.size[0], 0.0, 0.0))
            ax.quiver(*it.position, *d, color=it.color[:3])
        elif it.kind == 'text':
            ax.text(*it.position, it.text, color='black')
    ax.set_xlabel('x east [m]')
    ax.set_ylabel('y north [m]')
    ax.set_zlabel('z up [m]')
    pts = [it.position for it in build_scene(scene)] + [
        p for it in build_scene(scene) for p in it.points]
    if pts:
        cx = [p[0] for p in pts]
        cy = [p[1] for p in pts]
        half = max(max(cx) - min(cx), max(cy) - min(cy), 1.0) / 2.0 + 0.3
        mx, my = (max(cx) + min(cx)) / 2.0, (max(cy) + min(cy)) / 2.0
        ax.set_xlim(mx - half, mx + half)
        ax.set_ylim(my - half, my + half)
        ax.set_zlim(0.0, max(max(p[2] for p in pts) + 0.3, 1.0))
    ax.legend(loc='upper left', fontsize=8)
    if title:
        ax.set_title(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)


# --- a snapshot from a bag (rosbags, no ROS runtime) ------------------------------------

def scene_from_bag(bag_dir: str, at_s: float | None = None,
                   pad_size_m: tuple[float, float] | None = None) -> tuple[SceneState, float]:
    """The scene state at ``at_s`` seconds after the bag's first message (default: the
    midpoint) from the latest message of each scene input before it; returns (state, t)."""
    from deckland.ros import bag, rosio

    store = rosio.typestore()
    scene = SceneState() if pad_size_m is None else SceneState(pad_size_m=pad_size_m)
    info = bag.bag_info(bag_dir)
    topics = [t.name for t in info.topics if relative_name(t.name) is not None]
    if not topics:
        raise ValueError(f'{bag_dir}: none of the scene topics {SCENE_INPUTS}')
    t0, t1 = info.start_ns, info.end_ns
    t_ns = t0 + (t1 - t0) // 2 if at_s is None else t0 + int(at_s * 1e9)
    latest: dict[str, tuple[str, bytes]] = {}
    for topic, msgtype, log_ns, data in bag.iter_messages(bag_dir, topics):
        if log_ns > t_ns:
            break
        latest[str(relative_name(topic))] = (msgtype, data)
    apply_latest(scene, latest, lambda m: store.deserialize_cdr(m[1], m[0]))
    return scene, (t_ns - t0) * 1e-9


def pad_size_of(scenario: str) -> tuple[float, float]:
    """The apron size of a scenario (name or path)."""
    from deck_simulator.scenario import load_scenario

    sx, sy = load_scenario(scenario).apron.size_m
    return (float(sx), float(sy))
