"""What every trainer here shares: atomic checkpoints, their refusal when
written with other settings, and the EMA of the weights."""
from __future__ import annotations

import copy
import json
from pathlib import Path

from .. import require_torch
from ..errors import CheckpointMismatchError, ModelFileError
from .config import differences

torch = require_torch()

CHECKPOINT_FORMAT = 1


def save_checkpoint(path: Path, state: dict) -> None:
    from ...atomic import atomic_path

    with atomic_path(path) as tmp:
        torch.save(state, tmp)


def load_checkpoint(path: Path) -> dict:
    try:
        ck = torch.load(path, weights_only=True)
    except Exception as e:  # noqa: BLE001 - any failure: say which file
        raise ModelFileError(path, f"not a readable checkpoint ({e}); delete it to start afresh") from None
    if ck.get("format") != CHECKPOINT_FORMAT:
        raise ModelFileError(path, f"checkpoint format {ck.get('format')!r}", field="format",
                             allowed=str(CHECKPOINT_FORMAT))
    return ck


def resumable(path: Path, settings: dict) -> dict | None:
    """The checkpoint at ``path`` if there is one, refused (naming the
    differences) when its settings are not ``settings``."""
    if not Path(path).exists():
        return None
    ck = load_checkpoint(path)
    diff = differences(json.loads(ck["settings"]), settings)
    if diff:
        raise CheckpointMismatchError(path, diff)
    return ck


def make_ema(model):
    """A frozen copy of ``model`` for the exponential moving average."""
    ema = copy.deepcopy(model)
    for p in ema.parameters():
        p.requires_grad_(False)
    return ema


def ema_update(ema, model, decay: float) -> None:
    with torch.no_grad():
        for pe, p in zip(ema.parameters(), model.parameters()):
            pe.mul_(decay).add_(p, alpha=1.0 - decay)
