"""Landing gear as contact points against moving, tilted surfaces (pure, plain floats).

A :class:`Surface` is an oriented box given by the centre of its top face, the top's unit
normal and an in-plane axis, half-extents, a depth, and the linear and angular velocity of the
centre (the deck; the ground is an infinite half-space below z = 0). Each body point (gear
feet or skid points, and hull points at the prop tips) against each surface gets a linear
spring–damper normal force that never pulls, and Coulomb friction with an elastic stick: an
anchor fixed in the surface holds the point by a tangential spring–damper until that force
exceeds μ·Fn, then slips. A point inside the box nearer a side than the top strikes the side
(an edge strike). :meth:`ContactModel.wrench` sums the forces into a wrench for the body.
"""

from __future__ import annotations

from dataclasses import dataclass
import math

from deckland_common.frames import Vec3
from deckland_common.validate import (
    in_range,
    integer_at_least,
    non_negative,
    one_of,
    positive,
    require,
)

from deck_simulator.rigid_body import RigidBody

TOP = 1     # contact with the top face
SIDE = 2    # contact with a side face of the box (an edge strike)


@dataclass(frozen=True, slots=True)
class GearGeometry:
    """Landing gear: four feet at (±half_length, ±half_width) or two skids along body x at
    y = ±half_width from x = −half_length to +half_length (``skid_points`` each), all
    ``height_m`` below the body origin. Defaults: docs/interfaces.md (square 0.4 m footprint,
    gear bottom 0.15 m below the body origin)."""

    kind: str = 'feet'
    half_width_m: float = 0.2
    half_length_m: float = 0.2
    height_m: float = 0.15
    skid_points: int = 3

    def __post_init__(self) -> None:
        one_of('gear.kind', self.kind, ('feet', 'skids'))
        positive('gear.half_width_m', self.half_width_m)
        positive('gear.half_length_m', self.half_length_m)
        positive('gear.height_m', self.height_m)
        integer_at_least('gear.skid_points', self.skid_points, 2)

    def points(self) -> tuple[Vec3, ...]:
        """Contact points in the body frame (FLU)."""
        w, ln, h = self.half_width_m, self.half_length_m, -self.height_m
        if self.kind == 'feet':
            return ((ln, w, h), (ln, -w, h), (-ln, -w, h), (-ln, w, h))
        n = self.skid_points
        xs = [-ln + 2.0 * ln * i / (n - 1) for i in range(n)]
        return tuple((x, s * w, h) for s in (1.0, -1.0) for x in xs)

    def static_tip_angle_rad(self) -> float:
        """Tilt about the nearer footprint edge that puts the centre of mass over it."""
        return math.atan2(min(self.half_width_m, self.half_length_m), self.height_m)


def prop_tip_points(arm_length_m: float, prop_radius_m: float,
                    rotor_height_m: float) -> tuple[Vec3, ...]:
    """Hull points at the outer prop tips of a plus quadrotor (motor 1 on +x, 2 on +y, ...)."""
    a = arm_length_m + prop_radius_m
    return ((a, 0.0, rotor_height_m), (0.0, a, rotor_height_m), (-a, 0.0, rotor_height_m),
            (0.0, -a, rotor_height_m))


def restitution_of(zeta: float) -> float:
    """Coefficient of restitution of the linear spring–damper that never pulls (analytic).

    Penetration δ of a mass on k, c (ζ = c / 2√(k m)) from δ̇(0) = v0 without gravity:
    δ = v0/ω_d e^(−σt) sin ω_d t, σ = ζ ω_n. Contact ends when k δ + c δ̇ = 0, i.e. at
    ω_d t* = π − atan2(2σω_d, ω_n² − 2σ²), and e = −δ̇(t*) / v0.
    """
    in_range('zeta', zeta, 0.0, 0.999)
    wd = math.sqrt(1.0 - zeta * zeta)         # ω_n = 1
    phi = math.atan2(2.0 * zeta * wd, 1.0 - 2.0 * zeta * zeta)
    x = math.pi - phi                          # ω_d t*
    t = x / wd
    return -math.exp(-zeta * t) * (math.cos(x) - zeta / wd * math.sin(x))


def damping_ratio_for(restitution: float) -> float:
    """ζ whose no-pull restitution (:func:`restitution_of`) is ``restitution`` (bisection)."""
    in_range('restitution', restitution, 0.15, 0.95)
    lo, hi = 0.0, 0.999
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        if restitution_of(mid) > restitution:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


@dataclass(frozen=True, slots=True)
class ContactParams:
    """Gear compliance and friction. Defaults and their sources: docs/world/contact.md."""

    stiffness_n_per_m: float = 4.0e4    # whole gear, vertical (shared by the gear points)
    restitution: float = 0.5            # of a flat drop on the gear (sets ζ, not k)
    tangential_stiffness_ratio: float = 1.0
    friction_deck: float = 0.6          # Coulomb μ, gear on the deck / pad
    friction_ground: float = 0.6        # Coulomb μ, gear on the ground
    max_omega_h: float = 0.4            # sub-step: ω_max h at most this (measured, see doc)
    resting_omega_h: float = 0.8        # ... and this while resting (stable, no impact)
    resting_speed_mps: float = 0.02     # resting: every touching point slower than this ...
    resting_time_s: float = 0.1         # ... for this long (an impact lasts ~ 25 ms)
    near_margin_m: float = 0.05         # sub-step when a surface is this close (plus v·dt)

    def __post_init__(self) -> None:
        positive('stiffness_n_per_m', self.stiffness_n_per_m)
        in_range('restitution', self.restitution, 0.15, 0.95)
        in_range('tangential_stiffness_ratio', self.tangential_stiffness_ratio, 0.01, 10.0)
        in_range('friction_deck', self.friction_deck, 0.0, 3.0)
        in_range('friction_ground', self.friction_ground, 0.0, 3.0)
        in_range('max_omega_h', self.max_omega_h, 0.01, 1.5)
        in_range('resting_omega_h', self.resting_omega_h, self.max_omega_h, 1.5)
        non_negative('resting_speed_mps', self.resting_speed_mps)
        non_negative('resting_time_s', self.resting_time_s)
        positive('near_margin_m', self.near_margin_m)


class Surface:
    """An oriented box (top face centre c, top normal n, in-plane axis u, w = n × u) moving
    rigidly with velocity v of c and angular velocity ω (world). Infinite half-extents and
    depth make a half-space (the ground)."""

    __slots__ = ('cx', 'cy', 'cz', 'depth', 'half_u', 'half_w', 'kind', 'mu', 'nx', 'ny', 'nz',
                 'ox', 'oy', 'oz', 'rejected', 'ux', 'uy', 'uz', 'vx', 'vy', 'vz', 'wx', 'wy',
                 'wz')

    def __init__(self, kind: str, half_u_m: float, half_w_m: float, depth_m: float,
                 mu: float) -> None:
        require(half_u_m > 0 and half_w_m > 0 and depth_m > 0, f'surface {kind}',
                'needs half-extents and depth > 0', (half_u_m, half_w_m, depth_m))
        require(math.isfinite(mu) and mu >= 0.0, f'surface {kind}.mu', 'must be >= 0', mu)
        self.kind = kind
        self.half_u, self.half_w, self.depth = float(half_u_m), float(half_w_m), float(depth_m)
        self.mu = float(mu)
        self.rejected = 0
        self.cx = self.cy = self.cz = 0.0
        self.nx = self.ny = 0.0
        self.nz = 1.0
        self.ux, self.uy, self.uz = 1.0, 0.0, 0.0
        self.wx, self.wy, self.wz = 0.0, 1.0, 0.0
        self.vx = self.vy = self.vz = 0.0
        self.ox = self.oy = self.oz = 0.0

    def set_pose(self, centre_m: Vec3, normal: Vec3, axis_u: Vec3,
                 velocity_mps: Vec3 = (0.0, 0.0, 0.0),
                 angular_velocity_radps: Vec3 = (0.0, 0.0, 0.0)) -> bool:
        """Pose and velocity; ``axis_u`` is made orthogonal to the (normalised) normal.

        A non-finite value, a zero normal or an axis along the normal is rejected (False,
        counted in ``rejected``; the previous pose is kept).
        """
        nx, ny, nz = normal
        ux, uy, uz = axis_u
        cx, cy, cz = centre_m
        vx, vy, vz = velocity_mps
        ox, oy, oz = angular_velocity_radps
        n = math.sqrt(nx * nx + ny * ny + nz * nz)
        if not (n > 1e-9 and math.isfinite(n + ux + uy + uz + cx + cy + cz + vx + vy + vz + ox
                                            + oy + oz)):
            self.rejected += 1
            return False
        nx, ny, nz = nx / n, ny / n, nz / n
        d = ux * nx + uy * ny + uz * nz
        ux, uy, uz = ux - d * nx, uy - d * ny, uz - d * nz
        u = math.sqrt(ux * ux + uy * uy + uz * uz)
        if not u > 1e-6:
            self.rejected += 1
            return False
        ux, uy, uz = ux / u, uy / u, uz / u
        self.cx, self.cy, self.cz = cx, cy, cz
        self.nx, self.ny, self.nz = nx, ny, nz
        self.ux, self.uy, self.uz = ux, uy, uz
        self.wx, self.wy, self.wz = ny * uz - nz * uy, nz * ux - nx * uz, nx * uy - ny * ux
        self.vx, self.vy, self.vz = vx, vy, vz
        self.ox, self.oy, self.oz = ox, oy, oz
        return True

    def velocity_at(self, x: float, y: float, z: float) -> Vec3:
        """Velocity of the surface-fixed point now at (x, y, z): v + ω × (p − c)."""
        dx, dy, dz = x - self.cx, y - self.cy, z - self.cz
        return (self.vx + self.oy * dz - self.oz * dy, self.vy + self.oz * dx - self.ox * dz,
                self.vz + self.ox * dy - self.oy * dx)

    def local(self, x: float, y: float, z: float) -> Vec3:
        """(a, b, h): coordinates along u, w and n from the top-face centre."""
        dx, dy, dz = x - self.cx, y - self.cy, z - self.cz
        return (dx * self.ux + dy * self.uy + dz * self.uz,
                dx * self.wx + dy * self.wy + dz * self.wz,
                dx * self.nx + dy * self.ny + dz * self.nz)


def ground_surface(mu: float) -> Surface:
    """The ground: the half-space z <= 0, at rest."""
    return Surface('ground', math.inf, math.inf, math.inf, mu)


class ContactModel:
    """Contact of a rigid body's points with a set of surfaces; one call of :meth:`wrench` per
    integration step.

    Points 0 … n_gear−1 are the gear, the rest hull points (a hull contact is a prop strike).
    Per step it leaves a summary for the touchdown monitor: ``n_gear_contacts[s]`` (gear
    points touching the top of surface s), ``side_contact`` (any point on a side face),
    ``hull_contact`` (any hull point on any face), ``max_penetration_m``.
    """

    __slots__ = ('_anc', '_calm_s', '_kind', 'c_n', 'c_t', 'hull_contact', 'k_n', 'k_t',
                 'max_penetration_m', 'max_speed_mps', 'n_active', 'n_gear', 'n_gear_contacts',
                 'n_points', 'near_margin', 'new_contact', 'omega_max', 'params', 'points_body',
                 'r_max', 'side_contact', 'surfaces')

    def __init__(self, params: ContactParams, mass_kg: float,
                 inertia_kgm2: tuple[float, float, float], gear_points: tuple[Vec3, ...],
                 hull_points: tuple[Vec3, ...], surfaces: list[Surface]) -> None:
        positive('mass_kg', mass_kg)
        require(len(gear_points) >= 3, 'gear_points', 'must be at least 3', gear_points)
        self.params = params
        self.surfaces = surfaces
        self.n_gear = len(gear_points)
        pts: list[float] = []
        for bx, by, bz in (*gear_points, *hull_points):
            pts.extend((float(bx), float(by), float(bz)))
        self.points_body = pts                  # x, y, z of each point, flat
        self.n_points = len(pts) // 3
        self.r_max = max(math.sqrt(pts[3 * i] ** 2 + pts[3 * i + 1] ** 2 + pts[3 * i + 2] ** 2)
                         for i in range(self.n_points))
        k = params.stiffness_n_per_m / self.n_gear
        zeta = damping_ratio_for(params.restitution)
        self.k_n = k
        self.c_n = 2.0 * zeta * math.sqrt(params.stiffness_n_per_m * mass_kg) / self.n_gear
        self.k_t = k * params.tangential_stiffness_ratio
        self.c_t = self.c_n * math.sqrt(params.tangential_stiffness_ratio)
        # fastest contact mode, bounded from above: all gear points on the point farthest
        # from the centre of mass, against the smallest principal inertia
        j_min = min(inertia_kgm2)
        k_all = params.stiffness_n_per_m * max(1.0, params.tangential_stiffness_ratio)
        self.omega_max = math.sqrt(k_all * (1.0 / mass_kg + self.r_max * self.r_max / j_min))
        self.near_margin = params.near_margin_m
        n_pairs = self.n_points * len(surfaces)
        self._kind = [0] * n_pairs              # 0 none, TOP, SIDE
        self._anc = [0.0] * (3 * n_pairs)       # anchor in surface coordinates (a, b, h)
        self.n_gear_contacts = [0] * len(surfaces)
        self.side_contact = False
        self.hull_contact = False
        self.max_penetration_m = 0.0
        self.max_speed_mps = 0.0      # fastest touching point relative to its surface
        self.n_active = 0             # touching (point, surface) pairs
        self.new_contact = False      # a pair began touching in the last call
        self._calm_s = 0.0

    def substeps(self, dt_s: float) -> int:
        """Sub-steps of the next dt_s tick near or in contact (called once per tick):
        ω_max h <= ``max_omega_h``; while resting (every touching point slower than
        ``resting_speed_mps`` relative to its surface, no new contact, for
        ``resting_time_s``) ω_max h <= ``resting_omega_h``."""
        p = self.params
        if (self.n_active > 0 and not self.new_contact
                and self.max_speed_mps < p.resting_speed_mps):
            self._calm_s += dt_s
        else:
            self._calm_s = 0.0
        lim = p.resting_omega_h if self._calm_s > p.resting_time_s else p.max_omega_h
        return max(1, math.ceil(dt_s * self.omega_max / lim - 1e-9))

    def near(self, body: RigidBody, dt_s: float) -> bool:
        """True if a point may touch a surface within dt_s (or touches one now): the lowest
        point along a surface's normal is within ``near_margin_m`` plus the relative motion
        over dt_s of its top plane (and over its rectangle, by the same slack)."""
        w = math.sqrt(body.p * body.p + body.q * body.q + body.r * body.r)
        hit = False
        for s in self.surfaces:     # a plain loop: no generator on the 400 Hz path
            if self._close(s, body, w, dt_s):
                hit = True
                break
        return hit

    def _close(self, s: Surface, body: RigidBody, w: float, dt_s: float) -> bool:
        bx, by, bz = body.x, body.y, body.z
        dx, dy, dz = bx - s.cx, by - s.cy, bz - s.cz
        nx, ny, nz = s.nx, s.ny, s.nz
        h0 = dx * nx + dy * ny + dz * nz
        svx, svy, svz = s.velocity_at(bx, by, bz)
        rx, ry, rz = body.vx - svx, body.vy - svy, body.vz - svz
        ws = math.sqrt(s.ox * s.ox + s.oy * s.oy + s.oz * s.oz)
        r_max = self.r_max
        slack = self.near_margin + (math.sqrt(rx * rx + ry * ry + rz * rz)
                                    + (w + ws) * r_max) * dt_s
        if h0 - r_max > slack or h0 < -(s.depth + r_max + slack):
            return False
        # the lowest point along n: min over the points of p · (Rᵀ n)
        bnx = body.r00 * nx + body.r10 * ny + body.r20 * nz
        bny = body.r01 * nx + body.r11 * ny + body.r21 * nz
        bnz = body.r02 * nx + body.r12 * ny + body.r22 * nz
        pts = self.points_body
        low = math.inf
        for i in range(self.n_points):
            d = pts[3 * i] * bnx + pts[3 * i + 1] * bny + pts[3 * i + 2] * bnz
            if d < low:
                low = d
        if h0 + low > slack:
            return False
        if s.half_u == math.inf:
            return True
        reach = r_max + slack
        a0 = dx * s.ux + dy * s.uy + dz * s.uz
        b0 = dx * s.wx + dy * s.wy + dz * s.wz
        return abs(a0) <= s.half_u + reach and abs(b0) <= s.half_w + reach

    def _within(self, s: Surface, body: RigidBody, reach: float) -> bool:
        dx, dy, dz = body.x - s.cx, body.y - s.cy, body.z - s.cz
        h0 = dx * s.nx + dy * s.ny + dz * s.nz
        if h0 > reach or h0 < -(s.depth + reach):
            return False
        if s.half_u == math.inf:
            return True
        a0 = dx * s.ux + dy * s.uy + dz * s.uz
        b0 = dx * s.wx + dy * s.wy + dz * s.wz
        return abs(a0) <= s.half_u + reach and abs(b0) <= s.half_w + reach

    def wrench(self, body: RigidBody) -> tuple[float, float, float, float, float, float]:
        """Contact force (world, N) and torque about the centre of mass (body, N·m) now.

        Updates the friction anchors (stick / slip) and the per-step summary.
        """
        fx = fy = fz = 0.0
        tx = ty = tz = 0.0      # world frame, rotated into the body at the end
        kn, cn, kt, ct = self.k_n, self.c_n, self.k_t, self.c_t
        n_gear = self.n_gear
        n_pts = self.n_points
        pts = self.points_body
        kind = self._kind
        anc = self._anc
        counts = self.n_gear_contacts
        side = hull = new = False
        max_pen = 0.0
        max_v2 = 0.0
        n_active = 0
        r00, r01, r02 = body.r00, body.r01, body.r02
        r10, r11, r12 = body.r10, body.r11, body.r12
        r20, r21, r22 = body.r20, body.r21, body.r22
        bx, by, bz = body.x, body.y, body.z
        wbx, wby, wbz = body.angular_velocity_world()
        reach = self.r_max
        for si in range(len(self.surfaces)):
            s = self.surfaces[si]
            counts[si] = 0
            base = si * n_pts
            if not self._within(s, body, reach):
                for i in range(n_pts):
                    kind[base + i] = 0
                continue
            scx, scy, scz = s.cx, s.cy, s.cz
            nx, ny, nz = s.nx, s.ny, s.nz
            ux, uy, uz = s.ux, s.uy, s.uz
            wx, wy, wz = s.wx, s.wy, s.wz
            hu, hw, depth, mu = s.half_u, s.half_w, s.depth, s.mu
            svx, svy, svz, sox, soy, soz = s.vx, s.vy, s.vz, s.ox, s.oy, s.oz
            for i in range(n_pts):
                pair = base + i
                px, py, pz = pts[3 * i], pts[3 * i + 1], pts[3 * i + 2]
                rx = r00 * px + r01 * py + r02 * pz
                ry = r10 * px + r11 * py + r12 * pz
                rz = r20 * px + r21 * py + r22 * pz
                qx, qy, qz = bx + rx, by + ry, bz + rz
                dx, dy, dz = qx - scx, qy - scy, qz - scz
                h = dx * nx + dy * ny + dz * nz
                if h >= 0.0 or h < -depth:
                    kind[pair] = 0
                    continue
                a = dx * ux + dy * uy + dz * uz
                b = dx * wx + dy * wy + dz * wz
                pen_u = hu - abs(a)
                pen_w = hw - abs(b)
                if pen_u < 0.0 or pen_w < 0.0:
                    kind[pair] = 0
                    continue
                pen = -h
                k_new = TOP
                cnx, cny, cnz = nx, ny, nz
                if pen_u < pen or pen_w < pen:   # nearer a side face: an edge strike
                    k_new = SIDE
                    if pen_u <= pen_w:
                        pen = pen_u
                        sg = 1.0 if a >= 0.0 else -1.0
                        cnx, cny, cnz = sg * ux, sg * uy, sg * uz
                    else:
                        pen = pen_w
                        sg = 1.0 if b >= 0.0 else -1.0
                        cnx, cny, cnz = sg * wx, sg * wy, sg * wz
                # relative velocity of the body point and the surface point under it
                vpx = body.vx + wby * rz - wbz * ry
                vpy = body.vy + wbz * rx - wbx * rz
                vpz = body.vz + wbx * ry - wby * rx
                # surface velocity at the point: v + ω × (q − c)
                vrx = vpx - (svx + soy * dz - soz * dy)
                vry = vpy - (svy + soz * dx - sox * dz)
                vrz = vpz - (svz + sox * dy - soy * dx)
                vn = vrx * cnx + vry * cny + vrz * cnz
                fn = kn * pen - cn * vn
                if fn < 0.0:
                    fn = 0.0           # a spring–damper never pulls
                # the point projected onto the face it touches
                cx_, cy_, cz_ = qx + pen * cnx, qy + pen * cny, qz + pen * cnz
                ai = 3 * pair
                n_active += 1
                v2 = vrx * vrx + vry * vry + vrz * vrz
                if v2 > max_v2:
                    max_v2 = v2
                if kind[pair] != k_new:   # new contact (or another face): anchor here
                    new = True
                    ex, ey, ez = cx_ - scx, cy_ - scy, cz_ - scz
                    anc[ai] = ex * ux + ey * uy + ez * uz
                    anc[ai + 1] = ex * wx + ey * wy + ez * wz
                    anc[ai + 2] = ex * nx + ey * ny + ez * nz
                    kind[pair] = k_new
                aa, ab, ah = anc[ai], anc[ai + 1], anc[ai + 2]
                sx = cx_ - (scx + aa * ux + ab * wx + ah * nx)
                sy = cy_ - (scy + aa * uy + ab * wy + ah * ny)
                sz = cz_ - (scz + aa * uz + ab * wz + ah * nz)
                d = sx * cnx + sy * cny + sz * cnz
                sx, sy, sz = sx - d * cnx, sy - d * cny, sz - d * cnz
                vtx, vty, vtz = vrx - vn * cnx, vry - vn * cny, vrz - vn * cnz
                ftx = -kt * sx - ct * vtx
                fty = -kt * sy - ct * vty
                ftz = -kt * sz - ct * vtz
                lim = mu * fn
                f2 = ftx * ftx + fty * fty + ftz * ftz
                if f2 > lim * lim:
                    # slip: the Coulomb force along the trial direction; the anchor follows
                    # the point so that the spring's own stretch never exceeds μ Fn / k_t
                    # (a reset only releases spring energy, never stores any)
                    sc = lim / math.sqrt(f2)
                    ftx, fty, ftz = ftx * sc, fty * sc, ftz * sc
                    s2 = sx * sx + sy * sy + sz * sz
                    if kt * kt * s2 > lim * lim:
                        g = lim / (kt * math.sqrt(s2))
                        ex = cx_ - g * sx - scx
                        ey = cy_ - g * sy - scy
                        ez = cz_ - g * sz - scz
                        anc[ai] = ex * ux + ey * uy + ez * uz
                        anc[ai + 1] = ex * wx + ey * wy + ez * wz
                        anc[ai + 2] = ex * nx + ey * ny + ez * nz
                gx = fn * cnx + ftx
                gy = fn * cny + fty
                gz = fn * cnz + ftz
                fx += gx
                fy += gy
                fz += gz
                tx += ry * gz - rz * gy
                ty += rz * gx - rx * gz
                tz += rx * gy - ry * gx
                if pen > max_pen:
                    max_pen = pen
                if k_new == SIDE:
                    side = True
                if i >= n_gear:
                    hull = True
                elif k_new == TOP:
                    counts[si] += 1
        self.side_contact = side
        self.hull_contact = hull
        self.max_penetration_m = max_pen
        self.max_speed_mps = math.sqrt(max_v2)
        self.n_active = n_active
        self.new_contact = new
        # torque into the body frame: Rᵀ τ
        return (fx, fy, fz, r00 * tx + r10 * ty + r20 * tz, r01 * tx + r11 * ty + r21 * tz,
                r02 * tx + r12 * ty + r22 * tz)

    def spring_energy_j(self, body: RigidBody) -> float:
        """Elastic energy stored in the normal and stick springs now (for energy checks)."""
        e = 0.0
        n_pts = self.n_points
        for si in range(len(self.surfaces)):
            s = self.surfaces[si]
            for i in range(n_pts):
                pair = si * n_pts + i
                if self._kind[pair] == 0:
                    continue
                pb = self.points_body
                qx, qy, qz = body.point_world(pb[3 * i], pb[3 * i + 1], pb[3 * i + 2])
                a, b, h = s.local(qx, qy, qz)
                aa, ab, ah = self._anc[3 * pair], self._anc[3 * pair + 1], self._anc[3 * pair + 2]
                if self._kind[pair] == TOP:
                    pen = max(0.0, -h)
                    t2 = (a - aa) ** 2 + (b - ab) ** 2
                else:
                    pen_u, pen_w = s.half_u - abs(a), s.half_w - abs(b)
                    if pen_u <= pen_w:
                        pen, t2 = max(0.0, pen_u), (b - ab) ** 2 + (h - ah) ** 2
                    else:
                        pen, t2 = max(0.0, pen_w), (a - aa) ** 2 + (h - ah) ** 2
                e += 0.5 * self.k_n * pen * pen + 0.5 * self.k_t * t2
        return e


def step_with_contact(body: RigidBody, contact: ContactModel, h: float, fx: float, fy: float,
                      fz: float, tx: float, ty: float, tz: float) -> None:
    """One integration step of h: the contact wrench now plus the external force (world,
    gravity excluded) and torque (body), held over the step."""
    cfx, cfy, cfz, ctx, cty, ctz = contact.wrench(body)
    body.step(h, fx + cfx, fy + cfy, fz + cfz, tx + ctx, ty + cty, tz + ctz)
