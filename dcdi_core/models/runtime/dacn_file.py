"""The shipped DACN file (numpy only): its format and its checked reader.
``models.dacn.export`` writes it; ``models.dacn.correct`` runs it."""
from __future__ import annotations

from ...io.model_npz import read_model_npz

FORMAT, FORMAT_VERSION = "dcdi-dacn", 1


def read_dacn_file(path) -> tuple[dict, dict]:
    """(metadata, arrays) of an exported DACN, checked."""
    return read_model_npz(path, FORMAT, FORMAT_VERSION, "DACN")
