"""Deterministic, fully populated instances of every controlled_islanding_msgs message, and plain-data views of them."""

from __future__ import annotations

import dataclasses
import importlib
import random
from pathlib import Path

import numpy as np

MSG_DIR = Path(__file__).resolve().parents[1] / 'msg_schemas' / 'msg'
MESSAGE_NAMES = sorted(p.stem for p in MSG_DIR.glob('*.msg'))

_INT_RANGES = {'uint8': 255, 'uint16': 65535, 'uint32': 2**32 - 1, 'uint64': 2**40,
               'int8': 127, 'int16': 32767, 'int32': 2**31 - 1, 'int64': 2**40, 'octet': 255}


def msg_class(type_name: str) -> type:
    """Return the rclpy class for 'pkg/Name' or a bare name of our package."""
    pkg, _, name = type_name.rpartition('/')
    return getattr(importlib.import_module(f'{pkg or "controlled_islanding_msgs"}.msg'), name)


def _value(field_type: str, rng: random.Random):
    if field_type.startswith('sequence<'):
        inner = field_type[len('sequence<'):-1]
        return [_value(inner, rng) for _ in range(rng.randint(1, 4))]
    if field_type == 'boolean':
        return rng.random() < 0.5
    if field_type in ('double', 'float'):
        return rng.choice([0.0, -1.5, 2.25, 1e-9, 123456.789]) if field_type == 'double' else 0.5
    if field_type in _INT_RANGES:
        return rng.randint(0, _INT_RANGES[field_type])
    if field_type == 'string':
        return rng.choice(['', 'bus30', 'Line_21', 'décision-1', '16-17#2'])
    return sample(msg_class(field_type), rng)


def sample(cls: type, rng: random.Random | int = 0):
    """Return an instance of an rclpy message class with every field set from rng."""
    rng = rng if isinstance(rng, random.Random) else random.Random(rng)
    msg = cls()
    for field, field_type in cls.get_fields_and_field_types().items():
        value = _value(field_type, rng)
        if field_type == 'builtin_interfaces/Time':
            value.nanosec %= 1_000_000_000
        setattr(msg, field, value)
    return msg


def plain(obj):
    """Return nested builtin data for an rclpy message or a rosbags message, for comparing the two."""
    if hasattr(obj, 'get_fields_and_field_types'):
        return {f: plain(getattr(obj, f)) for f in obj.get_fields_and_field_types()}
    if dataclasses.is_dataclass(obj):
        return {f.name: plain(getattr(obj, f.name)) for f in dataclasses.fields(obj)
                if f.name != '__msgtype__' and not f.name.isupper()}
    if isinstance(obj, np.ndarray):
        return [plain(v) for v in obj.tolist()]
    if isinstance(obj, (list, tuple)) or type(obj).__name__ == 'array':
        return [plain(v) for v in obj]
    if isinstance(obj, (np.floating, np.integer, np.bool_)):
        return obj.item()
    return obj
