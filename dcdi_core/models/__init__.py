"""Networks of the project (torch), one package each, and the numpy runtime
that serves them.

Torch is imported only inside this package and only when a module that needs
it is imported; ``import dcdi_core.models`` itself, ``registry`` and
``runtime`` never import it, so Blender's own Python (numpy, no torch) can run
an exported Omni-Lens-Field. Layout (docs/design.md):

  olf/       Omni-Lens-Field: spec, architecture, PSF samples, training, export
  dacn/      the correction network: layers, architecture, DA2T data, training,
             export, tiled inference (``correct``), evaluation
  depth/     the small depth network and the public estimators' adapters
  common/    shared once: the training loop, checkpoints and exact resume,
             configs as data, distributed, metrics, LPIPS, split by scene,
             torch state to and from .npz
  runtime/   numpy only, never imports training or data code: reads shipped
             .npz files and runs the OLF; the part the add-on always bundles
  registry   the networks by name and their shipped weights (weights/)
"""
from __future__ import annotations

from ..errors import (CheckpointMismatchError, LensMismatchError, ModelError, ModelFileError,
                     OutsideTrainedRangeError, TorchMissingError)

TORCH_VERSION = "2.13.0"


def require_torch():
    """The ``torch`` module, or :class:`TorchMissingError` saying how to install it."""
    try:
        import torch
    except ImportError as e:
        raise TorchMissingError(
            f"this needs PyTorch, which is not installed here ({e}); install the CPU build with "
            f"`pip install torch=={TORCH_VERSION}` (Blender's own Python runs only "
            "dcdi_core.models.runtime, which needs numpy alone)") from None
    return torch


__all__ = ["require_torch", "ModelError", "TorchMissingError", "ModelFileError", "LensMismatchError",
           "OutsideTrainedRangeError", "CheckpointMismatchError", "TORCH_VERSION"]
