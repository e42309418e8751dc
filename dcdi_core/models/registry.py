"""The project's networks by name: where each one's package and shipped
weights are, and where a shipped one is recorded better than the
alternative. Read by the ``dcdi`` command (shipped files per lens) and the
correction rule; standard library only."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"


@dataclass(frozen=True)
class Network:
    name: str                 # the CLI's noun: ``dcdi <name> ...``
    summary: str
    package: str              # folder under dcdi_core/models/: architecture, data, training, export
    weights_prefix: str       # shipped files: weights/<prefix><key>.npz
    # lens ids whose shipped network scored better than the deconvolution
    # (dcdi_core.correct) on held-out captures: the DACN study
    # (experiments/dacn_study.py) decides it; `pipeline.choose_correction`
    # runs a network in 'auto' only for these lenses
    beats_deconvolution: tuple[str, ...] = ()
    # lens ids whose shipped depth network beat a constant depth (the training
    # set's median) by at least 30 % in AbsRel on held-out scenes (`dcdi report
    # depth`); `dcdi dof` estimates depth with no other network unasked
    beats_constant_depth: tuple[str, ...] = ()

    def shipped_files(self) -> list[Path]:
        return sorted(WEIGHTS_DIR.glob(f"{self.weights_prefix}*.npz")) if WEIGHTS_DIR.is_dir() else []

    def shipped_keys(self) -> list[str]:
        """The part of each shipped file's name after the prefix (a lens id, or 'radial')."""
        return [p.stem[len(self.weights_prefix):] for p in self.shipped_files()]

    def shipped_file(self, key: str) -> Path | None:
        return weights_file(self.weights_prefix, key)


def weights_file(prefix: str, key: str) -> Path | None:
    """The shipped weights/<prefix><key>.npz (``key``: a lens id or 'radial'),
    or None; a ``key`` that is not a name (``names.NAME_RULE``) is refused
    (InputRangeError): it becomes part of the file's name."""
    from ..errors import InputRangeError
    from ..names import check_name
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

# lens ids whose depth from the capture's own blur (dcdi_core.dfd, `dcdi depth
# estimate`, with the lens's shipped refinement weights/dfd-refine-<lens>.npz)
# beat the best constant depth (each frame's own median) by at least 30 % in
# AbsRel on held-out factory captures at the pixel pitch the refinement
# learned, with noise (`python -m dcdi_core.experiments.dfd_refine_study`,
# docs/depth.md): `dcdi dof` without a depth map estimates depth this way for
# these lenses at that pitch unasked. MOS-S1: 0.241 against 0.364 (0.66x);
# MOS-S2: 0.219 against 0.364 (0.60x).
BLUR_DEPTH_BEATS_CONSTANT: tuple[str, ...] = ("mos-s1", "mos-s2")


def network(name: str) -> Network:
    try:
        return NETWORKS[name]
    except KeyError:
        from ..errors import InputRangeError
        raise InputRangeError("network", name, ", ".join(NETWORKS)) from None
