"""Export a trained Omni-Lens-Field: torch -> .npz arrays + JSON metadata.

The file is what ``psf.olf.OmniLensField`` serves without torch. Arrays:
``trunk{i}.weight`` (out, in) and ``trunk{i}.bias`` of the trunk's Linear
layers (each followed by ReLU), ``head{j}.weight`` / ``head{j}.bias`` of the
heads (paper: R, G, B, each W -> k^2, Sigmoid; radial: one per lens,
W -> 3 k^2, softmax per channel). ``meta``: one JSON string (no pickle
anywhere; read with ``allow_pickle=False``) with the variant and spec, each
lens with its optical fingerprint, kernel size, pixel pitch and trained
field / depth / focus ranges, the PSF settings, the training run, its
held-out figures, the format version and a sha256 checksum of all of it.
"""
from __future__ import annotations

import json

import numpy as np

from ... import __version__
from ...atomic import atomic_path
from .. import require_torch
from ...psf.olf import FORMAT, FORMAT_VERSION, checksum

torch = require_torch()

# storage dtypes; the runtime computes in float32 (or float64) whatever the file holds
DTYPES = ("float32", "float16", "float64")


def olf_arrays(module, dtype="float32") -> tuple[dict, dict]:
    """(arrays, network description) of an ``arch.olf.OLF`` module."""
    arrays, trunk, heads = {}, [], []
    linears = [m for m in module.trunk if isinstance(m, torch.nn.Linear)]
    for i, m in enumerate(linears):
        arrays[f"trunk{i}.weight"] = m.weight.detach().cpu().numpy().astype(dtype)
        arrays[f"trunk{i}.bias"] = m.bias.detach().cpu().numpy().astype(dtype)
        trunk.append([f"trunk{i}.weight", f"trunk{i}.bias"])
    for j, m in enumerate(module.heads):
        arrays[f"head{j}.weight"] = m.weight.detach().cpu().numpy().astype(dtype)
        arrays[f"head{j}.bias"] = m.bias.detach().cpu().numpy().astype(dtype)
        heads.append([f"head{j}.weight", f"head{j}.bias"])
    out = "sigmoid (peak scale), one head per colour" if module.spec.variant == "paper" \
        else "softmax over each channel's k^2 pixels, one head per lens"
    return arrays, {"trunk": trunk, "heads": heads, "activation": "relu", "output": out}


def stored_held_out(meta: dict, arrays: dict, data) -> dict:
    """The held-out figures of the stored arrays (``dtype`` as written), served
    by the numpy runtime: what a user of the file gets."""
    from ..common.metrics import psf_scores
    from ...psf.olf import OmniLensField
    olf = OmniLensField(meta, arrays)
    scale = "peak" if olf.variant == "paper" else "sum"
    per = {ls.lens.id: psf_scores(olf.forward(ls.val_x, li, np.float64), ls.val_y, scale=scale)
           for li, ls in enumerate(data.lenses)}
    keys = [k for k in next(iter(per.values())) if k != "n"]
    mean = {k: (float(np.mean([v[k] for v in per.values()])) if all(v[k] is not None for v in per.values())
                else None) for k in keys}
    out = {"mean": mean, "lenses": per}
    focus = {}
    for li, ls in enumerate(data.lenses):
        fm = ls.val_coords.get("focus_m")
        entry = olf.lens_entry(ls.lens.id)
        if fm is None or entry.get("focus_diopters_range") is None:
            continue
        bands = focus_bands(fm, entry["focus_diopters_range"])
        pred = olf.forward(ls.val_x, li, np.float64)
        focus[ls.lens.id] = {b: psf_scores(pred[bands == b], ls.val_y[bands == b], scale=scale)
                             for b in FOCUS_BANDS if (bands == b).any()}
    if focus:
        out["focus"] = focus
    return out


FOCUS_BANDS = ("prescribed", "far", "mid", "near")


def focus_bands(focus_m, diopters_range) -> np.ndarray:
    """The band of each held-out focus (m; NaN = the prescribed focus): the
    learned diopter range cut in thirds, far (towards infinity) to near."""
    f = np.asarray(focus_m, dtype=np.float64)
    lo, hi = diopters_range
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (1.0 / f - lo) / (hi - lo)
    third = np.clip(np.floor(np.nan_to_num(t) * 3), 0, 2).astype(int)
    return np.where(np.isnan(f), "prescribed", np.array(FOCUS_BANDS[1:])[third])


def export_olf(result, path, *, weights: str = "ema", dtype: str = "float32") -> dict:
    """Write the trained run ``result`` (``train.loop.TrainResult``) to ``path``
    (atomically); returns the metadata. ``dtype``: how the arrays are stored
    (float16 halves the file; the held-out figures recorded are then those of
    the stored weights, measured with the numpy runtime)."""
    if weights not in ("ema", "model"):
        raise ValueError(f"weights = {weights!r}; allowed: 'ema' or 'model'")
    if dtype not in DTYPES:
        raise ValueError(f"dtype = {dtype!r}; allowed: {', '.join(map(repr, DTYPES))}")
    module = result.ema if weights == "ema" else result.model
    arrays, network = olf_arrays(module, dtype)
    cfg = result.config
    meta = {
        "format": FORMAT, "version": FORMAT_VERSION, "dcdi_version": __version__,
        "variant": result.spec.variant, "spec": result.spec.as_dict(), "network": network,
        "weights": weights, "dtype": dtype, "parameters": int(sum(a.size for a in arrays.values())),
        "lenses": result.data.lens_metadata(),
        "training": {"config": cfg.as_dict(), "iterations": result.step, "seconds": result.seconds,
                     "torch": torch.__version__},
        "held_out_torch": result.held_out.get(weights),
    }
    meta["held_out"] = stored_held_out(meta, arrays, result.data)
    meta["checksum"] = checksum(meta, arrays)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            from ...io.npzfile import save_npz
            save_npz(f, {"meta": np.array(json.dumps(meta, sort_keys=True)), **arrays}, compressed=False)
    return meta
