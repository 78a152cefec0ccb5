"""Small validation helpers for the parameter dataclasses (pure)."""

from __future__ import annotations

import math


def finite(owner: str, name: str, value: float) -> None:
    """Raise ValueError unless ``value`` is a finite real number."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(
            value):
        raise ValueError(f'{owner}.{name} must be a finite number, got {value!r}')


def positive(owner: str, name: str, value: float) -> None:
    finite(owner, name, value)
    if value <= 0:
        raise ValueError(f'{owner}.{name} must be > 0, got {value!r}')


def non_negative(owner: str, name: str, value: float) -> None:
    finite(owner, name, value)
    if value < 0:
        raise ValueError(f'{owner}.{name} must be >= 0, got {value!r}')


def in_range(owner: str, name: str, value: float, lo: float, hi: float) -> None:
    finite(owner, name, value)
    if not lo <= value <= hi:
        raise ValueError(f'{owner}.{name} must be in [{lo}, {hi}], got {value!r}')


def integer_at_least(owner: str, name: str, value: int, lo: int) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value < lo:
        raise ValueError(f'{owner}.{name} must be an integer >= {lo}, got {value!r}')
