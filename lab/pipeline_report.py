"""`python -m lab report pipeline` and `python -m lab report depth`: the DCDI pipeline on held-out
factory scenes.

For each camera lens (MOS-S1, MOS-S2), on the held-out DA2T pairs of its
factory data (noisy, perturbed captures; the models never trained on those
scenes), the result of each row is compared with the *ideal*: the target
lens's bokeh of the true all-in-focus image with the true depth, traced PSFs.

Rows:
- ``no correction``: the bokeh of the capture as it is (true depth);
- ``corrected, true depth``: DACN with the true depth, then the bokeh;
- ``corrected, estimated depth``: depth from the capture by the depth network,
  used for the correction and the bokeh;
- ``corrected, true depth, OLF PSFs``: as the second row with the
  Omni-Lens-Field's PSFs (where it covers the request);
- ``depth-unaware model``: the second row with the model trained on the
  one-depth baseline (if given).

Scores: PSNR / SSIM over the imaged pixels (``evaluate.image_scores``).
The depth report: AbsRel, RMSE, delta1 of the depth network from the capture
and from the sharp image.
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from dcdi_core.atomic import write_text
from dcdi_core.models.dacn.data import load_pair, pair_path
from dcdi_core.models.dacn.evaluate import image_scores, panel_strip


def held_out(pairs_dir, split_runs: list, count: int) -> list:
    """The first ``count`` pairs of ``pairs_dir`` that no run trained or
    validated on (its recorded split.json counts as one run's)."""
    from dcdi_core.models.common.split import Split
    from dcdi_core.models.dacn.evaluate import held_out_pairs
    splits = list(split_runs)
    if (Path(pairs_dir) / "split.json").exists():
        splits.append(Split.load(Path(pairs_dir) / "split.json"))
    ids, _ = held_out_pairs(pairs_dir, splits)
    return ids[:count]


def _bokeh(image, depth, lens, keep, library=None, settings=None):
    from dcdi_core.render.bokeh import BokehOptions, bokeh
    # not imaged (NaN): left as it is by the bokeh, and out of the scores
    return bokeh(np.clip(image, 0, None), depth, lens, BokehOptions(keep=keep, settings=settings),
                 library=library).image


def lens_rows(lens_id: str, pairs_dir, ids: list, models: dict, target, keep, *, olf_file=None, pictures=None,
              log=print) -> dict:
    """Scores (mean over ``ids``) and stage seconds of every row for one camera lens."""
    from dcdi_core.render.geometry import ImageGeometry
    from dcdi_core.models.dacn.correct import correct
    from dcdi_core.psf.sources import psf_source
    from dcdi_core.models.depth.train import predict_depth
    rows, seconds = {}, {"depth": [], "correction": [], "psfs and bokeh": []}
    olf_msg = None
    for i, pid in enumerate(ids):
        p = load_pair(pair_path(pairs_dir, pid))
        cap, aif, depth = np.array(p.capture), np.array(p.target), np.array(p.depth)
        geom = ImageGeometry.full_sensor(target, *depth.shape)
        ideal = _bokeh(aif, depth, target, keep)
        out = {"no correction": _bokeh(cap, depth, target, keep)}
        t0 = time.perf_counter()
        corrected = correct(models["dacn"], cap, depth)
        seconds["correction"].append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        out["corrected, true depth"] = _bokeh(corrected, depth, target, keep)
        seconds["psfs and bokeh"].append(time.perf_counter() - t0)
        if models.get("depth") is not None:
            t0 = time.perf_counter()
            est = predict_depth(models["depth"], cap)
            seconds["depth"].append(time.perf_counter() - t0)
            est = np.where(np.isnan(depth), np.nan, est)
            out["corrected, estimated depth"] = _bokeh(correct(models["dacn"], cap, est), est, target, keep)
        src = psf_source(target, olf_file=olf_file, pixel_pitch_mm=geom.pixel_pitch_mm)
        olf_msg = src.message
        if src.library is not None:
            label = "OLF" if src.kind == "olf" else "PSF basis"
            out[f"corrected, true depth, {label} PSFs"] = _bokeh(corrected, depth, target, keep, library=src.library)
        if models.get("baseline") is not None:
            out["depth-unaware model"] = _bokeh(correct(models["baseline"], cap, depth), depth, target, keep)
        for name, img in out.items():
            sc = image_scores(img, np.clip(ideal, 0, 1), depth)
            rows.setdefault(name, []).append((sc["psnr"], sc["ssim"]))
        if pictures is not None and i < 2:
            from dcdi_core.io.images import write_image
            from dcdi_core.render.pictures import depth_panel
            shown = est if models.get("depth") is not None else depth
            write_image(Path(pictures) / f"{lens_id}-{pid.replace('~', '-')}.png",
                        panel_strip([cap, corrected, depth_panel(shown), out["corrected, estimated depth"
                                     if "corrected, estimated depth" in out else "corrected, true depth"], ideal]))
        log(f"  {lens_id} {pid}: " + ", ".join(f"{k} {v[-1][0]:.2f} dB" for k, v in rows.items()))
    return {"rows": {k: {"psnr": float(np.mean([a for a, _ in v])), "ssim": float(np.mean([b for _, b in v]))}
                     for k, v in rows.items()},
            "seconds": {k: float(np.mean(v)) for k, v in seconds.items() if v}, "pairs": len(ids), "olf": olf_msg}


def stage_times(models: dict, target, keep, size, *, olf_file=None) -> dict:
    """Seconds of each stage on one synthetic frame of ``size`` (rows, cols)."""
    from dcdi_core.render.geometry import ImageGeometry
    from dcdi_core.render.synthetic import synthetic_rgbd
    from dcdi_core.models.dacn.correct import correct
    from dcdi_core.psf.sources import psf_source
    from dcdi_core.models.depth.train import predict_depth
    img, depth = synthetic_rgbd(*size)
    img = np.clip(img, 0, 1).astype(np.float32)
    out = {}
    if models.get("depth") is not None:
        t0 = time.perf_counter()
        predict_depth(models["depth"], img)
        out["depth"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    corrected = correct(models["dacn"], img, depth)
    out["correction"] = time.perf_counter() - t0
    geom = ImageGeometry.full_sensor(target, *size)
    src = psf_source(target, olf_file=olf_file, pixel_pitch_mm=geom.pixel_pitch_mm)
    t0 = time.perf_counter()
    _bokeh(corrected, depth, target, keep, library=src.library)
    out["psfs and bokeh (" + src.kind + ")"] = time.perf_counter() - t0
    return out


def markdown(results: dict, target_id: str, keep) -> str:
    lines = [f"Target lens {target_id}, keep {keep[0]:g}-{keep[1]:g} m sharp; PSNR dB / SSIM against the ideal "
             "(the target lens's bokeh of the true all-in-focus image with the true depth, traced PSFs), mean "
             "over held-out pairs.\n"]
    names = []
    for r in results.values():
        names += [n for n in r["rows"] if n not in names]
    lines.append("| row | " + " | ".join(f"{lens} ({r['pairs']} pairs)" for lens, r in results.items()) + " |")
    lines.append("|---|" + "---|" * len(results))
    for n in names:
        cells = [f"{r['rows'][n]['psnr']:.2f} / {r['rows'][n]['ssim']:.4f}" if n in r["rows"] else "-"
                 for r in results.values()]
        lines.append(f"| {n} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def write_report(out_dir, results: dict, times: dict, target_id: str, keep) -> str:
    out_dir = Path(out_dir)
    text = markdown(results, target_id, keep)
    if times:
        text += "\nStage seconds (one synthetic frame, this machine, torch 1 thread):\n\n"
        stages = sorted({s for t in times.values() for s in t})
        text += "| camera, size | " + " | ".join(stages) + " |\n|---|" + "---|" * len(stages) + "\n"
        for key, t in times.items():
            text += f"| {key} | " + " | ".join(f"{t[s]:.2f}" if s in t else "-" for s in stages) + " |\n"
    write_text(out_dir / "pipeline.md", text)
    write_text(out_dir / "pipeline.json", json.dumps({"results": results, "times": times}, indent=1) + "\n")
    return text


def median_depth_m(pairs_dir, step: int = 4, stride: int = 16) -> float:
    """The median finite depth (m) of a pairs folder's training scenes (its
    split.json's 'train' part; every pair without one): every ``step``-th
    pair, every ``stride``-th pixel of each row and column."""
    from dcdi_core.models.common.split import Split
    from dcdi_core.models.dacn.data import finished_pairs
    recs = finished_pairs(pairs_dir)
    sp = Path(pairs_dir) / "split.json"
    split = Split.load(sp) if sp.exists() else None
    ids = [p for p in sorted(recs) if split is None or split.part(recs[p]["frame"]) == "train"][::step]
    if not ids:
        from dcdi_core.errors import ModelError
        raise ModelError(f"{pairs_dir}: no training pairs to take a median depth from")
    vals = []
    for pid in ids:
        d = np.asarray(load_pair(pair_path(pairs_dir, pid), recs[pid]).depth)[::stride, ::stride]
        vals.append(d[np.isfinite(d) & (d > 0)])
    return float(np.median(np.concatenate(vals)))


def depth_report(pairs: dict, depth_models: dict, split_runs: dict, count: int, constants: dict | None = None) -> dict:
    """{lens: {'capture': scores, 'sharp': scores[, 'constant': scores]}} of
    each lens's depth network; 'constant' (with ``constants`` {lens: m}, the
    training set's median depth): that one depth everywhere, the bar a
    depth network must clear."""
    from dcdi_core.models.common.metrics import depth_scores
    from dcdi_core.models.dacn.data import finished_pairs
    from dcdi_core.models.depth.train import evaluate_depth
    out = {}
    for lens, d in pairs.items():
        ids = held_out(d, split_runs.get(lens, []), count)
        out[lens] = {"pairs": len(ids), "capture": evaluate_depth(depth_models[lens], d, ids, input="capture"),
                     "sharp": evaluate_depth(depth_models[lens], d, ids, input="target")}
        if constants and lens in constants:
            recs = finished_pairs(d)
            rows = [depth_scores(np.full(dep.shape, constants[lens]), dep)
                    for dep in (np.asarray(load_pair(pair_path(d, p), recs[p]).depth) for p in ids)]
            out[lens]["constant"] = {k: float(np.mean([r[k] for r in rows])) for k in ("abs_rel", "rmse", "delta1")}
            out[lens]["constant_m"] = float(constants[lens])
    return out


def depth_markdown(res: dict) -> str:
    bar = any("constant" in r for r in res.values())
    lines = ["| lens | pairs | from | AbsRel | RMSE m | delta < 1.25 |" + (" AbsRel vs constant |" if bar else ""),
             "|---|---|---|---|---|---|" + ("---|" if bar else "")]
    for lens, r in res.items():
        base = r.get("constant", {}).get("abs_rel")
        for k in ("capture", "sharp", "constant"):
            if k not in r:
                continue
            s = r[k]
            name = f"constant {r['constant_m']:.2f} m" if k == "constant" else k
            vs = "" if base is None or k == "constant" else f"{100 * (s['abs_rel'] / base - 1):+.0f} %"
            lines.append(f"| {lens} | {r['pairs']} | {name} | {s['abs_rel']:.3f} | {s['rmse']:.2f} | {s['delta1']:.3f} |"
                         + (f" {vs} |" if bar else ""))
    return "\n".join(lines) + "\n"
