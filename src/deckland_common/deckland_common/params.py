"""Declarative parameter specifications with start-up validation (pure, no rclpy).

Every deckland node lists its parameters as :class:`ParamSpec` rows. The node adapter declares
them with their descriptions and calls :func:`validate`; a bad value raises
:class:`ParameterError` naming the parameter, the value and the rule, and the node exits
instead of running on a silent default. Package READMEs render the same rows as tables.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass
import math
from typing import Any


class ParameterError(ValueError):
    """A parameter value broke its rule; the message is meant for the operator."""


@dataclass(frozen=True)
class ParamSpec:
    """One node parameter: name, default (its type is the parameter's type), meaning, rule."""

    name: str
    default: Any
    description: str
    check: Callable[[Any], bool] | None = None
    rule: str = ''

    def validate(self, value: Any) -> Any:
        expected = type(self.default)
        if expected is float and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        if not isinstance(value, expected) or (expected is int and isinstance(value, bool)):
            raise ParameterError(
                f'parameter {self.name!r}: expected {expected.__name__}, got {value!r}')
        if isinstance(value, float) and not math.isfinite(value):
            raise ParameterError(f'parameter {self.name!r}: must be finite, got {value!r}')
        if isinstance(value, list) and any(
                isinstance(v, float) and not math.isfinite(v) for v in value):
            raise ParameterError(f'parameter {self.name!r}: must be finite, got {value!r}')
        if self.check is not None and not self.check(value):
            raise ParameterError(f'parameter {self.name!r} = {value!r} violates: {self.rule}')
        return value


def positive(name: str, default: float, description: str) -> ParamSpec:
    return ParamSpec(name, default, description, lambda v: v > 0, 'must be > 0')


def non_negative(name: str, default: float, description: str) -> ParamSpec:
    return ParamSpec(name, default, description, lambda v: v >= 0, 'must be >= 0')


def in_range(name: str, default: float, lo: float, hi: float, description: str) -> ParamSpec:
    return ParamSpec(name, default, description, lambda v: lo <= v <= hi,
                     f'must be in [{lo}, {hi}]')


def one_of(name: str, default: str, choices: Iterable[str], description: str) -> ParamSpec:
    allowed = tuple(choices)
    return ParamSpec(name, default, description, lambda v: v in allowed,
                     f'must be one of {list(allowed)}')


def validate(values: dict[str, Any], specs: Iterable[ParamSpec]) -> dict[str, Any]:
    """Check every value against its spec; return the (coerced) values or raise."""
    out: dict[str, Any] = {}
    for spec in specs:
        out[spec.name] = spec.validate(values.get(spec.name, spec.default))
    return out


def markdown_table(specs: Iterable[ParamSpec]) -> str:
    """The README table for a list of specs."""
    rows = ['| name | type | default | meaning |', '| --- | --- | --- | --- |']
    for s in specs:
        rule = f' ({s.rule})' if s.rule else ''
        rows.append(f'| `{s.name}` | {type(s.default).__name__} | `{s.default!r}` | '
                    f'{s.description}{rule} |')
    return '\n'.join(rows)
