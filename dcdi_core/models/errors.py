"""Errors of ``dcdi_core.models`` (all below the engine's root, ``DcdiError``,
through its ``ModelError``).

Each names what the user can act on: the file, the field or setting, what was
found and what is allowed.
"""
from __future__ import annotations

from ..errors import InputRangeError, ModelError  # noqa: F401  (ModelError: the base of every error here)


class TorchMissingError(ModelError, ImportError):
    """PyTorch is needed (training, export) but not installed."""


class ModelFileError(ModelError, ValueError):
    """An exported model or checkpoint file that cannot be used (names the file and field)."""

    def __init__(self, path, message, *, field=None, allowed=None):
        self.path = str(path)
        self.field = field
        self.allowed = allowed
        text = self.path + (f", field '{field}'" if field is not None else "") + f": {message}"
        if allowed is not None:
            text += f"; allowed: {allowed}"
        super().__init__(text)


class LensMismatchError(ModelError, ValueError):
    """A lens whose prescription differs from the one a model learned (or a lens it never learned)."""


class CheckpointMismatchError(ModelError, ValueError):
    """A checkpoint written with other settings than the run that would resume it."""

    def __init__(self, path, differences: dict):
        self.path = str(path)
        self.differences = dict(differences)
        lines = "; ".join(f"{k}: checkpoint {a!r}, now {b!r}" for k, (a, b) in sorted(self.differences.items()))
        super().__init__(f"{self.path}: written with other settings, not resumed ({lines}); "
                         "run with the checkpoint's settings, or use another run folder to start afresh")


class OutsideTrainedRangeError(InputRangeError, ModelError):
    """A request outside the ranges a model was trained on (names the file, the input and the range)."""

    def __init__(self, path, name, value, allowed):
        super().__init__(name, value, allowed)
        self.path = str(path)
        self.args = (f"{self.path}: {self.args[0]} (the range this model was trained on; "
                     "trace the PSF instead)",)
