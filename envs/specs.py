"""What every scenario family's spec shares: a frozen dataclass with a ``family`` field, as a dict and as JSON."""

from __future__ import annotations

import json
from dataclasses import asdict, fields


class FamilySpec:
    """Mixin for a family's frozen spec dataclass: ``to_dict``, ``to_json`` and a ``from_dict`` that names any key
    the dataclass does not have."""

    def to_dict(self) -> dict:
        return asdict(self)

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), sort_keys=True)

    @classmethod
    def from_dict(cls, d: dict):
        unknown = set(d) - {f.name for f in fields(cls)}
        if unknown:
            family = cls.__dataclass_fields__["family"].default
            raise ValueError(f"unknown {family} scenario fields: {sorted(unknown)}")
        return cls(**d)
