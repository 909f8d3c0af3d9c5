"""The machinery of jaxcal's typed records (`jaxcal.records` re-exports it): the `Record` base,
a read-only mapping of its `result.json` block, the field markers that shape that block
(`optional`, `named`, `keyed`) and the conversion to and from plain JSON values (`plain`,
`from_plain`). It imports nothing from jaxcal."""

import types
import typing
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field, fields, is_dataclass

import numpy as np

#: Field metadata: the key is left out of the JSON block when the value is None.
OPTIONAL = "optional"
#: Field metadata: a tuple of `Named` rows written as a `{name: value}` object.
NAMED = "named"
#: Field metadata: a tuple of rows written as `{row.<key>: the row less its key}`.
KEYED = "keyed"


def optional(default=None):
    """A field whose key is written only when its value is not None."""
    return field(default=default, metadata={OPTIONAL: True})


def named(*, is_optional: bool = False):
    """A field of `Named` rows, written as one `{name: value}` object (None when optional)."""
    return field(default=None if is_optional else (), metadata={NAMED: True, OPTIONAL: is_optional})


def keyed(key: str, *, is_optional: bool = False):
    """A field of rows written as one object keyed by each row's field `key` (per joint, per camera)."""
    return field(default=None if is_optional else (), metadata={KEYED: key, OPTIONAL: is_optional})


def row_of(rows, key: str, value: str):
    """The row of `rows` whose field `key` is `value` (KeyError when none is)."""
    for r in rows:
        if getattr(r, key) == value:
            return r
    raise KeyError(value)


def plain(x):
    """A record, row or value as plain JSON types (dicts, lists, floats, ints, str, bool, None)."""
    if isinstance(x, Record):
        return {k: x[k] for k in x}
    if isinstance(x, (tuple, list)):
        return [plain(e) for e in x]
    if isinstance(x, dict):
        return {k: plain(v) for k, v in x.items()}
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, np.generic):
        return x.item()
    return x


def _decode(tp, value):
    """`value` (plain JSON) as type `tp`: records, tuples of them, arrays, optionals."""
    if value is None:
        return float("nan") if tp is float else None  # a number JSON cannot hold (`finite_json`)
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        inner = [a for a in args if a is not type(None)]
        return _decode(inner[0], value) if len(inner) == 1 else value
    if origin is tuple:
        return tuple(_decode(args[0], v) for v in value)
    if tp is np.ndarray:
        return np.asarray(_nan_for_null(value), np.float64)
    if isinstance(tp, type) and is_dataclass(tp):
        return from_plain(tp, value)
    return value


def _nan_for_null(value):
    """A JSON array (nested lists) with its nulls as NaN: an array's numbers JSON cannot hold."""
    if isinstance(value, list):
        return [_nan_for_null(v) for v in value]
    return float("nan") if value is None else value


def _row_type(tp):
    """The row type of `tuple[Row, ...]` or `tuple[Row, ...] | None`."""
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        tp = next(a for a in typing.get_args(tp) if a is not type(None))
    return typing.get_args(tp)[0]


def from_plain(cls, data: Mapping):
    """The record of type `cls` whose JSON block (`plain`) is `data`: the inverse of `plain`."""
    hints = typing.get_type_hints(cls)
    kwargs = {}
    for f in fields(cls):
        if f.name not in data:
            continue
        v, tp = data[f.name], hints[f.name]
        if f.metadata.get(NAMED) and v is not None:
            v = tuple(Named(str(k), x) for k, x in v.items())
        elif f.metadata.get(KEYED) and v is not None:
            row = _row_type(tp)
            v = tuple(from_plain(row, {f.metadata[KEYED]: k, **x}) for k, x in v.items())
        else:
            v = _decode(tp, v)
        kwargs[f.name] = v
    return cls(**kwargs)


class Record(Mapping):
    """A frozen result record that also reads as its JSON block (see the module docstring)."""

    def _keys(self) -> list[str]:
        return [
            f.name
            for f in fields(self)  # type: ignore[arg-type]
            if not (f.metadata.get(OPTIONAL) and getattr(self, f.name) is None)
        ]

    def __getitem__(self, key: str):
        for f in fields(self):  # type: ignore[arg-type]
            if f.name == key:
                v = getattr(self, key)
                if f.metadata.get(NAMED) and v is not None:
                    return {row.name: plain(row.value) for row in v}
                if f.metadata.get(KEYED) and v is not None:
                    k = f.metadata[KEYED]
                    return {getattr(row, k): {n: row[n] for n in row if n != k} for row in v}
                if f.metadata.get(OPTIONAL) and v is None:
                    break
                return plain(v)
        raise KeyError(key)

    def __iter__(self) -> Iterator[str]:
        return iter(self._keys())

    def __len__(self) -> int:
        return len(self._keys())

    __hash__ = None  # type: ignore[assignment]


@dataclass(frozen=True, eq=False)
class Named(Record):
    """One entry of a `{name: value}` block: a joint's count, a parameter's std."""

    name: str
    #: The number under that name (an int for counts).
    value: float
