"""Pinhole model of the down-looking IR camera: beacon pixel → relative position (pure).

Paper (29)-(30) with α = half of a configurable *full* FOV (Table 2 lists the Pixy's full
60°/47°), i.e. the pinhole model of a level camera (``paper_exact=True``). The default
generalises it: the pixel is undistorted (Brown–Conrady, :mod:`deckland_common.lens`; the
Pixy lens by default), its ray is rotated by the camera mount and the vehicle attitude into
ENU and intersected with the deck plane ``height_above_deck_m`` below the body origin (no
tilt error: ≈ 0.27 m at 10° and 1.5 m with (29)-(30)). (35) is ``rel_ENU = Rz(ψ) rel_FLU``.
Frames: :mod:`deckland_common.frames`; default mount: optical x = body −y, y = −x, z = −z.
Decisions and tests: the package README (decisions 1-5).
"""

from __future__ import annotations

from dataclasses import dataclass
import math

from deckland_common.frames import body_to_world_xy, mat_vec, rot_body_to_world
from deckland_common.lens import PIXY_K1, PIXY_K2, undistort

from deckland_common import validate as chk

# Default mount, columns = optical x, y, z axes expressed in body FLU.
_R_DEFAULT = ((0.0, -1.0, 0.0), (-1.0, 0.0, 0.0), (0.0, 0.0, -1.0))


@dataclass(frozen=True)
class CameraParams:
    """Intrinsics and mount of the Pixy. ``fov_*_deg`` are *full* fields of view."""

    fov_x_deg: float = 60.0
    fov_y_deg: float = 47.0
    width_px: float = 320.0
    height_px: float = 200.0
    cx_px: float = 160.0
    cy_px: float = 100.0
    mount_x_m: float = 0.0      # camera position relative to the body origin, FLU
    mount_y_m: float = 0.0
    mount_z_m: float = 0.0
    mount_roll_rad: float = 0.0   # extra rotation of the camera, body axes, Z-Y-X like the
    mount_pitch_rad: float = 0.0  # vehicle attitude (a mount pitch p looks exactly like a
    mount_yaw_rad: float = 0.0    # vehicle pitch p with a default mount)
    min_ray_down_cos: float = 0.1  # rays flatter than acos(this) from straight down: no fix
    k1: float = PIXY_K1           # lens distortion (Brown–Conrady, normalised coordinates):
    k2: float = PIXY_K2           # radial k1, k2 (the Pixy lens), tangential p1, p2;
    p1: float = 0.0               # all zero: the pinhole of (29)-(30)
    p2: float = 0.0
    paper_exact: bool = False     # (29)-(30) with z as given, no tilt, yaw-only rotation (35)

    def __post_init__(self) -> None:
        o = 'CameraParams'
        chk.in_range(f'{o}.fov_x_deg', self.fov_x_deg, 1.0, 170.0)
        chk.in_range(f'{o}.fov_y_deg', self.fov_y_deg, 1.0, 170.0)
        chk.positive(f'{o}.width_px', self.width_px)
        chk.positive(f'{o}.height_px', self.height_px)
        chk.in_range(f'{o}.cx_px', self.cx_px, 0.0, self.width_px)
        chk.in_range(f'{o}.cy_px', self.cy_px, 0.0, self.height_px)
        for name in ('mount_x_m', 'mount_y_m', 'mount_z_m'):
            chk.in_range(f'{o}.{name}', getattr(self, name), -2.0, 2.0)
        for name in ('mount_roll_rad', 'mount_pitch_rad', 'mount_yaw_rad'):
            chk.in_range(f'{o}.{name}', getattr(self, name), -math.pi, math.pi)
        chk.in_range(f'{o}.min_ray_down_cos', self.min_ray_down_cos, 0.0, 0.99)
        for name in ('k1', 'k2'):
            chk.in_range(f'{o}.{name}', getattr(self, name), -2.0, 2.0)
        for name in ('p1', 'p2'):
            chk.in_range(f'{o}.{name}', getattr(self, name), -0.1, 0.1)
        if not isinstance(self.paper_exact, bool):
            raise ValueError(f'{o}.paper_exact must be a bool, got {self.paper_exact!r}')

    @property
    def fx_px(self) -> float:
        """Focal length in x pixels, f_x = (W/2) / tan(fov_x/2)."""
        return 0.5 * self.width_px / math.tan(math.radians(self.fov_x_deg) / 2.0)

    @property
    def fy_px(self) -> float:
        """Focal length in y pixels, f_y = (H/2) / tan(fov_y/2)."""
        return 0.5 * self.height_px / math.tan(math.radians(self.fov_y_deg) / 2.0)


class CameraModel:
    """Pixel → beacon-minus-vehicle horizontal offset in ENU axes (see module docstring)."""

    __slots__ = (
        '_cx',
        '_cy',
        '_default_mount',
        '_inv_fx',
        '_inv_fy',
        '_lens',
        '_m',
        '_min_cos',
        '_off',
        '_paper_kx',
        '_paper_ky',
        'params',
    )

    def __init__(self, params: CameraParams | None = None) -> None:
        p = params if params is not None else CameraParams()
        self.params = p
        self._cx, self._cy = float(p.cx_px), float(p.cy_px)
        self._inv_fx, self._inv_fy = 1.0 / p.fx_px, 1.0 / p.fy_px
        mount = rot_body_to_world(p.mount_roll_rad, p.mount_pitch_rad, p.mount_yaw_rad)
        # R_body←optical = R_mount · R_default
        self._m = tuple(
            tuple(sum(mount[i][k] * _R_DEFAULT[k][j] for k in range(3)) for j in range(3))
            for i in range(3))
        self._default_mount = p.mount_roll_rad == 0.0 and p.mount_pitch_rad == 0.0 and (
            p.mount_yaw_rad == 0.0)
        self._off = (float(p.mount_x_m), float(p.mount_y_m), float(p.mount_z_m))
        self._min_cos = float(p.min_ray_down_cos)
        lens = (float(p.k1), float(p.k2), float(p.p1), float(p.p2))
        self._lens = lens if any(c != 0.0 for c in lens) else None
        # (29)-(30): tan α / x_max with α the half FOV (= 1 / f)
        self._paper_kx = math.tan(math.radians(p.fov_x_deg) / 2.0) / (0.5 * p.width_px)
        self._paper_ky = math.tan(math.radians(p.fov_y_deg) / 2.0) / (0.5 * p.height_px)

    def ray_body(self, px: float, py: float) -> tuple[float, float, float]:
        """Un-normalised ray of pixel (px, py) in body FLU axes (optical ray (u, v, 1),
        undistorted)."""
        u = (px - self._cx) * self._inv_fx
        v = (py - self._cy) * self._inv_fy
        lens = self._lens
        if lens is not None:
            u, v = undistort(u, v, lens[0], lens[1], lens[2], lens[3])
        if self._default_mount:
            return -v, -u, -1.0
        m = self._m
        return (m[0][0] * u + m[0][1] * v + m[0][2],
                m[1][0] * u + m[1][1] * v + m[1][2],
                m[2][0] * u + m[2][1] * v + m[2][2])

    def relative_position(self, px: float, py: float, height_above_deck_m: float,
                          roll: float, pitch: float, yaw: float) -> tuple[float, float] | None:
        """Beacon minus vehicle (body origin), ENU axes, metres; None if the ray misses the deck.

        Tilt-compensated model: ray d_b = R_bc (u, v, 1), u = (px−cx)/f_x, v = (py−cy)/f_y;
        d_w = R(φ,θ,ψ) d_b; camera at o_w = R · mount offset; the deck plane is
        z = −height_above_deck_m relative to the body origin; s = (−h − o_z)/d_z.
        With ``paper_exact`` the paper's (29)-(30) are evaluated with z = height_above_deck_m
        (the caller passes the raw lidar range, as the paper does) and rotated by yaw only,
        our form of (35).
        """
        if self.params.paper_exact:
            return self.paper_relative_position(px, py, height_above_deck_m, yaw)
        dbx, dby, dbz = self.ray_body(px, py)
        cr, sr = math.cos(roll), math.sin(roll)
        cp, sp = math.cos(pitch), math.sin(pitch)
        cy, sy = math.cos(yaw), math.sin(yaw)
        # third row of R = Rz Ry Rx first: the ray must point down
        r20, r21, r22 = -sp, cp * sr, cp * cr
        dwz = r20 * dbx + r21 * dby + r22 * dbz
        norm = math.sqrt(dbx * dbx + dby * dby + dbz * dbz)
        if dwz > -self._min_cos * norm:
            return None
        r00, r01, r02 = cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr
        r10, r11, r12 = sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr
        dwx = r00 * dbx + r01 * dby + r02 * dbz
        dwy = r10 * dbx + r11 * dby + r12 * dbz
        ox, oy, oz = self._off
        if ox == 0.0 and oy == 0.0 and oz == 0.0:
            s = -height_above_deck_m / dwz
            return s * dwx, s * dwy
        owx = r00 * ox + r01 * oy + r02 * oz
        owy = r10 * ox + r11 * oy + r12 * oz
        owz = r20 * ox + r21 * oy + r22 * oz
        s = (-height_above_deck_m - owz) / dwz
        if s <= 0.0:
            return None
        return owx + s * dwx, owy + s * dwy

    def paper_relative_position(self, px: float, py: float, z_m: float,
                                yaw: float) -> tuple[float, float]:
        """(29)-(30) in the paper's body frame, then our (35): FLU (x, −y_paper) → ENU by yaw."""
        y_paper = z_m * self._paper_kx * (px - self._cx)      # (29)
        x_paper = -z_m * self._paper_ky * (py - self._cy)     # (30)
        return body_to_world_xy(x_paper, -y_paper, yaw)

    def ray_world(self, px: float, py: float, roll: float, pitch: float,
                  yaw: float) -> tuple[float, float, float]:
        """The pixel's ray in world ENU axes (diagnostics and tests)."""
        return mat_vec(rot_body_to_world(roll, pitch, yaw), self.ray_body(px, py))
