"""Train / validation / test split by scene, recorded.

Every view of a scene goes to one part, so a test scene is never trained
on. Scenes are ranked by a seeded hash of their name and the first
round(test n) are test, the next round(val n) validation, the rest
training: exact counts, independent of the order the reader lists them in.
The split is written as JSON (``Split.save``) beside the data and read back
(``Split.load``), so a later run uses the recorded split, not a new one.
"""
from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path

from ...atomic import write_text
from ...errors import InputRangeError
from ...errors import ModelFileError
from ...io.jsontext import loads

PARTS = ("train", "val", "test")


def rank_key(seed: int, scene: str) -> str:
    return hashlib.sha256(f"{seed}\0{scene}".encode()).hexdigest()


@dataclass
class Split:
    scenes: dict                       # scene -> part
    ids: dict                          # id -> scene
    seed: int = 0
    fractions: dict = field(default_factory=dict)

    def part(self, id: str) -> str:
        return self.scenes[self.ids[id]]

    def of(self, part: str) -> list[str]:
        """The ids of one part, sorted."""
        if part not in PARTS:
            raise InputRangeError("split part", part, ", ".join(PARTS))
        return sorted(i for i, s in self.ids.items() if self.scenes[s] == part)

    def as_dict(self) -> dict:
        return {"format": 1, "seed": self.seed, "fractions": self.fractions,
                "scenes": dict(sorted(self.scenes.items())), "ids": dict(sorted(self.ids.items()))}

    def save(self, path) -> None:
        write_text(path, json.dumps(self.as_dict(), indent=1) + "\n")

    @classmethod
    def load(cls, path) -> "Split":
        try:
            d = loads(Path(path).read_text(encoding="utf-8"), path)
            split = cls(d["scenes"], d["ids"], d.get("seed", 0), d.get("fractions", {}))
        except (OSError, ValueError, KeyError, TypeError) as e:
            raise ModelFileError(path, f"not a split file ({e})") from None
        bad = {p for p in split.scenes.values() if p not in PARTS}
        if bad or any(s not in split.scenes for s in split.ids.values()):
            raise ModelFileError(path, "parts outside train/val/test, or ids of unlisted scenes")
        return split


def split_by_scene(ids_to_scenes: dict, *, val: float = 0.1, test: float = 0.1, seed: int = 0) -> Split:
    """{id: scene} -> Split with round(test n) test and round(val n) validation scenes."""
    if not (0 <= val and 0 <= test and val + test < 1):
        raise InputRangeError("val, test fractions", (val, test), "each >= 0, together < 1")
    scenes = sorted(set(ids_to_scenes.values()), key=lambda s: rank_key(seed, s))
    n = len(scenes)
    n_test, n_val = round(test * n), round(val * n)
    parts = {}
    for k, s in enumerate(scenes):
        parts[s] = "test" if k < n_test else "val" if k < n_test + n_val else "train"
    return Split(parts, dict(ids_to_scenes), seed, {"val": val, "test": test})


def split_source(source, **kw) -> Split:
    """The split of an RGB-D reader's frames by its scenes."""
    return split_by_scene({i: source.scene(i) for i in source.ids()}, **kw)
