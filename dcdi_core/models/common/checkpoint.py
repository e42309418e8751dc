"""Checkpoints and the EMA of the weights, for the shared training loop
(``loop``): atomic checkpoints, their refusal when written with other
settings or on other data, the exact restore of a run's state, and one
optimiser step followed by the EMA."""
from __future__ import annotations

import copy
import json
from pathlib import Path

from .. import require_torch
from ...errors import CheckpointMismatchError, ModelFileError
from .config import differences
from ...io.jsontext import loads

torch = require_torch()

CHECKPOINT_FORMAT = 1


def save_checkpoint(path: Path, state: dict) -> None:
    from ...atomic import atomic_path

    with atomic_path(path) as tmp:
        torch.save(state, tmp)


def load_checkpoint(path: Path) -> dict:
    try:
        ck = torch.load(path, weights_only=True, map_location="cpu")
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
    diff = differences(loads(ck["settings"], f"{path}: settings"), settings)
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


def update(opt, loss, lr: float, model, ema, decay: float) -> None:
    """One optimiser step on ``loss`` at learning rate ``lr``, then the EMA."""
    for g in opt.param_groups:
        g["lr"] = lr
    opt.zero_grad(set_to_none=True)
    loss.backward()
    opt.step()
    ema_update(ema, model, decay)


def training_state(*, step: int, settings: dict, config_json: str, data_key: str, model, ema, opt, rng,
                   history: list, **extra) -> dict:
    """What a checkpoint holds: weights, EMA, optimiser, iteration, the batch
    generator's and torch's RNG states, the history and ``extra``; tensors on
    the CPU (a GPU run's checkpoint resumes on the CPU and back)."""
    from ... import __version__
    from .distributed import to_cpu

    return {"format": CHECKPOINT_FORMAT, "dcdi_version": __version__, "step": step,
            "settings": json.dumps(settings, sort_keys=True), "config": config_json, "data_key": data_key,
            "model": to_cpu(model.state_dict()), "ema": to_cpu(ema.state_dict()), "optim": to_cpu(opt.state_dict()),
            "torch_rng": torch.get_rng_state(), "numpy_rng": json.dumps(rng.bit_generator.state),
            "history": json.dumps(history), **extra}


def restore(ck: dict | None, model, ema, opt, rng, *, say=None, path=None, iters=None) -> tuple[int, list]:
    """Load a checkpoint's state into the run's objects: (step, history);
    (0, []) without one. ``say`` is told where the run resumes."""
    if ck is None:
        return 0, []
    if say is not None:
        say(f"resumed {path} at iteration {int(ck['step'])} of {iters}")
    model.load_state_dict(ck["model"])
    ema.load_state_dict(ck["ema"])
    opt.load_state_dict(ck["optim"])
    torch.set_rng_state(ck["torch_rng"])
    rng.bit_generator.state = json.loads(ck["numpy_rng"])
    return int(ck["step"]), json.loads(ck["history"])


def open_run(run_dir, config):
    """(run folder, checkpoint path, result settings, checkpoint or None) of
    a run of ``config`` (torch threads set as it says; a checkpoint written
    with other settings refused)."""
    torch.set_num_threads(config.threads)
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    ckpt_path = run_dir / "checkpoint.pt"
    settings = config.result_settings()
    return run_dir, ckpt_path, settings, resumable(ckpt_path, settings)


def check_data(ck: dict | None, ckpt_path, key: str, what: str) -> None:
    """Refuse to resume a checkpoint trained on other data (``what`` names it)."""
    if ck is not None and ck["data_key"] != key:
        raise CheckpointMismatchError(ckpt_path, {what: (ck["data_key"][:12], key[:12])})

