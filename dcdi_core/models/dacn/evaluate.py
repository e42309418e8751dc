"""DACN evaluation on held-out DA2T pairs: per pair, per scene, per depth band.

Every model is scored on the *depth-aware* capture of each pair (what a
camera records), whatever it was trained on: the depth-unaware model
(trained on the one-depth baseline) is judged on the same captures as the
DA2T one. The uncorrected capture is scored beside them.

Scores (``models.metrics``, data range 1, outputs clipped to [0, 1]) are
taken over the imaged pixels only (the lens images nothing where the depth
on the sensor is NaN). Per depth band (metres, the pixel's depth on the
sensor): PSNR from the band's pooled squared error over all pairs, SSIM as
the mean of the SSIM map over the band's pixels (the map's entry of a pixel
is that of the 11 x 11 window centred on it). Per scene: the mean of its
pairs. Pairs of scenes that the model's run trained or validated on are
never scored (``held_out_pairs``).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ...errors import InputRangeError
from .data import finished_pairs, load_pair, pair_path
from ...errors import ModelError
from ..common.metrics import WINDOW, psnr, ssim_map

DEPTH_BANDS_M = ((0.0, 0.7), (0.7, 1.0), (1.0, 2.0), (2.0, 5.0), (5.0, 10.0), (10.0, math.inf))
# field bands (image height over the sensor's semi-diagonal)
FIELD_BANDS = ((0.0, 0.3), (0.3, 0.6), (0.6, 1.01))


def field_band_name(lo: float, hi: float) -> str:
    return f"field {lo:g}-{min(hi, 1.0):g}"


def srgb_encode(x: np.ndarray) -> np.ndarray:
    """sRGB encoding (IEC 61966-2-1) of linear values, clipped to [0, 1] first."""
    x = np.clip(x, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(np.maximum(x, 0.0031308), 1 / 2.4) - 0.055)


def band_name(lo: float, hi: float) -> str:
    if lo <= 0:
        return f"< {hi:g} m"
    if math.isinf(hi):
        return f"> {lo:g} m"
    return f"{lo:g}-{hi:g} m"


@dataclass
class BandSums:
    """Pooled sums of one depth band: squared error and its count (pixels x
    channels), SSIM map values and their count."""
    sse: float = 0.0
    n: int = 0
    ssim_sum: float = 0.0
    ssim_n: int = 0

    def add(self, sse: float, n: int, ssim_sum: float, ssim_n: int) -> None:
        self.sse += sse
        self.n += n
        self.ssim_sum += ssim_sum
        self.ssim_n += ssim_n

    def scores(self) -> dict:
        out = {"pixels": self.n // 3}
        if self.n:
            mse = self.sse / self.n
            out["psnr"] = float("inf") if mse == 0 else 10.0 * math.log10(1.0 / mse)
        if self.ssim_n:
            out["ssim"] = self.ssim_sum / self.ssim_n
        return out


def image_scores(out: np.ndarray, target: np.ndarray, depth_m: np.ndarray, bands=DEPTH_BANDS_M,
                 field=None) -> dict:
    """Scores of one (H, W, 3) image against its target over the imaged
    pixels (finite or infinite ``depth_m``; NaN: not imaged): 'psnr', 'ssim',
    'psnr_srgb' (of the sRGB-encoded images), 'psnr_unmasked' (every pixel,
    linear), 'bands' {name: (sse, n, ssim_sum, ssim_n)} for pooling, and
    with ``field`` (H, W) each pixel's field, 'fields' alike per field band."""
    out = np.clip(np.asarray(out, np.float64), 0.0, 1.0)
    target = np.asarray(target, np.float64)
    if out.shape != target.shape or out.shape[:2] != depth_m.shape or out.ndim != 3:
        raise InputRangeError("image, target, depth shapes", (out.shape, target.shape, depth_m.shape),
                              "(H, W, 3), (H, W, 3) and (H, W)")
    imaged = ~np.isnan(depth_m)
    if not imaged.any():
        raise ModelError("no imaged pixel to score (the depth on the sensor is NaN everywhere)")
    err = ((out - target) ** 2).sum(axis=2)
    smap = ssim_map(out.transpose(2, 0, 1), target.transpose(2, 0, 1), 1.0).mean(axis=0)
    m = WINDOW // 2
    inner = np.zeros_like(imaged)
    inner[m:m + smap.shape[0], m:m + smap.shape[1]] = True
    full_ssim = np.zeros(imaged.shape)
    full_ssim[m:m + smap.shape[0], m:m + smap.shape[1]] = smap
    d = np.where(imaged, depth_m, np.nan)
    rec = {"psnr": float(psnr(out[imaged], target[imaged], 1.0)),
           "ssim": float(full_ssim[imaged & inner].mean()) if (imaged & inner).any() else float("nan"),
           "psnr_srgb": float(psnr(srgb_encode(out[imaged]), srgb_encode(target[imaged]), 1.0)),
           "psnr_unmasked": float(psnr(out, np.clip(target, 0.0, 1.0), 1.0)),
           "bands": {}, "fields": {}}
    if field is not None:
        for lo, hi in FIELD_BANDS:
            sel = imaged & (field >= lo) & (field < hi)
            if sel.any():
                s_sel = sel & inner
                rec["fields"][field_band_name(lo, hi)] = (float(err[sel].sum()), int(sel.sum()) * 3,
                                                          float(full_ssim[s_sel].sum()), int(s_sel.sum()))
    with np.errstate(invalid="ignore"):
        for lo, hi in bands:
            sel = imaged & (d >= lo) & ((d < hi) | (np.isinf(hi) & np.isinf(d)))
            if sel.any():
                s_sel = sel & inner
                rec["bands"][band_name(lo, hi)] = (float(err[sel].sum()), int(sel.sum()) * 3,
                                                   float(full_ssim[s_sel].sum()), int(s_sel.sum()))
    return rec


def held_out_pairs(data_root, run_splits: list) -> tuple[list, dict]:
    """(pair ids to score, {pair id: record}) of ``data_root``: pairs whose
    scene no run trained or validated on (in every run's recorded split, the
    scene is 'test' or unknown). A folder with none is an error."""
    pairs = finished_pairs(data_root)
    if not pairs:
        raise ModelError(f"{data_root}: no DA2T pairs (pairs.jsonl); build them with dcdi dacn pairs")
    keep = []
    for pid, rec in sorted(pairs.items()):
        # by scene: frames of other folders may reuse a trained frame's id (a factory's index), not its scene
        seen = any(sp.scenes.get(rec["scene"], "test") != "test" for sp in run_splits)
        if not seen:
            keep.append(pid)
    if not keep:
        raise ModelError(f"{data_root}: every pair belongs to a scene a model trained or validated on; "
                         "give the test pairs (or pairs of other scenes)")
    return keep, pairs


@dataclass
class Evaluation:
    names: list                                 # 'capture' (uncorrected), then the models
    pairs: list = field(default_factory=list)   # per pair {id, scene, <name>: {psnr, ssim}}
    bands: dict = field(default_factory=dict)   # name -> band -> BandSums
    fields: dict = field(default_factory=dict)  # name -> field band -> BandSums
    seconds: dict = field(default_factory=dict)  # name -> inference seconds in all

    def keys(self) -> list:
        return [k for k in ("psnr", "ssim", "psnr_srgb", "psnr_unmasked", "lpips")
                if self.pairs and k in self.pairs[0][self.names[0]]]

    def per_scene(self) -> dict:
        out = {}
        for row in self.pairs:
            out.setdefault(row["scene"], []).append(row)
        return {s: {n: {k: float(np.mean([r[n][k] for r in rows])) for k in self.keys()} for n in self.names}
                for s, rows in sorted(out.items())}

    def mean(self) -> dict:
        return {n: {k: float(np.mean([r[n][k] for r in self.pairs])) for k in self.keys()} for n in self.names}

    def band_scores(self) -> dict:
        return {n: {b: s.scores() for b, s in self.bands[n].items()} for n in self.names}

    def field_scores(self) -> dict:
        return {n: {b: s.scores() for b, s in self.fields.get(n, {}).items()} for n in self.names}

    def as_dict(self) -> dict:
        return {"names": self.names, "mean": self.mean(), "bands": self.band_scores(), "fields": self.field_scores(),
                "scenes": self.per_scene(), "pairs": self.pairs, "seconds": self.seconds}


def pair_geometry(record: dict, h: int, w: int):
    """The ``ImageGeometry`` a pair's record states (None for pairs built
    before it was recorded)."""
    from ...render.geometry import ImageGeometry
    g = record.get("geometry")
    if not g:
        return None
    return ImageGeometry(h, w, g["pixel_pitch_mm"], tuple(g["center_px"]), g["semi_diagonal_mm"])


def evaluate_models(models: dict, data_root, *, ids=None, correct_fn=None, tile: int = 256, overlap: int = 32,
                    progress=None, keep_outputs: int = 0, lpips=None) -> tuple[Evaluation, list]:
    """Score ``models`` {name: model} on the held-out pairs ``ids`` of
    ``data_root`` (default: all finished pairs), beside the capture and,
    where the pairs hold it, the deconvolution alone ('deconvolution').
    Returns (Evaluation, outputs) with outputs the first ``keep_outputs``
    pairs' (id, capture, {name: corrected}, target, depth) for pictures.
    ``correct_fn``: the tiled inference (default ``models.correct.correct``;
    it is given the pair's deconvolution and geometry); ``lpips``: an
    ``models.lpips.LPIPS`` to add that score (over the imaged pixels)."""
    if correct_fn is None:
        from .correct import correct as correct_fn
    for taken in ("capture", "deconvolution"):
        if taken in models:
            raise InputRangeError("model name", taken, "any other name (capture and deconvolution are the "
                                  "uncorrected input and the physics alone)")
    pairs = finished_pairs(data_root)
    ids = sorted(pairs) if ids is None else list(ids)
    has_dec = bool(ids) and all(pairs[p].get("deconvolved") for p in ids)
    names = ["capture"] + (["deconvolution"] if has_dec else []) + list(models)
    ev = Evaluation(names, bands={n: {} for n in names}, fields={n: {} for n in names},
                    seconds={n: 0.0 for n in models})
    kept = []
    for i, pid in enumerate(ids):
        p = load_pair(pair_path(data_root, pid), pairs[pid])
        capture, target, depth = np.array(p.capture), np.array(p.target), np.array(p.depth)
        dec = np.array(p.deconvolved) if has_dec else None
        geom = pair_geometry(pairs[pid], *depth.shape)
        fld = None if geom is None else geom.field(*np.indices(depth.shape))
        row = {"id": pid, "scene": pairs[pid]["scene"]}
        outs = {}
        for name in names:
            if name == "capture":
                out = capture
            elif name == "deconvolution":
                out = dec
            else:
                t0 = time.perf_counter()
                out = correct_fn(models[name], capture, depth, deconvolved=dec, geometry=geom, tile=tile,
                                 overlap=overlap)
                ev.seconds[name] += time.perf_counter() - t0
                outs[name] = out
            sc = image_scores(out, target, depth, field=fld)
            row[name] = {k: sc[k] for k in ("psnr", "ssim", "psnr_srgb", "psnr_unmasked")}
            if lpips is not None:
                from ..common.lpips import lpips_score
                row[name]["lpips"] = lpips_score(lpips, out, target, ~np.isnan(depth))
            for b, sums in sc["bands"].items():
                ev.bands[name].setdefault(b, BandSums()).add(*sums)
            for b, sums in sc["fields"].items():
                ev.fields[name].setdefault(b, BandSums()).add(*sums)
        ev.pairs.append(row)
        if i < keep_outputs:
            kept.append((pid, capture, outs, target, depth))
        if progress:
            progress(i + 1, len(ids))
    order = [band_name(lo, hi) for lo, hi in DEPTH_BANDS_M]
    ev.bands = {n: dict(sorted(b.items(), key=lambda kv: order.index(kv[0]))) for n, b in ev.bands.items()}
    forder = [field_band_name(lo, hi) for lo, hi in FIELD_BANDS]
    ev.fields = {n: dict(sorted(b.items(), key=lambda kv: forder.index(kv[0]))) for n, b in ev.fields.items()}
    return ev, kept


def markdown_tables(ev: Evaluation) -> str:
    """The mean table (linear PSNR / SSIM over the imaged pixels, sRGB PSNR,
    PSNR over every pixel) and the per depth and field band tables (PSNR dB
    / SSIM, pooled) as Markdown."""
    mean = ev.mean()
    lp = "lpips" in ev.keys()
    lines = ["| | PSNR / SSIM (imaged) | PSNR sRGB | PSNR every pixel" + (" | LPIPS" if lp else "") + " |",
             "|---|---|---|---|" + ("---|" if lp else "")]
    for n in ev.names:
        m = mean[n]
        lines.append(f"| {n} | {m['psnr']:.2f} / {m['ssim']:.4f} | {m['psnr_srgb']:.2f} | {m['psnr_unmasked']:.2f}"
                     + (f" | {m['lpips']:.4f}" if lp else "") + " |")
    out = "\n".join(lines) + "\n\n"
    for kind, scores, order in (("depth", ev.band_scores(), [band_name(lo, hi) for lo, hi in DEPTH_BANDS_M]),
                                ("field", ev.field_scores(), [field_band_name(lo, hi) for lo, hi in FIELD_BANDS])):
        bands = [b for b in order if any(b in scores[n] for n in ev.names)]
        if not bands:
            continue
        rows = ["| " + kind + " band | " + " | ".join(bands) + " |", "|" + "---|" * (len(bands) + 1)]
        for n in ev.names:
            cells = []
            for b in bands:
                s = scores[n].get(b, {})
                cells.append(f"{s['psnr']:.2f} / {s.get('ssim', float('nan')):.4f}" if "psnr" in s else "-")
            rows.append(f"| {n} | " + " | ".join(cells) + " |")
        px = {b: scores[ev.names[0]].get(b, {}).get("pixels", 0) for b in bands}
        total = max(sum(px.values()), 1)
        rows.append("| share of pixels | " + " | ".join(f"{100 * px[b] / total:.1f} %" for b in bands) + " |")
        out += "\n".join(rows) + "\n\n"
    return out


def panel_strip(panels, gap: int = 4) -> np.ndarray:
    """(H, W, 3) images side by side, clipped to [0, 1], with white gaps."""
    h = panels[0].shape[0]
    sep = np.ones((h, gap, 3), np.float32)
    parts = []
    for i, p in enumerate(panels):
        parts += ([sep] if i else []) + [np.clip(np.asarray(p, np.float32), 0.0, 1.0)]
    return np.concatenate(parts, axis=1)


def write_pictures(kept: list, out_dir, names: list) -> list:
    """One PNG per kept pair: capture | each model's correction | target
    (sRGB-encoded by ``io.images.write_image``, written atomically); returns
    the paths."""
    from ...io.images import write_image

    out_dir = Path(out_dir)
    paths = []
    for pid, capture, outs, target, _depth in kept:
        panels = [capture] + [outs[n] for n in names if n in outs] + [target]
        path = out_dir / f"{pid.replace('~', '-')}.png"
        write_image(path, panel_strip(panels))
        paths.append(path)
    return paths
