"""Training configs as data, shared by the three networks: frozen
dataclasses with a JSON round-trip.

Every field decides the result (weights) except those in ``OPERATIONAL``,
which say how the run is carried out (how often to checkpoint or validate);
a checkpoint is resumed only by a config equal to its own in every other
field (``differences``).
"""
from __future__ import annotations

import json

from ...io.jsontext import loads

OPERATIONAL = ("checkpoint_every", "validate_every")


class JSONConfig:
    """JSON round-trip of a frozen config dataclass with an ``as_dict``."""

    def to_json(self) -> str:
        return json.dumps(self.as_dict(), indent=2, sort_keys=True)

    @classmethod
    def from_dict(cls, d: dict):
        return cls(**d)

    @classmethod
    def from_json(cls, text: str):
        return cls.from_dict(loads(text, f"a {cls.__name__} record"))


def differences(a: dict, b: dict) -> dict:
    """{setting: (a's, b's)} where two ``result_settings`` differ."""
    keys = set(a) | set(b)
    return {k: (a.get(k), b.get(k)) for k in sorted(keys) if a.get(k) != b.get(k)}
