"""The typed rows the stages hand each other and the verdict reports (`jaxcal.stages`).

Beside `jaxcal.records` (the result's blocks) and built the same way: frozen
records whose field names are their `result.json` keys. Like it, this module
imports nothing from jaxcal but `jaxcal.records`.
"""

from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from typing import Generic, TypeVar

from .records import Record


@dataclass(frozen=True, eq=False)
class Check(Record):
    """One plausibility check of the verdict (`result.json`'s `checks`): its name
    (`joint_2.origin.mm`, `board_scale`, `ee_sigma_mm`, ...), the value measured,
    the limit it is held to, and whether it passed (a finite value within the limit)."""

    check: str
    value: float
    limit: float
    passed: bool


V = TypeVar("V")


@dataclass(frozen=True, eq=False)
class ByTarget(Mapping, Generic[V]):
    """One frame's values per target found in it (the detector's corners, or the PnP poses),
    in the order of the targets: it reads as the read-only `{target: value}` mapping the
    per-frame readers take (`name in frame`, `frame[name]`, `frame.get(name)`, `bool(frame)`)."""

    #: The targets found in the frame, and each one's value.
    names: tuple[str, ...] = ()
    entries: tuple[V, ...] = ()

    @classmethod
    def of(cls, values: Mapping) -> "ByTarget[V]":
        """The frame of a `{target: value}` mapping (its order kept)."""
        return cls(tuple(values), tuple(values.values()))

    def __getitem__(self, name: str) -> V:
        for n, v in zip(self.names, self.entries):
            if n == name:
                return v
        raise KeyError(name)

    def get(self, name: str, default=None):
        for n, v in zip(self.names, self.entries):
            if n == name:
                return v
        return default

    def __contains__(self, name) -> bool:
        return name in self.names

    def __iter__(self) -> Iterator[str]:
        return iter(self.names)

    def __len__(self) -> int:
        return len(self.names)

    def values(self):
        return self.entries

    def items(self):
        return tuple(zip(self.names, self.entries))
