"""A torch module's state to and from the shipped .npz format
(``io.model_npz``), and the pixel pitch a run was trained at."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ...errors import InputRangeError
from ...errors import ModelFileError
from ...io.model_npz import DTYPES


def state_arrays(module, dtype: str = "float16") -> dict:
    """{name: array} of a torch module's state, floating arrays in ``dtype``."""
    if dtype not in DTYPES:
        raise InputRangeError("dtype", dtype, " or ".join(DTYPES))
    out = {}
    for k, v in module.state_dict().items():
        a = v.detach().cpu().numpy()
        out[k] = a.astype(dtype) if a.dtype.kind == "f" else a
    return out


def load_state(module, arrays: dict, path) -> None:
    """Load float32 copies of ``arrays`` into a torch module (eval mode)."""
    import torch
    state = {k: torch.from_numpy(np.asarray(a, np.float32) if a.dtype.kind == "f" else np.asarray(a))
             for k, a in arrays.items()}
    try:
        module.load_state_dict(state)
    except RuntimeError as e:
        raise ModelFileError(path, f"weights do not fit the recorded network ({str(e)[:200]})") from None
    module.eval()


def trained_pixel_pitch_mm(data_root) -> float | None:
    """The image pixel pitch (mm) of a run's DA2T pairs (their first record), or None."""
    from ..dacn.data import finished_pairs
    recs = finished_pairs(data_root) if data_root and Path(data_root).exists() else {}
    pitches = {round(r["pixel_pitch_mm"], 9) for r in recs.values() if "pixel_pitch_mm" in r}
    return next(iter(pitches)) if len(pitches) == 1 else None
