"""Correction without training: the lens's blur undone with its own PSFs.

``deconvolve`` (depth- and field-aware Wiener deconvolution in the same
patch-wise frame as ``render.simulate``), ``DeconvOptions``, and the noise
it must not amplify (``NoiseModel``, ``estimate_noise``). numpy only: it runs
in Blender without torch. A PSF source (a traced library or the
Omni-Lens-Field's) is handed in by the caller; nothing here imports
``models``.
"""
from .deconvolution import DeconvOptions, DeconvResult, deconvolve
from .noise import NoiseModel, estimate_noise

__all__ = ["DeconvOptions", "DeconvResult", "deconvolve", "NoiseModel", "estimate_noise"]
