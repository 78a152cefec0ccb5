"""deckland_common.validate: the one set of field checks."""

import math

import pytest

from deckland_common import validate as v


def test_checks_pass_good_values():
    v.finite('a', 1.5)
    v.positive('a', 1)
    v.non_negative('a', 0.0)
    v.in_range('a', 0.5, 0.0, 1.0)
    v.integer_at_least('n', 3, 1)
    v.one_of('m', 'x', ('x', 'y'))
    v.finite_tuple('t', [1.0, 2.0, 3.0], 3)


@pytest.mark.parametrize('fn, args, text', [
    (v.finite, ('p.a', math.nan), 'p.a must be a finite number, got nan'),
    (v.finite, ('p.a', True), 'p.a must be a finite number, got True'),
    (v.positive, ('p.a', 0.0), 'p.a must be a finite number > 0, got 0.0'),
    (v.non_negative, ('p.a', -1), 'p.a must be a finite number >= 0, got -1'),
    (v.in_range, ('p.a', 2.0, 0.0, 1.0), 'p.a must be in [0.0, 1.0], got 2.0'),
    (v.integer_at_least, ('p.n', 1.0, 1), 'p.n must be an integer >= 1, got 1.0'),
    (v.one_of, ('p.m', 'z', ('x', 'y')), "p.m must be one of ['x', 'y'], got 'z'"),
    (v.finite_tuple, ('p.t', (1.0, math.inf, 0.0), 3), 'p.t must be 3 finite numbers'),
])
def test_checks_name_the_field_rule_and_value(fn, args, text):
    with pytest.raises(ValueError) as exc:
        fn(*args)
    assert text in str(exc.value)
