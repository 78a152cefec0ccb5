"""Scenarios: nested frozen dataclasses loaded from YAML with strict validation.

``load_scenario(name_or_path)`` takes a built-in name (``builtin_names()``: the YAML files in
``deck_simulator/data/``) or a path. Unknown keys are rejected, types and ranges checked, and
every error names the source and the key path, e.g. ``scenario 'x.yaml': apron.heave.stroke_m
must be > 0, got -1``. ``vehicle`` and ``sensors`` override fields of ``VehicleParams`` /
``SensorSuiteParams`` (a partial section keeps the defaults of the keys it does not give;
lists stand for tuples);
``faults`` is validated by :func:`deck_simulator.faults.parse_faults`.
"""

from __future__ import annotations

from dataclasses import MISSING, dataclass, field, fields, is_dataclass, replace
from pathlib import Path
import typing
from typing import Any

from deckland_common.validate import is_finite_number, require
import yaml

from deck_simulator.faults import FaultSpec, parse_faults
from deck_simulator.sensor_suite import SensorSuiteParams
from deck_simulator.ship_link import ShipTelemetryParams
from deck_simulator.ship_params import ShipParams
from deck_simulator.touchdown import OutcomeRules
from deck_simulator.vehicle import VehicleParams

DATA_DIR = Path(__file__).resolve().parent / 'data'

HEAVE_MODELS = ('none', 'triangle', 'sine', 'sea_state')
SPECTRA = ('jonswap', 'pierson_moskowitz')
_HEAVE_KEYS = {
    'none': {'model'},
    'triangle': {'model', 'stroke_m', 'speed_mps'},
    'sine': {'model', 'amplitude_m', 'period_s'},
    'sea_state': {'model', 'significant_height_m', 'peak_period_s', 'spectrum', 'components',
                  'jonswap_gamma'},
}


@dataclass(frozen=True, slots=True)
class HeaveSpec:
    """Deck heave model and its parameters (only the chosen model's keys may be given)."""

    model: str = 'none'
    stroke_m: float = 0.30           # triangle: peak-to-peak (Table 3: 300 mm)
    speed_mps: float = 0.09          # triangle: constant speed (Table 3: 90 mm/s)
    amplitude_m: float = 0.25        # sine
    period_s: float = 6.0            # sine
    significant_height_m: float = 1.0   # sea_state: Hs = 4 √m0
    peak_period_s: float = 7.0       # sea_state: Tp
    spectrum: str = 'jonswap'        # sea_state: jonswap | pierson_moskowitz
    components: int = 80             # sea_state: number of sinusoids
    jonswap_gamma: float = 3.3       # sea_state: JONSWAP peak enhancement

    def __post_init__(self) -> None:
        require(self.model in HEAVE_MODELS, 'model', f'must be one of {list(HEAVE_MODELS)}',
                self.model)
        for name in ('stroke_m', 'speed_mps', 'period_s', 'peak_period_s'):
            v = getattr(self, name)
            require(is_finite_number(v) and v > 0, name, 'must be > 0', v)
        for name in ('amplitude_m', 'significant_height_m'):
            v = getattr(self, name)
            require(is_finite_number(v) and v >= 0, name, 'must be >= 0', v)
        require(self.spectrum in SPECTRA, 'spectrum', f'must be one of {list(SPECTRA)}',
                self.spectrum)
        require(isinstance(self.components, int) and 2 <= self.components <= 1000, 'components',
                'must be an integer in [2, 1000]', self.components)
        require(is_finite_number(self.jonswap_gamma) and self.jonswap_gamma >= 1.0,
                'jonswap_gamma', 'must be >= 1', self.jonswap_gamma)


@dataclass(frozen=True, slots=True)
class ApronSpec:
    """The pad: the paper's apron (a box on the ground that heaves and drifts), or the pad
    on a ship's deck (``ship``: docs/world/ship.md; the ship places and moves it)."""

    position_m: tuple[float, float] = (-3.2, -2.0)      # beacon / pad centre, world ENU
    size_m: tuple[float, float] = (1.05, 0.85)          # x × y extent (Table 3); ship: along
    #                                                     × across the hull
    mean_height_m: float = 0.60                         # pad top above ground
    heave: HeaveSpec = field(default_factory=HeaveSpec)
    drift_velocity_mps: tuple[float, float] = (0.0, 0.0)
    ship: ShipParams | None = None

    def __post_init__(self) -> None:
        require(all(v > 0 for v in self.size_m), 'size_m', 'must be > 0', self.size_m)
        require(self.mean_height_m >= 0, 'mean_height_m', 'must be >= 0', self.mean_height_m)
        if self.ship is not None:
            require(self.heave.model == 'none' and self.drift_velocity_mps == (0.0, 0.0)
                    and self.position_m == (-3.2, -2.0) and self.mean_height_m == 0.60,
                    'ship', 'places and moves the pad: give no position_m, mean_height_m, '
                    'heave or drift_velocity_mps with it', 'both')
            require(self.size_m[0] <= self.ship.deck_size_m[0]
                    and self.size_m[1] <= self.ship.deck_size_m[1], 'size_m',
                    "must fit on the ship's deck (ship.deck_size_m)", self.size_m)


@dataclass(frozen=True, slots=True)
class WindSpec:
    """Mean wind plus Ornstein–Uhlenbeck gusts (per axis, stationary σ, correlation τ)."""

    mean_mps: tuple[float, float] = (0.0, 0.0)
    gust_std_mps: float = 0.0
    gust_tau_s: float = 2.0
    vertical_gust_ratio: float = 0.3      # σ_z / σ_xy

    def __post_init__(self) -> None:
        require(self.gust_std_mps >= 0, 'gust_std_mps', 'must be >= 0', self.gust_std_mps)
        require(self.gust_tau_s > 0, 'gust_tau_s', 'must be > 0', self.gust_tau_s)
        require(self.vertical_gust_ratio >= 0, 'vertical_gust_ratio', 'must be >= 0',
                self.vertical_gust_ratio)


@dataclass(frozen=True, slots=True)
class RandomizeSpec:
    """Per-run randomisation drawn from the seed (noise streams are always seeded)."""

    start_offset_m: float = 0.0          # uniform in a disc of this radius
    start_yaw_rad: float = 0.0           # uniform in ± this
    heave_phase: bool = True             # random triangle/sine phase
    gps_bias: bool = True                # initial GPS/baro bias drawn from its stationary law
    wind_direction_rad: float = 0.0      # mean wind rotated by uniform ± this
    mean_height_m: float = 0.0           # deck mean height jitter, uniform ± this

    def __post_init__(self) -> None:
        for name in ('start_offset_m', 'start_yaw_rad', 'wind_direction_rad', 'mean_height_m'):
            v = getattr(self, name)
            require(v >= 0, name, 'must be >= 0', v)


@dataclass(frozen=True, slots=True)
class Scenario:
    name: str = 'default'
    timeout_s: float = 120.0
    start_position_m: tuple[float, float, float] = (-2.8, -0.3, 2.0)
    start_yaw_rad: float = 0.0
    apron: ApronSpec = field(default_factory=ApronSpec)
    wind: WindSpec = field(default_factory=WindSpec)
    vehicle: VehicleParams = field(default_factory=VehicleParams)
    sensors: SensorSuiteParams = field(default_factory=SensorSuiteParams)
    randomize: RandomizeSpec = field(default_factory=RandomizeSpec)
    faults: tuple[FaultSpec, ...] = ()   # entries may be given as mappings (parsed here)
    #: the landing's outcome rules (touchdown.OutcomeRules; docs/world/contact.md)
    outcome: OutcomeRules = field(default_factory=OutcomeRules)
    #: the ship's own MAVLink telemetry (deck_simulator.ship_link); None: no telemetry
    ship_telemetry: ShipTelemetryParams | None = None

    def __post_init__(self) -> None:
        require(self.timeout_s > 0, 'timeout_s', 'must be > 0', self.timeout_s)
        require(self.start_position_m[2] > 0, 'start_position_m', 'must have z > 0',
                self.start_position_m)
        object.__setattr__(self, 'faults', parse_faults(self.faults))

    @property
    def landing_area_m(self) -> tuple[float, float]:
        """Where an operator says the pad is at the start (the planner's landing area)."""
        ship = self.apron.ship
        if ship is not None:
            return ship.pad_position_m[0], ship.pad_position_m[1]
        return self.apron.position_m


# --- generic YAML → dataclass builder ---------------------------------------------------------

#: keys of the ideal sensors the honest models replaced (docs/world/sensors.md): refused
#: with the key that now does the job
RETIRED_KEYS = {
    'sensors.camera.rate_hz': 'sensors.true_camera.timing.rate_hz',
    'sensors.camera.latency_s': 'sensors.true_camera.timing.latency_s',
    'sensors.lidar.rate_hz': 'sensors.lidar.timing.rate_hz',
    'sensors.lidar.noise_m': 'sensors.lidar.noise_std_m (and the other error keys)',
    'sensors.imu.rate_hz': 'sensors.imu.timing.rate_hz',
    'sensors.imu.attitude_noise_rad': 'sensors.attitude.tilt_noise_rad',
    'sensors.imu.yaw_noise_rad': 'sensors.attitude.yaw_noise_rad',
    'sensors.imu.accel_noise_mps2': 'sensors.imu.accel_noise_density',
    'sensors.gps': 'sensors.local_position (horizontal / vertical / timing)',
}

def _convert(tp: Any, value: Any, path: str, base: Any = None) -> Any:
    origin = typing.get_origin(tp)
    if is_dataclass(tp):
        if not isinstance(value, dict):
            raise ValueError(f'{path} must be a mapping, got {value!r}')
        return _build(tp, value, path, base)
    if tp is float:
        if not is_finite_number(value):
            raise ValueError(f'{path} must be a finite number, got {value!r}')
        return float(value)
    if tp is int:
        if not isinstance(value, int) or isinstance(value, bool):
            raise ValueError(f'{path} must be an integer, got {value!r}')
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise ValueError(f'{path} must be true or false, got {value!r}')
        return value
    if tp is str:
        if not isinstance(value, str):
            raise ValueError(f'{path} must be a string, got {value!r}')
        return value
    if path == 'faults':
        return parse_faults(value)
    if path == 'ship_telemetry':
        return None if value is None else _convert(ShipTelemetryParams, value, path)
    if path == 'apron.ship':
        return None if value is None else ShipParams.from_mapping(value, path)
    if tp is tuple or origin is tuple:
        if not isinstance(value, list | tuple):
            raise ValueError(f'{path} must be a list, got {value!r}')
        args = typing.get_args(tp)
        if not args or (len(args) == 2 and args[1] is Ellipsis):
            inner = args[0] if args else Any
            return tuple(value if inner is Any else
                         (_convert(inner, v, f'{path}[{i}]') for i, v in enumerate(value)))
        if len(value) != len(args):
            raise ValueError(f'{path} must have {len(args)} entries, got {value!r}')
        return tuple(_convert(a, v, f'{path}[{i}]') for i, (a, v) in
                     enumerate(zip(args, value, strict=True)))
    return value


def _field_default(cls: type, name: str) -> Any:
    for f in fields(cls):
        if f.name == name:
            if f.default is not MISSING:
                return f.default
            if f.default_factory is not MISSING:
                return f.default_factory()
    return None


def _build(cls: type, data: dict, path: str, base: Any = None) -> Any:
    """``cls`` from ``data``; the keys not given keep ``base``'s values (the field's default
    in the enclosing dataclass), so a partial section changes only what it names."""
    hints = typing.get_type_hints(cls)
    names = [f.name for f in fields(cls)]
    allowed = set(names)
    if cls is HeaveSpec:
        model = data.get('model', 'none')
        if model not in HEAVE_MODELS:
            raise ValueError(f'{path}.model must be one of {list(HEAVE_MODELS)}, got {model!r}')
        allowed = _HEAVE_KEYS[model]
    kwargs = {}
    for key, value in data.items():
        where = f'{path}.{key}' if path else str(key)
        if where in RETIRED_KEYS:
            raise ValueError(f'key {where!r} is retired: use {RETIRED_KEYS[where]}')
        if key not in allowed:
            raise ValueError(f'unknown key {where!r} (allowed: {sorted(allowed)})')
        tp = hints[key]
        sub = None
        if is_dataclass(tp):
            sub = getattr(base, key) if base is not None else _field_default(cls, key)
        kwargs[key] = _convert(tp, value, where, sub)
    try:
        if base is not None:
            return replace(base, **kwargs)
        return cls(**kwargs)
    except ValueError as exc:
        raise ValueError(f'{path + "." if path else ""}{exc}') from None
    except TypeError as exc:  # pragma: no cover - only with malformed dataclasses
        raise ValueError(f'{path}: {exc}') from None


def scenario_from_dict(data: dict, source: str = '<dict>') -> Scenario:
    """Build and validate a :class:`Scenario`; ValueError names the source and key path."""
    if not isinstance(data, dict):
        raise ValueError(f'scenario {source!r}: top level must be a mapping, got {data!r}')
    try:
        return _build(Scenario, data, '')
    except ValueError as exc:
        raise ValueError(f'scenario {source!r}: {exc}') from None


def builtin_names() -> list[str]:
    """Names of the scenarios shipped in deck_simulator/data/."""
    return sorted(p.stem for p in DATA_DIR.glob('*.yaml'))


def load_scenario(name_or_path: str | Path) -> Scenario:
    """A built-in scenario by name, or a YAML file by path."""
    text = str(name_or_path)
    path = Path(text)
    if text in builtin_names():
        path = DATA_DIR / f'{text}.yaml'
    elif not path.is_file():
        raise ValueError(f'scenario {text!r}: no such built-in ({", ".join(builtin_names())}) '
                         'or file')
    try:
        data = yaml.safe_load(path.read_text(encoding='utf-8'))
    except yaml.YAMLError as exc:
        raise ValueError(f'scenario {text!r}: invalid YAML: {exc}') from None
    if data is None:
        data = {}
    return scenario_from_dict(data, text)


def default_value(cls: type, name: str) -> Any:
    """The default of a dataclass field (README tables)."""
    for f in fields(cls):
        if f.name == name:
            if f.default is not MISSING:
                return f.default
            return f.default_factory()  # type: ignore[misc]
    raise KeyError(name)
