"""The deck interface the world uses for every deck model (pure, plain floats).

:class:`PadState` is the deck at one instant (pad centre, velocity, acceleration, attitude,
angular velocity and acceleration, world ENU) with the helpers contact, lidar and beacon need
(plane, height under a point, deck/world frames, motion of a deck-fixed point).
:class:`DeckMotion` is the protocol (``pad_state(t_s)``); :class:`HeaveDeckMotion` adapts the
heave-only :class:`~deck_simulator.deck.Deck`, ``deck_simulator.ship.ShipMotion`` is the ship.
"""

from __future__ import annotations

from typing import Protocol

from deckland_common.frames import Mat3, Vec3

from deck_simulator.deck import Deck


def _cross(a: Vec3, b: Vec3) -> Vec3:
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


_IDENTITY: Mat3 = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))


class PadState:
    """The deck at one instant, world ENU; the deck frame is the pad frame. Read-only.

    Deck frame: origin at the pad centre on its top surface, axes of the hull (FLU: x to the
    bow, y to port, z out of the deck). ``rotation`` takes deck vectors to world vectors
    (``rot_body_to_world(*rpy_rad)``); angular velocity and acceleration are world vectors.
    A plain class, not a frozen dataclass: it is built on every call of the hot path.
    """

    __slots__ = ('accel_mps2', 'alpha_radps2', 'omega_radps', 'position_m', 'rotation',
                 'rpy_rad', 'velocity_mps')

    def __init__(self, position_m: Vec3, velocity_mps: Vec3, accel_mps2: Vec3, rpy_rad: Vec3,
                 omega_radps: Vec3, alpha_radps2: Vec3, rotation: Mat3) -> None:
        self.position_m = position_m
        self.velocity_mps = velocity_mps
        self.accel_mps2 = accel_mps2
        self.rpy_rad = rpy_rad          # roll, pitch, yaw (Z-Y-X, frames); yaw = heading
        self.omega_radps = omega_radps
        self.alpha_radps2 = alpha_radps2
        self.rotation = rotation

    def as_tuple(self) -> tuple[Vec3, Vec3, Vec3, Vec3, Vec3, Vec3]:
        """(position, velocity, acceleration, rpy, ω, α): for comparisons and logs."""
        return (self.position_m, self.velocity_mps, self.accel_mps2, self.rpy_rad,
                self.omega_radps, self.alpha_radps2)

    def normal(self) -> Vec3:
        """Unit normal of the deck plane (world), pointing up out of the deck."""
        r = self.rotation
        return r[0][2], r[1][2], r[2][2]

    def plane(self) -> tuple[Vec3, Vec3]:
        """The deck plane: a point on it (the pad centre) and its unit normal."""
        return self.position_m, self.normal()

    def height_under(self, x_m: float, y_m: float) -> float:
        """World z of the deck plane below (or above) the world point (x, y)."""
        p = self.position_m
        r = self.rotation
        nx, ny, nz = r[0][2], r[1][2], r[2][2]
        return p[2] - (nx * (x_m - p[0]) + ny * (y_m - p[1])) / nz

    def to_world(self, point_deck: Vec3) -> Vec3:
        """World position of a point given in the deck frame."""
        r = self.rotation
        p = self.position_m
        x, y, z = point_deck
        return (p[0] + r[0][0] * x + r[0][1] * y + r[0][2] * z,
                p[1] + r[1][0] * x + r[1][1] * y + r[1][2] * z,
                p[2] + r[2][0] * x + r[2][1] * y + r[2][2] * z)

    def to_deck(self, point_world: Vec3) -> Vec3:
        """Deck-frame coordinates of a world point (z = height above the deck plane)."""
        r = self.rotation
        p = self.position_m
        dx, dy, dz = point_world[0] - p[0], point_world[1] - p[1], point_world[2] - p[2]
        return (r[0][0] * dx + r[1][0] * dy + r[2][0] * dz,
                r[0][1] * dx + r[1][1] * dy + r[2][1] * dz,
                r[0][2] * dx + r[1][2] * dy + r[2][2] * dz)

    def point_velocity(self, point_world: Vec3) -> Vec3:
        """World velocity of the deck-fixed point at a world position: v + ω × (p − P)."""
        p = self.position_m
        w = _cross(self.omega_radps, (point_world[0] - p[0], point_world[1] - p[1],
                                      point_world[2] - p[2]))
        v = self.velocity_mps
        return v[0] + w[0], v[1] + w[1], v[2] + w[2]

    def point_accel(self, point_world: Vec3) -> Vec3:
        """World acceleration of that deck-fixed point: a + α × r + ω × (ω × r)."""
        p = self.position_m
        r = (point_world[0] - p[0], point_world[1] - p[1], point_world[2] - p[2])
        t = _cross(self.alpha_radps2, r)
        c = _cross(self.omega_radps, _cross(self.omega_radps, r))
        a = self.accel_mps2
        return a[0] + t[0] + c[0], a[1] + t[1] + c[1], a[2] + t[2] + c[2]

    def relative_velocity(self, point_world: Vec3, velocity_world: Vec3) -> Vec3:
        """Velocity of a body at a world point relative to the deck under it, deck axes."""
        d = self.point_velocity(point_world)
        r = self.rotation
        vx = velocity_world[0] - d[0]
        vy = velocity_world[1] - d[1]
        vz = velocity_world[2] - d[2]
        return (r[0][0] * vx + r[1][0] * vy + r[2][0] * vz,
                r[0][1] * vx + r[1][1] * vy + r[2][1] * vz,
                r[0][2] * vx + r[1][2] * vy + r[2][2] * vz)


class DeckMotion(Protocol):
    """What the world asks of any deck: its state at a time (the helpers are on PadState)."""

    def pad_state(self, t_s: float) -> PadState: ...


class HeaveDeckMotion:
    """The heave-only :class:`~deck_simulator.deck.Deck` as a :class:`DeckMotion`.

    Level, world-axis aligned (yaw 0), drifting at the deck's constant drift velocity.
    """

    __slots__ = ('deck',)

    def __init__(self, deck: Deck) -> None:
        self.deck = deck

    def pad_state(self, t_s: float) -> PadState:
        cx, cy, z, vz, az = self.deck.state(t_s)
        zero: Vec3 = (0.0, 0.0, 0.0)
        return PadState((cx, cy, z), (self.deck.drift_x, self.deck.drift_y, vz), (0.0, 0.0, az),
                        zero, zero, zero, _IDENTITY)
