"""What ships with the engine, in one place: for each lens its PSF basis,
its ray map, the Omni-Lens-Field, its correction network (DACN), its depth network and
the learned refinement of its depth from blur, and what each is recorded to
beat (:func:`for_lens`); the networks by name (the ``dcdi`` command's
nouns). Read by the PSF sources, the correction rule, the depth job, the
command and the add-on; standard library only (no file is opened here)."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

ENGINE_DIR = Path(__file__).resolve().parent
# the lens folders that ship beside the engine (the repository's, the add-on's bundle): inputs like the rest
SHIPPED_LENS_DIRS = (ENGINE_DIR.parent / "lenses", ENGINE_DIR / "lenses")
WEIGHTS_DIR = Path(__file__).resolve().parent / "models" / "weights"
BASIS_DIR = Path(__file__).resolve().parent / "psf" / "data" / "basis"
RAYMAP_DIR = Path(__file__).resolve().parent / "psf" / "data" / "raymap"
# the Omni-Lens-Field in ray space (``psf.rayfield``): the lenses no ray map ships for
OLF_RAYS_FILE = Path(__file__).resolve().parent / "psf" / "data" / "olf" / "olf-rays.npz"


@dataclass(frozen=True)
class Network:
    name: str                 # the CLI's noun: ``dcdi <name> ...``
    summary: str
    package: str              # folder under dcdi_core/models/: architecture, data, training, export
    weights_prefix: str       # shipped files: weights/<prefix><key>.npz
    # lens ids whose shipped network scored better than the deconvolution
    # (dcdi_core.correct) on held-out captures: the DACN study
    # (lab/dacn_study.py) decides it; `pipeline.choose_correction`
    # runs a network in 'auto' only for these lenses
    beats_deconvolution: tuple[str, ...] = ()
    # lens ids whose shipped depth network beat a constant depth (the training
    # set's median) by at least 30 % in AbsRel on held-out scenes (`python -m lab report
    # depth`); `dcdi dof` estimates depth with no other network unasked
    beats_constant_depth: tuple[str, ...] = ()

    def shipped_files(self) -> list[Path]:
        return sorted(WEIGHTS_DIR.glob(f"{self.weights_prefix}*.npz")) if WEIGHTS_DIR.is_dir() else []

    def shipped_keys(self) -> list[str]:
        """The part of each shipped file's name after the prefix (a lens id, or 'radial')."""
        return [p.stem[len(self.weights_prefix):] for p in self.shipped_files()]

    def shipped_file(self, key: str) -> Path | None:
        return weights_file(self.weights_prefix, key)


def is_shipped_file(path) -> bool:
    """Whether ``path`` is a file the engine ships (its code, ray maps, bases,
    weights, quality tables, or a lens of the folders beside it): an input
    of every job, never a job's output."""
    p = Path(path)
    if not p.is_file():
        return False
    real = p.resolve()
    return any(real.is_relative_to(d.resolve()) for d in (ENGINE_DIR, *SHIPPED_LENS_DIRS) if d.is_dir())


def weights_file(prefix: str, key: str) -> Path | None:
    """The shipped weights/<prefix><key>.npz (``key``: a lens id or 'radial'),
    or None; a ``key`` that is not a name (``names.NAME_RULE``) is refused
    (InputRangeError): it becomes part of the file's name."""
    from .errors import InputRangeError
    from .names import check_name
    p = WEIGHTS_DIR / f"{prefix}{check_name(key, 'weights key', error=InputRangeError)}.npz"
    return p if p.is_file() else None


NETWORKS = {
    "olf": Network("olf", "Omni-Lens-Field: an MLP of a lens's PSFs over field, depth and focus", "olf",
                   "olf-"),                                  # runtime/olf.py runs it in numpy
    # the shipped refining DACNs, on held-out captures at 12.2 um with noise (the DACN study,
    # docs/correction.md): MOS-S1 +1.97 dB over the deconvolution, MOS-S2 +2.78 dB (9,600 iterations, seed 0)
    "dacn": Network("dacn", "depth-aware correction network (DA2T-trained), per lens", "dacn",
                    "dacn-", beats_deconvolution=("mos-s1", "mos-s2")),
    "depth": Network("depth", "small metric-depth network on a lens's captures", "depth",
                     "depth-"),
}

# the learned refinement of the depth from the capture's own blur (dcdi_core.dfd,
# `dcdi depth estimate`): weights/dfd-refine-<lens>.npz, run in numpy
# (models.runtime.dfd_refine). beats_constant_depth: lens ids whose refined
# depth from blur beat the best constant depth (each frame's own median) by at
# least 30 % in AbsRel on held-out factory captures at the pixel pitch the
# refinement learned, with noise (`python -m lab dfd-refine-study`,
# docs/depth.md): `dcdi dof` without a depth map estimates depth this way for
# these lenses at that pitch unasked. MOS-S1: 0.241 against 0.364 (0.66x);
# MOS-S2: 0.219 against 0.364 (0.60x).
REFINEMENT = Network("dfd-refine", "learned refinement of the depth from blur", "depth", "dfd-refine-",
                     beats_constant_depth=("mos-s1", "mos-s2"))


def basis_file(lens_id: str, focus_stack: bool = False) -> Path | None:
    """The shipped PSF basis of ``lens_id`` (psf/data/basis/<lens>.npz; with
    ``focus_stack``, its focus stack psf/data/basis/focus/<lens>.npz), or None;
    ``lens_id`` must be a name (``names.NAME_RULE``): it becomes the file's name."""
    from .errors import InputRangeError
    from .names import check_name
    name = f"{check_name(lens_id, 'lens id', error=InputRangeError)}.npz"
    p = (BASIS_DIR / "focus" if focus_stack else BASIS_DIR) / name
    return p if p.is_file() else None


def olf_rays_file() -> Path | None:
    """The shipped Omni-Lens-Field in ray space (psf/data/olf/olf-rays.npz), or None."""
    return OLF_RAYS_FILE if OLF_RAYS_FILE.is_file() else None


def raymap_file(lens_id: str) -> Path | None:
    """The shipped ray map of ``lens_id`` (psf/data/raymap/<lens>.npz: its
    rays at any focus, stop and pitch), or None; ``lens_id`` must be a name."""
    from .errors import InputRangeError
    from .names import check_name
    p = RAYMAP_DIR / f"{check_name(lens_id, 'lens id', error=InputRangeError)}.npz"
    return p if p.is_file() else None


@dataclass(frozen=True)
class LensShipped:
    """What ships for one lens (files, None where none ships) and what each
    is recorded to beat. ``olf``: the shipped Omni-Lens-Field file; whether
    it covers this lens and a request is ``psf.sources``' question (it reads
    the file)."""

    lens_id: str
    basis: Path | None
    raymap: Path | None
    olf: Path | None
    dacn: Path | None
    depth_network: Path | None
    refinement: Path | None
    dacn_beats_deconvolution: bool
    depth_network_beats_constant: bool
    blur_depth_beats_constant: bool


def for_lens(lens_id: str) -> LensShipped:
    """What ships for ``lens_id`` (a name; checked before it becomes a file's name)."""
    olf = NETWORKS["olf"].shipped_files()
    return LensShipped(lens_id, basis_file(lens_id), raymap_file(lens_id), olf[0] if olf else None,
                       NETWORKS["dacn"].shipped_file(lens_id), NETWORKS["depth"].shipped_file(lens_id),
                       REFINEMENT.shipped_file(lens_id),
                       lens_id in NETWORKS["dacn"].beats_deconvolution,
                       lens_id in NETWORKS["depth"].beats_constant_depth,
                       lens_id in REFINEMENT.beats_constant_depth)


def network(name: str) -> Network:
    try:
        return NETWORKS[name]
    except KeyError:
        from .errors import InputRangeError
        raise InputRangeError("network", name, ", ".join(NETWORKS)) from None
