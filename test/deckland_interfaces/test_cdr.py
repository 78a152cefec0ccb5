"""rosbags (types registered from the .msg files) and rclpy (the rosidl build) serialise every
deckland_interfaces message to the same CDR, both ways, for seeded random contents.

rclpy's serialiser (Fast CDR) leaves the alignment padding uninitialised (bytes of old heap
contents, e.g. ``69 64 6c 5f`` = "idl_"), rosbags writes zeros there; so the bytes are compared
outside the padding, and every value is compared after a decode by the other side.
"""

import importlib
import math
import random

from deckland.ros import msgtypes
import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message

STORE = msgtypes.typestore()
NAMES = sorted(n.rsplit('/', 1)[1] for n in STORE.types
               if n.startswith('deckland_interfaces/msg/'))
INTS = {'uint8': 8, 'uint16': 16, 'uint32': 32, 'int32': 31}
TEXT = 'abc Step 5 → Step 6 σ > 0.2 m_'


def rclpy_class(type_str):
    pkg, name = type_str.replace('/msg/', '/').split('/')
    return getattr(importlib.import_module(f'{pkg}.msg'), name)


def value(type_str, rng):
    """Plain-Python random contents for an rclpy field type string."""
    if type_str.startswith('sequence<'):
        inner = type_str[len('sequence<'):-1]
        return [value(inner, rng) for _ in range(rng.randrange(4))]
    if type_str.endswith(']'):
        inner, n = type_str[:-1].split('[')
        return [value(inner, rng) for _ in range(int(n))]
    if type_str == 'double':
        return rng.choice([rng.uniform(-1e3, 1e3), rng.uniform(-1, 1), 0.0, math.inf])
    if type_str == 'boolean':
        return rng.random() < 0.5
    if type_str in INTS:
        return rng.randrange(2 ** INTS[type_str])
    if type_str == 'string':
        return ''.join(rng.choice(TEXT) for _ in range(rng.randrange(40)))
    cls = rclpy_class(type_str)
    return {f: value(t, rng) for f, t in cls.get_fields_and_field_types().items()}


def to_rclpy(type_str, data):
    cls = rclpy_class(type_str)
    kwargs = {}
    for f, t in cls.get_fields_and_field_types().items():
        v = data[f]
        if isinstance(v, dict):
            v = to_rclpy(t, v)
        elif t.startswith('sequence<') and '/' in t:
            v = [to_rclpy(t[len('sequence<'):-1], x) for x in v]
        kwargs[f] = v
    return cls(**kwargs)


def to_rosbags(type_str, data):
    full = type_str if '/msg/' in type_str else type_str.replace('/', '/msg/')
    cls = STORE.types[full]
    fields = rclpy_class(type_str).get_fields_and_field_types()
    kwargs = {}
    for f, t in fields.items():
        v = data[f]
        if isinstance(v, dict):
            v = to_rosbags(t, v)
        elif t.startswith('sequence<') and '/' in t:
            v = [to_rosbags(t[len('sequence<'):-1], x) for x in v]
        elif t.endswith(']'):
            v = np.array(v, dtype=np.float64)
        kwargs[f] = v
    return cls(**kwargs)


def same(a, b):
    """rclpy message == rosbags message, field by field."""
    if hasattr(a, 'get_fields_and_field_types'):
        return all(same(getattr(a, f), getattr(b, f)) for f in a.get_fields_and_field_types())
    if isinstance(b, (list, np.ndarray)) or (hasattr(a, '__len__') and not isinstance(a, str)):
        return len(a) == len(b) and all(same(x, y) for x, y in zip(a, b, strict=True))
    return a == b


@pytest.mark.parametrize('name', NAMES)
def test_cdr_identical_both_ways(name):
    full = f'deckland_interfaces/msg/{name}'
    rng = random.Random(f'1:cdr:{name}')
    for _ in range(50):
        data = value(f'deckland_interfaces/{name}', rng)
        r_msg = to_rclpy(f'deckland_interfaces/{name}', data)
        b_msg = to_rosbags(f'deckland_interfaces/{name}', data)
        r_cdr = serialize_message(r_msg)
        b_cdr = bytes(STORE.serialize_cdr(b_msg, full))
        assert len(r_cdr) == len(b_cdr)
        differ = [i for i, (x, y) in enumerate(zip(r_cdr, b_cdr, strict=True)) if x != y]
        assert all(b_cdr[i] == 0 for i in differ)            # padding only
        assert bytes(STORE.serialize_cdr(STORE.deserialize_cdr(r_cdr, full), full)) == b_cdr
        # rclpy bytes -> rosbags object, rosbags bytes -> rclpy object
        assert same(r_msg, STORE.deserialize_cdr(r_cdr, full))
        assert deserialize_message(b_cdr, type(r_msg)) == r_msg


def test_random_contents_reach_every_field_kind():
    """The generator is not vacuous: an ApronState sample holds rivals, inf and UTF-8 text."""
    rng = random.Random('1:cdr:ApronState')
    samples = [value('deckland_interfaces/ApronState', rng) for _ in range(50)]
    assert any(s['rivals'] for s in samples)
    assert any(s['time_since_seen_s'] == math.inf for s in samples)
    status = [value('deckland_interfaces/PlannerStatus', rng) for _ in range(20)]
    assert any('→' in s['reason'] for s in status)
