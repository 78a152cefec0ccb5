"""Validation helpers for parameter dataclasses and configuration (pure, no rclpy).

The one set of checks every package uses in ``__post_init__`` and in its loaders: each raises
``ValueError`` with the field's name, the rule it broke and the value, e.g.
``faults[0].land_speed_mps must be in (0, 5] m/s, got 9.0``.
"""

from __future__ import annotations

import math
from typing import Any


def is_number(value: Any) -> bool:
    """A real number (int or float), not a bool."""
    return isinstance(value, int | float) and not isinstance(value, bool)


def is_finite_number(value: Any) -> bool:
    """A real number (not a bool) that is finite."""
    return is_number(value) and math.isfinite(value)


def require(cond: bool, name: str, rule: str, value: Any) -> None:
    """Raise ``ValueError('<name> <rule>, got <value>')`` unless ``cond``."""
    if not cond:
        raise ValueError(f'{name} {rule}, got {value!r}')


def finite(name: str, value: Any) -> None:
    require(is_finite_number(value), name, 'must be a finite number', value)


def positive(name: str, value: Any) -> None:
    require(is_finite_number(value) and value > 0, name, 'must be a finite number > 0', value)


def non_negative(name: str, value: Any) -> None:
    require(is_finite_number(value) and value >= 0, name, 'must be a finite number >= 0',
            value)


def in_range(name: str, value: Any, lo: float, hi: float) -> None:
    require(is_finite_number(value) and lo <= value <= hi, name, f'must be in [{lo}, {hi}]',
            value)


def integer_at_least(name: str, value: Any, lo: int) -> None:
    require(isinstance(value, int) and not isinstance(value, bool) and value >= lo, name,
            f'must be an integer >= {lo}', value)


def one_of(name: str, value: Any, choices: tuple[Any, ...]) -> None:
    require(value in choices, name, f'must be one of {list(choices)}', value)


def finite_tuple(name: str, value: Any, length: int) -> None:
    """A tuple (or list) of ``length`` finite numbers."""
    require(isinstance(value, tuple | list) and len(value) == length
            and all(is_finite_number(v) for v in value), name,
            f'must be {length} finite numbers', value)
