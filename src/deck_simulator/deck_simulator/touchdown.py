"""Touchdown monitor: the landing record and its outcome from the contact states (pure).

:meth:`TouchdownMonitor.update` is called after every integration step in which anything
may touch (every contact sub-step) and at least once per physics tick otherwise. It records
the first contact (relative normal and lateral speed of the centre of mass against the
surface, relative tilt), every later impact, bounces and their height, edge and prop strikes,
tip-over, feet leaving the pad, and settling (relative speed near zero for ``settle_time_s``,
disarmed). :meth:`TouchdownMonitor.record` applies the :class:`OutcomeRules`; a run a pilot
would call a failure is never a success. Rules, defaults and sources: docs/world/contact.md.
"""

from __future__ import annotations

from dataclasses import dataclass
import math

from deckland_common.validate import in_range, non_negative, positive, require

from deck_simulator.contact import ContactModel, Surface
from deck_simulator.rigid_body import RigidBody


@dataclass(frozen=True, slots=True)
class OutcomeRules:
    """Limits of a successful landing (defaults and sources: docs/world/contact.md)."""

    crash_speed_mps: float = 1.0              # any impact, relative normal speed
    max_lateral_speed_mps: float = 0.5        # any impact, relative speed along the surface
    max_tilt_rad: float = math.radians(12.0)  # any impact, vehicle vs surface
    max_bounce_height_m: float | None = None  # None: off (bounces are reported)
    tip_over_tilt_rad: float = 0.0            # 0: the gear's static stability angle
    settle_speed_mps: float = 0.05
    settle_rate_radps: float = 0.2
    settle_time_s: float = 1.0
    bounce_min_height_m: float = 0.01         # a hop lower than this is not a bounce
    impact_min_speed_mps: float = 0.1         # a slower re-touch without a bounce: no impact
    check_period_s: float = 1.0 / 400.0       # tilt, pad, settle and hop checks (not touches)

    def __post_init__(self) -> None:
        positive('crash_speed_mps', self.crash_speed_mps)
        positive('max_lateral_speed_mps', self.max_lateral_speed_mps)
        in_range('max_tilt_rad', self.max_tilt_rad, 0.0, math.pi / 2)
        if self.max_bounce_height_m is not None:
            positive('max_bounce_height_m', self.max_bounce_height_m)
        in_range('tip_over_tilt_rad', self.tip_over_tilt_rad, 0.0, math.pi / 2)
        positive('settle_speed_mps', self.settle_speed_mps)
        positive('settle_rate_radps', self.settle_rate_radps)
        positive('settle_time_s', self.settle_time_s)
        non_negative('bounce_min_height_m', self.bounce_min_height_m)
        non_negative('impact_min_speed_mps', self.impact_min_speed_mps)
        positive('check_period_s', self.check_period_s)


@dataclass(frozen=True, slots=True)
class Pad:
    """The landing pad: a rectangle on the top of surface ``surface_index`` (deck frame:
    centre offset along u, w and half-sizes); the default is the whole top face."""

    surface_index: int = 0
    offset_u_m: float = 0.0
    offset_w_m: float = 0.0
    half_u_m: float = math.inf
    half_w_m: float = math.inf


@dataclass(frozen=True, slots=True)
class Impact:
    t_s: float
    surface: str              # 'pad' | 'deck' (off the pad) | 'edge' | 'ground' | 'water' | 'hull'
    normal_speed_mps: float   # relative, along the surface normal, positive approaching
    lateral_speed_mps: float  # relative, along the surface
    tilt_rad: float           # body z vs surface normal
    after_bounce_m: float     # height of the hop that ended here (0 for the first contact)


@dataclass(frozen=True, slots=True)
class LandingRecord:
    contact_kind: str                         # first contact: Impact.surface, or 'none'
    first: Impact | None
    impacts: tuple[Impact, ...]               # the first contact and every later impact
    bounces: int
    max_bounce_height_m: float
    horizontal_error_m: float                 # first contact: CoM to pad centre, in plane
    feet_pad_m: tuple[tuple[float, float], ...]   # each gear point (u, w) from the pad centre
    feet_on_pad: bool
    yaw_rel_rad: float                        # body x vs pad u, about the pad normal
    tipped: bool
    edge_strike: bool
    prop_strike: bool
    slid_off_pad: bool
    left_deck: bool                           # touched the deck, later the ground
    settled: bool
    settled_t_s: float
    success: bool
    crash: bool
    outcome: str                              # 'deck' | 'failed' | 'crash' | 'fallback' | 'none'
    reasons: tuple[str, ...]


_BEFORE, _CONTACT, _AIR = 0, 1, 2


class TouchdownMonitor:
    """Watches a :class:`ContactModel` and its body; see the module docstring."""

    __slots__ = ('_air_max', '_first', '_first_err', '_impacts', '_next_check', '_on_pad_once',
                 '_period', '_phase', '_settle_since', 'bounces', 'contact', 'edge_strike',
                 'left_deck', 'max_bounce_m', 'pad', 'prop_strike', 'rules', 'settled',
                 'settled_t_s', 'slid_off_pad', 'tip_angle', 'tipped', 'touched_deck')

    def __init__(self, rules: OutcomeRules, contact: ContactModel, pad: Pad,
                 static_tip_angle_rad: float) -> None:
        require(0 <= pad.surface_index < len(contact.surfaces), 'pad.surface_index',
                'must name a surface of the contact model', pad.surface_index)
        self.rules = rules
        self.contact = contact
        self.pad = pad
        self.tip_angle = (rules.tip_over_tilt_rad if rules.tip_over_tilt_rad > 0.0
                          else static_tip_angle_rad)
        self._phase = _BEFORE
        self._first: Impact | None = None
        self._first_err = math.nan
        self._impacts: list[Impact] = []
        self._air_max = 0.0
        self._next_check = -math.inf
        self._period = rules.check_period_s * (1.0 - 1e-6)
        self._settle_since = math.inf
        self._on_pad_once = False
        self.bounces = 0
        self.max_bounce_m = 0.0
        self.tipped = self.edge_strike = self.prop_strike = False
        self.slid_off_pad = self.left_deck = self.touched_deck = False
        self.settled = False
        self.settled_t_s = math.inf

    @property
    def in_contact(self) -> bool:
        return self._phase == _CONTACT

    @property
    def first(self) -> Impact | None:
        """The first contact, once there is one."""
        return self._first

    @property
    def done(self) -> bool:
        """The run can end: settled, or a crash that no later event can undo."""
        return self.settled or self.tipped or self.edge_strike or self.prop_strike or any(
            i.normal_speed_mps > self.rules.crash_speed_mps for i in self._impacts)

    # --- per step --------------------------------------------------------------------------

    def update(self, t_s: float, body: RigidBody, armed: bool) -> None:
        c = self.contact
        n_touch = 0
        for n in c.n_gear_contacts:
            n_touch += n
        touching = n_touch > 0 or c.side_contact or c.hull_contact
        phase = self._phase
        if phase == _BEFORE and not touching:
            return
        if c.side_contact:
            self.edge_strike = True
        if c.hull_contact:
            self.prop_strike = True
        if touching and phase != _CONTACT:
            self._touch(t_s, body)
            self._next_check = -math.inf
        elif phase == _CONTACT and not touching:
            self._phase = _AIR
            self._air_max = 0.0
            self._next_check = -math.inf
        if t_s >= self._next_check:
            self._next_check = t_s + self._period
            if self._phase == _CONTACT:
                self._in_contact(t_s, body, armed, n_touch)
            elif self._phase == _AIR:
                h = self._gear_clearance(body)
                if h > self._air_max:
                    self._air_max = h

    def _surface_of_touch(self) -> int:
        c = self.contact
        if c.side_contact:
            return self.pad.surface_index
        best, best_n = self.pad.surface_index, -1
        for si in range(len(c.n_gear_contacts)):
            if c.n_gear_contacts[si] > best_n:
                best, best_n = si, c.n_gear_contacts[si]
        return best

    def _relative(self, body: RigidBody, s: Surface) -> tuple[float, float, float]:
        """(approach speed, lateral speed, tilt) of the body against surface s."""
        vx, vy, vz = s.velocity_at(body.x, body.y, body.z)
        rx, ry, rz = body.vx - vx, body.vy - vy, body.vz - vz
        vn = rx * s.nx + ry * s.ny + rz * s.nz
        lx, ly, lz = rx - vn * s.nx, ry - vn * s.ny, rz - vn * s.nz
        cos_t = body.r02 * s.nx + body.r12 * s.ny + body.r22 * s.nz
        tilt = math.acos(max(-1.0, min(1.0, cos_t)))
        return -vn, math.sqrt(lx * lx + ly * ly + lz * lz), tilt

    def _touch(self, t_s: float, body: RigidBody) -> None:
        c = self.contact
        si = self._surface_of_touch()
        s = c.surfaces[si]
        vn, lat, tilt = self._relative(body, s)
        if c.side_contact:
            kind = 'edge'
        elif c.hull_contact and sum(c.n_gear_contacts) == 0:
            kind = 'hull'
        elif si == self.pad.surface_index:
            kind = 'pad' if self._gear_in_pad(body, True) else 'deck'
        else:
            kind = s.kind
        if kind in ('pad', 'deck'):
            self.touched_deck = True
        elif self.touched_deck and si != self.pad.surface_index:
            self.left_deck = True
        hop = self._air_max if self._phase == _AIR else 0.0
        bounce = hop >= self.rules.bounce_min_height_m
        imp = Impact(t_s, kind, vn, lat, tilt, hop)
        if self._first is None:
            self._first = imp
            a, b, _ = self.contact.surfaces[self.pad.surface_index].local(body.x, body.y, body.z)
            self._first_err = math.hypot(a - self.pad.offset_u_m, b - self.pad.offset_w_m)
            self._impacts.append(imp)
        elif bounce or vn >= self.rules.impact_min_speed_mps:
            self._impacts.append(imp)
        if bounce:
            self.bounces += 1
            if hop > self.max_bounce_m:
                self.max_bounce_m = hop
        self._phase = _CONTACT
        self._air_max = 0.0

    def _in_contact(self, t_s: float, body: RigidBody, armed: bool, n_touch: int) -> None:
        c = self.contact
        s = c.surfaces[self._surface_of_touch()]
        _, _, tilt = self._relative(body, s)
        if tilt > self.tip_angle:
            self.tipped = True
        if c.n_gear_contacts[self.pad.surface_index] > 0:
            if self._gear_in_pad(body, False):
                self._on_pad_once = True
            elif self._on_pad_once:
                self.slid_off_pad = True
        if self.touched_deck:
            for si in range(len(c.n_gear_contacts)):
                if si != self.pad.surface_index and c.n_gear_contacts[si] > 0:
                    self.left_deck = True
        # settling: relative to the surface carrying the vehicle
        vx, vy, vz = s.velocity_at(body.x, body.y, body.z)
        rx, ry, rz = body.vx - vx, body.vy - vy, body.vz - vz
        wx, wy, wz = body.angular_velocity_world()
        wx, wy, wz = wx - s.ox, wy - s.oy, wz - s.oz
        ru = self.rules
        still = (not armed and n_touch >= min(3, c.n_gear)
                 and rx * rx + ry * ry + rz * rz <= ru.settle_speed_mps ** 2
                 and wx * wx + wy * wy + wz * wz <= ru.settle_rate_radps ** 2)
        if not still:
            self._settle_since = math.inf
        elif self._settle_since == math.inf:
            self._settle_since = t_s
        elif not self.settled and t_s - self._settle_since >= ru.settle_time_s - 1e-9:
            self.settled = True
            self.settled_t_s = t_s

    # --- geometry ------------------------------------------------------------------------

    def _pad_coords(self, body: RigidBody, i: int) -> tuple[float, float, float]:
        pts = self.contact.points_body
        s = self.contact.surfaces[self.pad.surface_index]
        qx, qy, qz = body.point_world(pts[3 * i], pts[3 * i + 1], pts[3 * i + 2])
        a, b, h = s.local(qx, qy, qz)
        return a - self.pad.offset_u_m, b - self.pad.offset_w_m, h

    def _gear_in_pad(self, body: RigidBody, touching_only: bool) -> bool:
        """All gear points (or only those touching the pad surface) inside the pad."""
        pad = self.pad
        s = self.contact.surfaces[pad.surface_index]
        for i in range(self.contact.n_gear):
            a, b, h = self._pad_coords(body, i)
            if touching_only and h > 1e-4:
                continue
            if (abs(a) > pad.half_u_m or abs(b) > pad.half_w_m or abs(a + pad.offset_u_m)
                    > s.half_u or abs(b + pad.offset_w_m) > s.half_w):
                return False
        return True

    def _gear_clearance(self, body: RigidBody) -> float:
        """Lowest gear point's height above the surface below it (the pad's if over it)."""
        c = self.contact
        low = math.inf
        for i in range(c.n_gear):
            px, py, pz = c.points_body[3 * i], c.points_body[3 * i + 1], c.points_body[3 * i + 2]
            qx, qy, qz = body.point_world(px, py, pz)
            best = math.inf
            for s in c.surfaces:
                a, b, h = s.local(qx, qy, qz)
                if h >= 0.0 and abs(a) <= s.half_u and abs(b) <= s.half_w and h < best:
                    best = h
            if best < low:
                low = best
        return 0.0 if low == math.inf else low

    # --- outcome -------------------------------------------------------------------------

    def record(self, body: RigidBody) -> LandingRecord:
        """The landing record now, with the outcome rules applied."""
        ru = self.rules
        first = self._first
        pad_s = self.contact.surfaces[self.pad.surface_index]
        feet = []
        on_pad = True
        for i in range(self.contact.n_gear):
            a, b, _ = self._pad_coords(body, i)
            feet.append((a, b))
            if (abs(a) > self.pad.half_u_m or abs(b) > self.pad.half_w_m
                    or abs(a + self.pad.offset_u_m) > pad_s.half_u
                    or abs(b + self.pad.offset_w_m) > pad_s.half_w):
                on_pad = False
        # heading of body x projected on the pad plane, against u
        bxx, bxy, bxz = body.r00, body.r10, body.r20
        yaw_rel = math.atan2(bxx * pad_s.wx + bxy * pad_s.wy + bxz * pad_s.wz,
                             bxx * pad_s.ux + bxy * pad_s.uy + bxz * pad_s.uz)
        err = self._first_err
        reasons: list[str] = []
        crash = False
        if first is None:
            a, b, _ = pad_s.local(body.x, body.y, body.z)
            return LandingRecord('none', None, (), 0, 0.0,
                                 math.hypot(a - self.pad.offset_u_m, b - self.pad.offset_w_m),
                                 tuple(feet), on_pad, yaw_rel, False, False, False, False,
                                 False, False, math.inf, False, False, 'none', ('no contact',))
        for imp in self._impacts:
            if imp.normal_speed_mps > ru.crash_speed_mps:
                reasons.append(f'impact {imp.normal_speed_mps:.2f} m/s > '
                               f'{ru.crash_speed_mps:.2f} at {imp.t_s:.2f} s')
                crash = True
        if self.edge_strike:
            reasons.append('edge strike')
            crash = True
        if self.prop_strike:
            reasons.append('prop strike')
            crash = True
        if self.tipped:
            reasons.append('tipped over')
            crash = True
        if self.left_deck:
            reasons.append('bounced or slid off the deck')
            crash = True
        if first.surface == 'water':
            reasons.append('landed in the water')
            crash = True
        failed = False
        for imp in self._impacts:
            if imp.lateral_speed_mps > ru.max_lateral_speed_mps:
                reasons.append(f'lateral {imp.lateral_speed_mps:.2f} m/s > '
                               f'{ru.max_lateral_speed_mps:.2f} at {imp.t_s:.2f} s')
                failed = True
            if imp.tilt_rad > ru.max_tilt_rad:
                reasons.append(f'tilt {math.degrees(imp.tilt_rad):.1f}° > '
                               f'{math.degrees(ru.max_tilt_rad):.1f}° at {imp.t_s:.2f} s')
                failed = True
        limit = ru.max_bounce_height_m
        if limit is not None and self.max_bounce_m > limit:
            reasons.append(f'bounce {self.max_bounce_m:.3f} m > {limit:.3f}')
            failed = True
        if self.slid_off_pad:
            reasons.append('slid over the pad edge')
            failed = True
        if not on_pad and first.surface in ('pad', 'deck'):
            reasons.append('a foot off the pad')
            failed = True
        if first.surface == 'deck':
            reasons.append('first contact off the pad')
            failed = True
        if not self.settled:
            reasons.append('not settled')
            failed = True
        if crash:
            outcome = 'crash'
        elif first.surface == 'ground':
            outcome = 'fallback'
            reasons.insert(0, 'landed on the ground')
        elif failed:
            outcome = 'failed'
        else:
            outcome = 'deck'
            reasons.append('landed on the pad')
        return LandingRecord(
            contact_kind=first.surface, first=first, impacts=tuple(self._impacts),
            bounces=self.bounces, max_bounce_height_m=self.max_bounce_m,
            horizontal_error_m=err, feet_pad_m=tuple(feet), feet_on_pad=on_pad,
            yaw_rel_rad=yaw_rel, tipped=self.tipped, edge_strike=self.edge_strike,
            prop_strike=self.prop_strike, slid_off_pad=self.slid_off_pad,
            left_deck=self.left_deck, settled=self.settled, settled_t_s=self.settled_t_s,
            success=outcome == 'deck', crash=crash, outcome=outcome, reasons=tuple(reasons))
