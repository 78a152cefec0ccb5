"""Parameters of the ship deck model: the ``ship:`` mapping of a scenario, and the built-ins.

``ShipParams`` has one field per YAML key (table in ``docs/world/ship.md``), validated at
construction with ``deckland_common.validate``; ``ShipParams.from_mapping`` takes YAML (lists for
tuples, ints for floats) and refuses unknown keys. ``SHIP_BUILTINS`` are the parameter sets of the
``ship_ss3``, ``ship_ss4`` and ``ship_turning`` scenarios. The model is ``deck_simulator.ship``.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
import math
from typing import Any

from deckland_common.validate import (
    finite,
    finite_tuple,
    in_range,
    integer_at_least,
    is_finite_number,
    one_of,
    require,
)

SPECTRA = ('jonswap', 'pierson_moskowitz')


@dataclass(frozen=True, slots=True)
class ShipParams:
    """The ``ship:`` mapping of a scenario; field = YAML key (docs/world/ship.md)."""

    # vessel (a 20 m monohull workboat; docs/world/ship.md "Default vessel")
    length_m: float = 20.0               # waterline length L
    beam_m: float = 6.0                  # waterline beam B
    draft_m: float = 1.6                 # mean draft d
    # track: the mean (calm-water) motion of the centre of motion
    speed_mps: float = 2.5               # U, forward speed through the water
    heading_rad: float = 0.0             # ψ0, ENU yaw of the bow at t = 0
    turn_rate_radps: float = 0.0         # r, constant rate of turn (+ = to port, CCW)
    pad_position_m: tuple[float, float] = (0.0, 0.0)   # pad centre's mean position at t = 0
    motion_centre_height_m: float = 0.6  # centre of motion above the mean water level (z = 0)
    pad_offset_m: tuple[float, float, float] = (-5.0, 0.0, 1.9)  # pad top from it, hull FLU
    deck_size_m: tuple[float, float] = (5.0, 5.0)  # deck around the pad (centred), along × across
    # sea
    significant_height_m: float = 0.88   # Hs = 4 √m0
    peak_period_s: float = 7.5           # Tp
    spectrum: str = 'jonswap'
    jonswap_gamma: float = 3.3
    wave_heading_rad: float = math.pi    # β0: waves' travel direction − ψ0 (π head, 0 following)
    spreading_s: float | None = 1.0      # D(δ) ∝ cos^2s δ, |δ| ≤ π/2; None: long-crested
    components: int = 100                # wave components (frequency bins)
    # responses: damped second-order systems at the encounter frequency
    heave_period_s: float = 2.8
    heave_damping: float = 0.25
    roll_period_s: float = 5.4
    roll_damping: float = 0.08
    pitch_period_s: float = 2.8
    pitch_damping: float = 0.25
    # numerics
    table_dt_s: float = 0.1              # node spacing of the interpolated table

    def __post_init__(self) -> None:
        for name in ('length_m', 'beam_m', 'draft_m'):
            in_range(name, getattr(self, name), 0.5, 400.0)
        in_range('speed_mps', self.speed_mps, 0.0, 30.0)
        finite('heading_rad', self.heading_rad)
        in_range('turn_rate_radps', self.turn_rate_radps, -0.5, 0.5)
        finite_tuple('pad_position_m', self.pad_position_m, 2)
        finite('motion_centre_height_m', self.motion_centre_height_m)
        finite_tuple('pad_offset_m', self.pad_offset_m, 3)
        finite_tuple('deck_size_m', self.deck_size_m, 2)
        require(all(v > 0.0 for v in self.deck_size_m), 'deck_size_m', 'must be > 0',
                self.deck_size_m)
        require(self.motion_centre_height_m + self.pad_offset_m[2] > 0.0, 'pad_offset_m',
                'must put the pad top above the mean water level '
                '(motion_centre_height_m + pad_offset_m[2] > 0)', self.pad_offset_m)
        in_range('significant_height_m', self.significant_height_m, 0.0, 20.0)
        in_range('peak_period_s', self.peak_period_s, 1.0, 30.0)
        one_of('spectrum', self.spectrum, SPECTRA)
        in_range('jonswap_gamma', self.jonswap_gamma, 1.0, 10.0)
        finite('wave_heading_rad', self.wave_heading_rad)
        if self.spreading_s is not None:
            in_range('spreading_s', self.spreading_s, 0.0, 1000.0)
        integer_at_least('components', self.components, 2)
        require(self.components <= 1000, 'components', 'must be <= 1000', self.components)
        for name in ('heave_period_s', 'roll_period_s', 'pitch_period_s'):
            in_range(name, getattr(self, name), 0.5, 60.0)
        for name in ('heave_damping', 'roll_damping', 'pitch_damping'):
            v = getattr(self, name)
            require(is_finite_number(v) and 0.0 < v <= 2.0, name, 'must be in (0, 2]', v)
        in_range('table_dt_s', self.table_dt_s, 0.001, 0.2)
        # YAML gives lists and ints: store tuples of floats
        object.__setattr__(self, 'pad_position_m', tuple(float(v) for v in self.pad_position_m))
        object.__setattr__(self, 'pad_offset_m', tuple(float(v) for v in self.pad_offset_m))
        object.__setattr__(self, 'deck_size_m', tuple(float(v) for v in self.deck_size_m))

    @classmethod
    def from_mapping(cls, data: Any, path: str = 'ship') -> ShipParams:
        """Build from a YAML mapping; unknown keys and bad values raise ``ValueError``."""
        if not isinstance(data, dict):
            raise ValueError(f'{path} must be a mapping, got {data!r}')
        types = {f.name: str(f.type) for f in fields(cls)}
        unknown = sorted(str(k) for k in data if k not in types)
        if unknown:
            raise ValueError(f'{path}: unknown key(s) {unknown}; known: {sorted(types)}')
        values = {}
        for key, value in data.items():     # YAML lists for tuples, ints for floats
            if types[key].startswith('tuple') and isinstance(value, list | tuple):
                value = tuple(_as_float(v) for v in value)
            elif types[key].startswith('float'):
                value = _as_float(value)
            values[key] = value
        try:
            return cls(**values)
        except ValueError as exc:
            raise ValueError(f'{path}.{exc}') from None
        except TypeError as exc:
            raise ValueError(f'{path}: {exc}') from None


def _as_float(value: Any) -> Any:
    return float(value) if isinstance(value, int) and not isinstance(value, bool) else value


#: The built-in parameter sets of the ship scenarios (docs/world/ship.md "Built-ins").
SHIP_BUILTINS: dict[str, ShipParams] = {
    # WMO sea state 3 (Bales et al. 1981 mean Hs and modal Tp), head seas, 2.5 m/s
    'ship_ss3': ShipParams(significant_height_m=0.88, peak_period_s=7.5, speed_mps=2.5,
                           wave_heading_rad=math.pi),
    # WMO sea state 4, stern-quartering seas (waves from 45° off the stern), 2.5 m/s
    'ship_ss4': ShipParams(significant_height_m=1.88, peak_period_s=8.8, speed_mps=2.5,
                           wave_heading_rad=math.pi / 4.0),
    # sea state 3, 2 m/s, turning to port at 1.5 °/s from head seas through beam seas
    'ship_turning': ShipParams(significant_height_m=0.88, peak_period_s=7.5, speed_mps=2.0,
                               wave_heading_rad=math.pi,
                               turn_rate_radps=math.radians(1.5)),
}
