"""``KEY=VALUE,KEY=VALUE`` options (a model error, a measurement noise) into a dataclass, with
the error naming what is wrong. Imports no ROS."""
from __future__ import annotations

import dataclasses
from typing import TypeVar

T = TypeVar('T')


def parse_key_values(cls: type[T], text: str, what: str) -> T:
    """`cls` (a dataclass) from ``"a=1,b=2"`` (any subset of its fields; empty: its defaults);
    each value converted to its field's default's type (int or float). ValueError naming `what`
    and the part that is wrong; the dataclass checks the values."""
    fields = {f.name: f for f in dataclasses.fields(cls)}
    values: dict = {}
    for part in filter(None, (p.strip() for p in text.split(','))):
        key, sep, value = part.partition('=')
        key = key.strip()
        if not sep or key not in fields:
            raise ValueError(f'{what} {part!r}: give KEY=VALUE with KEY one of '
                             f'{", ".join(sorted(fields))}')
        kind = type(fields[key].default)
        try:
            values[key] = int(value) if kind is int else float(value)
        except ValueError:
            raise ValueError(f'{what} {key}: {value.strip()!r} is not a '
                             f'{"whole number" if kind is int else "number"}') from None
    return cls(**values)
