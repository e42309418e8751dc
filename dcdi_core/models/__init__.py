"""Networks of the project (torch), and the numpy runtime that serves them.

Torch is imported only inside this package and only when a module that needs
it is imported (``arch``, ``layers``, ``data.psf_samples``, ``train``, ``export``);
``import dcdi_core.models`` itself, ``metrics`` (numpy part) and ``runtime``
never import it, so Blender's own Python (numpy, no torch) can run an exported
Omni-Lens-Field. Layout (DESIGN.md):

  arch/      nn.Modules only (``arch.olf``, ``arch.dacn``) and their torch-free
             specs (``arch.spec``, ``arch.dacn_spec``)
  layers/    building blocks: deformable conv, cross-attention, Swin and EDSR blocks
  data/      training samples (``data.psf_samples``: ray-traced PSFs for the OLF;
             ``data.rgbd``, ``data.da2t``, ``data.split``, ``data.depth``: DACN's)
  train/     configs as data, a plain loop, atomic checkpoints and exact resume
  export     torch -> .npz arrays + JSON metadata (no pickle)
  runtime/   numpy only: loads an exported .npz and runs it
  metrics    PSNR, SSIM (numpy; torch versions for training)
"""
from __future__ import annotations

from .errors import (CheckpointMismatchError, LensMismatchError, ModelError, ModelFileError,
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
