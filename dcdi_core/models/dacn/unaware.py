"""The depth-unaware pipeline at any design's size: the study's ``refine@2m``
row, and how any run trained that way is fed.

The paper's baseline is a network that never learns depth. Beside the
plain ``baseline`` row (no depth, no field, no deconvolution) the study
also trains the shipped design (``refine``: depth and field channels, the
deconvolution in front) the depth-unaware way, so that only depth differs
between it and ``refine``:

- trained on the one-depth captures (every patch blurred at
  ``told_depth_m``, the pairs' ``baseline_depth_m``), told that depth
  everywhere, and refining their deconvolution at that one depth
  (``DeconvOptions.one_depth_m``);
- tested, as every row, on the depth-aware captures, still told one depth
  and refining the one-depth deconvolution: what a camera pipeline that
  knows no depth would do.

``derive_pairs`` writes that training set (a pairs folder of its own,
resumable; ``da2t.json`` records ``told_depth_m``, so a run trained on it
carries the fact in its checkpoint), and ``Correction`` is the inference
that honours it (``dcdi dacn eval`` uses it for such runs).
"""
from __future__ import annotations

import hashlib
import shutil
from pathlib import Path

import numpy as np

from ...errors import InputRangeError
from ...io.jsontext import loads


def told_depth(model_info: dict) -> float | None:
    """The one depth (m) a run was trained to be told, None for a
    depth-aware run (read from its checkpoint's recorded ``da2t.json``)."""
    v = (model_info.get("da2t") or {}).get("told_depth_m")
    return None if v is None else float(v)


def told_depth_map(depth_m: np.ndarray, told_m: float) -> np.ndarray:
    """``told_m`` where the lens images (finite depth), NaN elsewhere."""
    return np.where(np.isnan(depth_m), np.nan, np.float32(told_m)).astype(np.float32)


class OneDepthDeconvolution:
    """The nominal lens's deconvolution of an image told one depth (every
    window's PSFs at ``told_m``); PSF libraries kept per pixel pitch."""

    def __init__(self, lens_id: str, told_m: float, config):
        from ...correct.deconvolution import DeconvOptions
        from ...optics.lens import load_lens
        if not (np.isfinite(told_m) and told_m > 0):
            raise InputRangeError("told depth", told_m, "a finite depth > 0 m")
        self.lens, self.told_m, self.config = load_lens(lens_id), float(told_m), config
        self.options = DeconvOptions(one_depth_m=self.told_m)
        self._libraries = {}

    def __call__(self, image: np.ndarray, depth_m: np.ndarray, geometry) -> np.ndarray:
        from ...correct.deconvolution import deconvolve
        from .data import nominal_library
        lib = nominal_library(self.lens, geometry, self.config, self._libraries)
        return deconvolve(image, told_depth_map(depth_m, self.told_m), self.lens, self.options,
                          geometry=geometry, library=lib).image.astype(np.float32)


DERIVED_KEYS = ("told_depth_m", "derived_from")      # what derive_pairs adds to its source's da2t.json


def _config(pairs_dir):
    from .data import DA2TConfig
    path = Path(pairs_dir, "da2t.json")
    d = loads(path.read_text(encoding="utf-8"), path)
    return DA2TConfig.from_dict({k: v for k, v in d.items() if k not in DERIVED_KEYS})


def derive_pairs(src, dst, told_m: float | None = None, *, progress=None) -> dict:
    """The depth-unaware training set of the DA2T pairs in ``src``, into
    ``dst``: each pair's one-depth capture (its ``baseline``) as the capture,
    the depth told ``told_m`` (default: the pairs' ``baseline_depth_m``, the
    depth that capture was blurred at) and the nominal lens's one-depth
    deconvolution. Resumable; a ``dst`` derived with another depth or from
    other pairs is refused. Returns {pair id: record} of ``dst``."""
    from ...dataset.factory_folder import append_record
    from .data import DA2TPair, finished_pairs, frame_geometry, load_pair, pair_path, record_settings, save_pair
    src, dst = Path(src), Path(dst)
    if not (src / "da2t.json").exists():
        raise InputRangeError(f"{src}/da2t.json", "missing", "a DA2T pairs folder (dcdi dacn pairs)")
    cfg_src = loads((src / "da2t.json").read_text(encoding="utf-8"), src / "da2t.json")
    if "told_depth_m" in cfg_src:
        raise InputRangeError(f"{src}/da2t.json", "derived pairs", "DA2T pairs as dcdi dacn pairs built them")
    base_m = float(cfg_src["baseline_depth_m"])
    if told_m is not None and float(told_m) != base_m:
        raise InputRangeError(f"{src}/da2t.json: told depth", told_m, f"{base_m:g} m, the depth its one-depth "
                              "captures were blurred at (build pairs with --baseline-depth to tell another)")
    told_m = base_m
    record_settings(dst, dict(cfg_src, told_depth_m=told_m, derived_from=str(src.resolve())))
    if (src / "split.json").exists() and not (dst / "split.json").exists():
        shutil.copyfile(src / "split.json", dst / "split.json")
    deconv = OneDepthDeconvolution(cfg_src["lens"], told_m, _config(src))
    todo = finished_pairs(src)
    done = finished_pairs(dst)
    for i, (pid, rec) in enumerate(sorted(todo.items())):
        if pid in done:
            continue
        p = load_pair(pair_path(src, pid), rec)
        h, w = p.depth.shape
        geom = frame_geometry(deconv.lens, h, w, rec.get("sensor_px"), rec.get("top_left"))
        image = np.array(p.baseline)
        told = told_depth_map(np.array(p.depth), told_m)
        new = dict(rec, told_depth_m=told_m, deconvolved=True, capture="baseline")
        save_pair(dst, DA2TPair(pid, p.scene, image, np.array(p.target), image, told, new,
                                deconv(image, told, geom)))
        append_record(dst / "pairs.jsonl", new)
        done[pid] = new
        if progress:
            progress(i + 1, len(todo))
    return done


class Correction:
    """The evaluation's inference (``evaluate_models``' ``correct_fn``): a
    run trained told one depth (``told_depth``) is told it here too and
    refines the one-depth deconvolution (made once per capture); every other
    run is ``models.dacn.correct.correct`` as it is. Geometry: the
    capture's on the sensor (the deconvolution's PSFs are the nominal
    lens's at its pitch, traced as the pairs' settings say)."""

    def __init__(self, told: dict, lens_id: str, pairs_dir):
        self.told = {id(m): t for m, t in told.items() if t is not None}
        self._deconv = {t: OneDepthDeconvolution(lens_id, t, _config(pairs_dir)) for t in set(self.told.values())}
        self._made = {}

    def __call__(self, model, capture, depth, *, deconvolved=None, geometry=None, **kw):
        from .correct import correct
        t = self.told.get(id(model))
        if t is None:
            return correct(model, capture, depth, deconvolved=deconvolved, geometry=geometry, **kw)
        # the evaluation runs every model on one capture before the next: keep the last capture's only
        key = hashlib.blake2b(np.ascontiguousarray(capture).tobytes(), digest_size=16).hexdigest()
        if self._made.get(t, (None,))[0] != key:
            self._made[t] = (key, self._deconv[t](capture, depth, geometry))
        return correct(model, capture, told_depth_map(depth, t), deconvolved=self._made[t][1], geometry=geometry,
                       **kw)
