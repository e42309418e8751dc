"""`python -m lab report correction`: the lens's blur undone without training
(``dcdi_core.correct.deconvolve``), against the truth, beside the capture,
the depth-unaware deconvolution and the shipped DACN.

Frames. Each scene (the built-in synthetic scene at several seeds, and the
all-in-focus frames of factory folders given with ``--data``) is simulated
through the lens by ``render.simulate.LensSimulator`` (distortion, the
depth-aware patch-wise blur, sensor noise: full well 10,000 e-, read noise
3 e-) at two pixel pitches:

- the paper's, 12.2 um: the frame is a crop of the 1280 x 1920 sensor
  centred on the axis ('centre'), half way to the sensor's corner
  ('mid-field'), or with its outer corner on the sensor's corner ('edge');
- the full sensor: the frame spans the sensor's diagonal (480 x 640 frames:
  35.2 um pixels, where the shipped DACN learned).

PSFs: the shipped Omni-Lens-Field's where it covers the pitch, for the
simulation and the deconvolution alike (true PSFs: the deconvolution's
error is its own, not the PSFs'); one row deconvolves with traced PSFs
instead (the model's error included).

Scores (``models.common.metrics``, data range 1): outputs and the target
(the simulation's sharp image on the sensor) clipped to [0, 1] as a sensor
records them; over the imaged pixels (the distortion leaves a crop's outer
pixels unimaged); PSNR from the squared error pooled over all frames' pixels
of a region, SSIM the mean of the SSIM map (each channel's, averaged) over
the region's pixels; in linear light and in sRGB; with every pixel, and
with the pixels within the kernel's radius of a clipped capture value
(>= 0.98) left out (their light is lost to every method). Regions: the whole
frame, depth bands (the pixel's depth on the sensor) and field bands (its
normalised image height). Times: wall and CPU seconds (all threads) per
megapixel of frame, the PSF bins computed beforehand.
"""
from __future__ import annotations

import dataclasses
import json
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from dcdi_core.atomic import write_text
from dcdi_core.correct import DeconvOptions, NoiseModel, deconvolve
from dcdi_core.correct.wiener import layout_for
from dcdi_core.errors import InputRangeError
from dcdi_core.io.images import linear_to_srgb
from dcdi_core.models.common.metrics import WINDOW, ssim_map
from dcdi_core.models.dacn.evaluate import BandSums
from dcdi_core.render.geometry import ImageGeometry
from dcdi_core.render.simulate import LensSimulator, SimulateOptions
from dcdi_core.render.base import check_within_sensor
from dcdi_core.psf.sources import open_library
from dcdi_core.render.synthetic import synthetic_rgbd

PAPER_PITCH_MM = 0.0122
SENSOR_PX = (1280, 1920)                    # the paper's sensor at 12.2 um
POSITIONS = {"centre": 0.0, "mid-field": 0.5, "edge": 1.0}   # of the way from the axis to the sensor's corner
DEPTH_BANDS_M = ((0.7, 1.0), (1.0, 2.0), (2.0, 5.0), (5.0, 10.0), (10.0, math.inf))
FIELD_BANDS = ((0.0, 0.35), (0.35, 0.7), (0.7, 1.0))
NOISE = {"full_well_electrons": 10000.0, "read_noise_electrons": 3.0}
CLIP_LEVEL = 0.98
VIEWS = ("linear", "sRGB", "linear, highlights masked", "sRGB, highlights masked")
CROPS, FULL = "12.2 um crops", "full sensor"
FIXED_PRIOR_WEIGHT = 60.0     # the deconvolution's default weight when its prior was one image statistic


@dataclass(frozen=True)
class ReportOptions:
    """What the report measures (checked when made).

    lenses: lens ids. data: factory folders (or any RGB-D source
    ``dataset.rgbd.open_source`` reads) whose first ``frames`` frames join
    the synthetic scenes. quick: small frames, one seed, no traced PSFs
    (for tests). threads: torch's threads for the DACN."""

    lenses: tuple = ("mos-s1", "mos-s2")
    data: tuple = ()
    quick: bool = False
    frames: int = 2
    threads: int = 1

    def __post_init__(self):
        if not self.lenses:
            raise InputRangeError("--lens", "none", "one or more lens ids, e.g. mos-s1")
        if not (isinstance(self.frames, int) and self.frames >= 1):
            raise InputRangeError("--frames", self.frames, "an integer >= 1 (frames per --data folder)")
        if not (isinstance(self.threads, int) and self.threads >= 1):
            raise InputRangeError("--threads", self.threads, "an integer >= 1")

    @property
    def crop_px(self) -> tuple[int, int]:
        return (128, 192) if self.quick else (320, 480)      # smaller edge crops lie wholly in the unimaged corner

    @property
    def full_px(self) -> tuple[int, int]:
        return (60, 80) if self.quick else (480, 640)

    @property
    def seeds(self) -> tuple[int, ...]:
        return (1,) if self.quick else (1, 2, 3)

    @property
    def traced(self) -> bool:
        return not self.quick


# ------------------------------------------------------------------ frames
SYNTHETIC = "synthetic scenes"


@dataclass
class Scene:
    name: str
    source: str                  # SYNTHETIC, or the data folder's name: frames are scored per source
    image: np.ndarray            # (H, W, 3) linear, all in focus
    depth: np.ndarray            # (H, W) metres


@dataclass
class Frame:
    """One simulated capture and what scores it."""

    case: str                    # '12.2 um, centre', ..., 'full sensor'
    group: str                   # CROPS or FULL
    scene: str
    source: str
    capture: np.ndarray
    sharp: np.ndarray
    depth: np.ndarray            # on the sensor; NaN: not imaged
    geometry: ImageGeometry
    library: object              # the PSFs that simulated it
    traced: object = None        # a traced library at its pitch (or None)
    sim_seconds: tuple = (0.0, 0.0)

    @property
    def megapixels(self) -> float:
        return self.depth.size / 1e6


def crop_geometry(lens, h: int, w: int, position: str) -> ImageGeometry:
    """A h x w crop of the 1280 x 1920 sensor at 12.2 um, at ``position``
    (one of POSITIONS); refused if it does not lie within the sensor."""
    big_h, big_w = SENSOR_PX
    if h > big_h or w > big_w:
        raise InputRangeError("frame size at 12.2 um", (h, w), f"at most {big_h} x {big_w} px (the sensor)")
    f = POSITIONS[position]
    r0 = min(max(round((big_h - 1) / 2 * (1 + f) - (h - 1) / 2), 0), big_h - h)
    c0 = min(max(round((big_w - 1) / 2 * (1 + f) - (w - 1) / 2), 0), big_w - w)
    geom = ImageGeometry.from_pixel_pitch(lens, h, w, PAPER_PITCH_MM,
                                          center_px=((big_h - 1) / 2 - r0, (big_w - 1) / 2 - c0))
    check_within_sensor(geom, f"the {position} crop")
    return geom


def cases(lens, size_crop, size_full) -> list[tuple[str, str, Callable]]:
    """(case, group, geometry of a (h, w) frame) for each place a frame is put."""
    out = [(f"12.2 um, {p}", CROPS, (lambda h, w, p=p: crop_geometry(lens, h, w, p))) for p in POSITIONS]
    out.append((FULL, FULL, lambda h, w: ImageGeometry.full_sensor(lens, h, w)))
    return out


def load_data_scenes(folders, frames: int) -> list[Scene]:
    """The first ``frames`` frames of each RGB-D source (all read now: a bad
    folder fails before any work)."""
    from dcdi_core.dataset.rgbd import open_source
    out = []
    for folder in folders:
        src = open_source(folder)
        ids = src.ids()[:frames]
        if not ids:
            raise InputRangeError("--data", str(folder), "a folder with at least one finished frame")
        for i in ids:
            fr = src.load(i)
            out.append(Scene(f"{Path(folder).name}/{i}", Path(folder).name, fr.image, fr.depth))
    return out


def scenes_at(size, data_scenes: list[Scene], seeds) -> list[Scene]:
    """The synthetic scene at ``size`` for each seed, then the data frames (their own size)."""
    out = []
    for s in seeds:
        img, dep = synthetic_rgbd(*size, seed=s)
        out.append(Scene(f"synthetic (seed {s})", SYNTHETIC, img, dep))
    return out + list(data_scenes)


class Libraries:
    """The PSF libraries of one lens per pixel pitch: the OLF's where it
    covers the pitch (else traced), and traced ones for the traced row."""

    def __init__(self, lens):
        self.lens = lens
        self.olf, self.traced, self.messages = {}, {}, {}

    def main(self, geometry: ImageGeometry):
        key = round(geometry.pixel_pitch_mm, 9)
        if key not in self.olf:
            from dcdi_core.psf.sources import PSFRequest, open_source
            src = open_source(self.lens, geometry, PSFRequest(fit_kernel=False))
            lib = src.library
            if src.kind != "trace":
                lib.build()                  # every bin now (network or basis: cheap): none inside a timing
            self.olf[key], self.messages[key] = (lib, src.kind), src.message
        return self.olf[key]

    def trace(self, geometry: ImageGeometry, depth):
        key = round(geometry.pixel_pitch_mm, 9)
        if key not in self.traced:
            self.traced[key] = open_library(self.lens, geometry, fit_depth_m=depth)
        return self.traced[key]


def _ensure(library, depth) -> None:
    """The bins a frame's deconvolutions need (its depths, 2 m, infinity)."""
    d = np.asarray(depth, np.float64)
    d = d[d > 0]                          # NaN (not imaged) compares False
    library.ensure(np.concatenate([d.ravel(), [2.0, math.inf]]), clamp_near=True)


def simulate_frame(lens, libs: Libraries, case, group, geometry, scene: Scene, seed: int, traced: bool) -> Frame:
    lib, kind = libs.main(geometry)
    sim = LensSimulator(lens, SimulateOptions(geometry=geometry), library=lib)
    t, c = time.perf_counter(), time.process_time()
    r = sim(scene.image, scene.depth, noise=dict(NOISE), seed=seed)
    secs = (time.perf_counter() - t, time.process_time() - c)
    _ensure(lib, r.depth)
    tr = None
    if traced and kind in ("olf", "basis"):
        tr = libs.trace(geometry, r.depth)
        _ensure(tr, r.depth)
    return Frame(case, group, scene.name, scene.source, r.image, r.sharp, r.depth, geometry, lib, tr, secs)


def all_frames(lens, libs: Libraries, options: ReportOptions, data_scenes, log) -> list[Frame]:
    frames = []
    for k, (case, group, geom_of) in enumerate(cases(lens, options.crop_px, options.full_px)):
        size = options.crop_px if group == CROPS else options.full_px
        for j, scene in enumerate(scenes_at(size, data_scenes, options.seeds)):
            geom = geom_of(*scene.depth.shape)
            frames.append(simulate_frame(lens, libs, case, group, geom, scene, 1000 * k + j, options.traced))
        log(f"  {lens.id}, {case}: {len(frames)} frames simulated")
    return frames


# ------------------------------------------------------------------ scores
class Sums(BandSums):
    """Pooled sums of one region (``models.dacn.evaluate.BandSums``), added
    from an error map, an SSIM map and the region's pixels; scores JSON-safe."""

    def add_region(self, err: np.ndarray, smap: np.ndarray, sel: np.ndarray) -> None:
        s = smap[sel]
        s = s[np.isfinite(s)]
        self.add(float(err[sel].sum()), 3 * int(sel.sum()), float(s.sum()), int(s.size))

    def scores(self) -> dict:
        base = super().scores()
        return {"psnr": _finite(base.get("psnr", math.nan)), "ssim": _finite(base.get("ssim", math.nan)),
                "pixels": base["pixels"]}


def _finite(v: float):
    return None if v is None or not math.isfinite(v) else round(float(v), 4)


def band_name(lo: float, hi: float, unit: str = " m") -> str:
    return f"> {lo:g}{unit}" if math.isinf(hi) else f"{lo:g}-{hi:g}{unit}"


def regions(frame: Frame) -> dict[str, np.ndarray]:
    """{region: pixels} of a frame: 'all' imaged pixels, depth bands, field bands."""
    d = frame.depth
    imaged = ~np.isnan(d)
    h, w = d.shape
    fld = frame.geometry.field(np.arange(h)[:, None], np.arange(w)[None, :])
    out = {"all": imaged}
    with np.errstate(invalid="ignore"):
        for lo, hi in DEPTH_BANDS_M:
            out["depth " + band_name(lo, hi)] = imaged & (d >= lo) & ((d < hi) | np.isinf(hi))
    for lo, hi in FIELD_BANDS:
        top = fld <= hi + 1e-9 if hi >= 1.0 else fld < hi
        out["field " + band_name(lo, hi, "")] = imaged & (fld >= lo) & top
    return out


def highlights(capture: np.ndarray, radius: int) -> np.ndarray:
    """Pixels within ``radius`` px (a square) of a capture value >= CLIP_LEVEL."""
    clipped = (capture >= CLIP_LEVEL).any(axis=2)
    if not clipped.any():
        return clipped
    s = np.pad(np.cumsum(np.cumsum(clipped.astype(np.int64), 0), 1), ((1, 0), (1, 0)))
    h, w = clipped.shape
    r0, r1 = np.clip(np.arange(h) - radius, 0, h), np.clip(np.arange(h) + radius + 1, 0, h)
    c0, c1 = np.clip(np.arange(w) - radius, 0, w), np.clip(np.arange(w) + radius + 1, 0, w)
    return (s[r1][:, c1] - s[r0][:, c1] - s[r1][:, c0] + s[r0][:, c0]) > 0


def error_maps(out: np.ndarray, truth: np.ndarray, srgb: bool):
    """(squared error summed over channels (H, W), SSIM map (H, W), NaN
    where the 11 x 11 window leaves the frame) of [0, 1]-clipped images."""
    a = np.clip(np.asarray(out, np.float64), 0.0, 1.0)
    b = np.clip(np.asarray(truth, np.float64), 0.0, 1.0)
    if srgb:
        a, b = linear_to_srgb(a), linear_to_srgb(b)
    err = ((a - b) ** 2).sum(axis=2)
    smap = ssim_map(a.transpose(2, 0, 1), b.transpose(2, 0, 1), 1.0).mean(axis=0)
    full = np.full(err.shape, np.nan)
    m = WINDOW // 2
    full[m:m + smap.shape[0], m:m + smap.shape[1]] = smap
    return err, full


class Scores:
    """Sums per (view, region), added frame by frame."""

    def __init__(self):
        self.sums: dict = {}
        self.wall = self.cpu = self.megapixels = 0.0
        self.frames = 0

    def add(self, out, frame: Frame, masks: dict, hi: np.ndarray, seconds=(0.0, 0.0)) -> None:
        for srgb in (False, True):
            err, smap = error_maps(out, frame.sharp, srgb)
            space = "sRGB" if srgb else "linear"
            for region, sel in masks.items():
                self.sums.setdefault((space, region), Sums()).add_region(err, smap, sel)
                self.sums.setdefault((space + ", highlights masked", region), Sums()).add_region(err, smap, sel & ~hi)
        self.wall += seconds[0]
        self.cpu += seconds[1]
        self.megapixels += frame.megapixels
        self.frames += 1

    def result(self) -> dict:
        out = {v: {r: s.scores() for (v2, r), s in self.sums.items() if v2 == v} for v in VIEWS}
        mp = max(self.megapixels, 1e-12)
        out["seconds_per_megapixel"] = {"wall": _finite(self.wall / mp), "cpu": _finite(self.cpu / mp)}
        out["frames"] = self.frames
        return out


# ------------------------------------------------------------------ methods
@dataclass
class Method:
    name: str
    run: Callable                # Frame -> (H, W, 3) image
    timed: bool = True


def _deconv(lens, options: DeconvOptions, traced: bool = False) -> Callable:
    def run(frame: Frame):
        lib = frame.traced if traced else frame.library
        return deconvolve(frame.capture, frame.depth, lens, options, geometry=frame.geometry, library=lib).image
    return run


def load_network(lens_id: str, threads: int):
    """The shipped DACN of a lens, or (None, why not)."""
    from dcdi_core.shipped import network
    path = network("dacn").shipped_file(lens_id)
    if path is None:
        return None, f"no shipped DACN for {lens_id}"
    try:
        import torch
    except ImportError:
        return None, "torch is not installed"
    from dcdi_core.models.dacn.correct import load_dacn
    torch.set_num_threads(threads)
    return load_dacn(path)[0], f"{path.name} ({threads} torch thread(s))"


def methods(lens, model, traced: bool) -> list[Method]:
    rows = [Method("capture", lambda f: f.capture, timed=False),
            Method("deconvolution, depth per patch", _deconv(lens, DeconvOptions())),
            Method("deconvolution, depth layers 0.1 D", _deconv(lens, DeconvOptions(layer_step_diopters=0.1))),
            Method("deconvolution, HQS (iterative)", _deconv(lens, DeconvOptions(method="hqs"))),
            Method("deconvolution, one depth 2 m", _deconv(lens, DeconvOptions(one_depth_m=2.0))),
            Method("deconvolution, one depth infinity", _deconv(lens, DeconvOptions(one_depth_m=math.inf)))]
    if traced:
        rows.append(Method("deconvolution, traced PSFs", _deconv(lens, DeconvOptions(), traced=True)))
    if model is not None:
        rows.append(Method("DACN (shipped)", _network(lens, model)))
    return rows


def _network(lens, model) -> Callable:
    """The shipped network as `dcdi correct` runs it: a refining one after
    the default deconvolution (its time included), told where the frame
    lies on the sensor."""
    from dcdi_core.models.dacn.correct import correct
    first = _deconv(lens, DeconvOptions()) if model.spec.refine else None

    def run(frame: Frame):
        return correct(model, frame.capture, frame.depth, geometry=frame.geometry,
                       deconvolved=first(frame) if first else None)
    return run


def timed(fn, frame: Frame):
    t, c = time.perf_counter(), time.process_time()
    out = fn(frame)
    return out, (time.perf_counter() - t, time.process_time() - c)


def picture_frame(frames: list[Frame]) -> Frame | None:
    """The frame of the picture: mid-field at 12.2 um, a data frame if there is one."""
    mid = [f for f in frames if f.case.endswith("mid-field")]
    data = [f for f in mid if f.source != SYNTHETIC]
    return (data or mid or [None])[0]


def score_methods(frames: list[Frame], rows: list[Method], log) -> tuple[dict, dict]:
    """{source: {case or group: {method: scores}}}, and {method: output} of the picture's frame."""
    acc: dict = {}
    pic, picture = picture_frame(frames), {}
    for frame in frames:
        masks = regions(frame)
        hi = highlights(frame.capture, frame.library.kernel_size // 2)
        for m in rows:
            if "traced" in m.name and frame.traced is None:
                continue
            out, secs = timed(m.run, frame)
            for key in (frame.case, frame.group):
                acc.setdefault(frame.source, {}).setdefault(key, {}).setdefault(m.name, Scores()).add(
                    out, frame, masks, hi, secs if m.timed else (0.0, 0.0))
            if frame is pic:
                picture[m.name] = out
        log(f"    {frame.case}, {frame.scene}: PSNR " + ", ".join(
            f"{n} {acc[frame.source][frame.case][n].result()['linear']['all']['psnr']} dB"
            for n in ("capture", "deconvolution, depth per patch")))
    if pic is not None:
        picture["frame"] = pic
    return {src: {k: {n: s.result() for n, s in v.items()} for k, v in by.items()} for src, by in acc.items()}, picture


def simulation_times(frames: list[Frame]) -> dict:
    """{source: {case or group: wall and CPU s per megapixel}} of the simulation that made the captures."""
    out = {}
    for f in frames:
        for key in (f.case, f.group):
            t = out.setdefault(f.source, {}).setdefault(key, [0.0, 0.0, 0.0])
            t[0], t[1], t[2] = t[0] + f.sim_seconds[0], t[1] + f.sim_seconds[1], t[2] + f.megapixels
    return {src: {k: {"wall": _finite(t[0] / t[2]), "cpu": _finite(t[1] / t[2])} for k, t in by.items()}
            for src, by in out.items()}


# ------------------------------------------------------------------ settings
def variants(kernel_size: int, traced: bool) -> list[tuple[str, DeconvOptions, bool]]:
    """(label, options, traced PSFs) for the error-against-time table: the
    default, then one setting changed at a time."""
    base = DeconvOptions()
    pad = layout_for(base.patch, kernel_size, None).pad
    default = (f"default: {base.method}, prior {base.prior}, patch {base.patch}, pad {pad} px, weight {base.weight:g}, "
               + ("one depth a patch" if base.layer_step_diopters is None else f"layers {base.layer_step_diopters:g} D")
               + (", noise estimated" if base.noise is None else ", noise given") + ", the OLF's PSFs")
    out = [(default, base, False), ("patch 32", dataclasses.replace(base, patch=32), False),
           (f"pad {max(2, pad // 2)} px", dataclasses.replace(base, pad=max(2, pad // 2)), False),
           (f"pad {2 * pad} px", dataclasses.replace(base, pad=min(2 * pad, 512)), False)]
    out += [(f"weight {w:g}", dataclasses.replace(base, weight=w), False)
            for w in (base.weight / 3, base.weight * 3, base.weight * 10)]
    other = "hqs" if base.method == "wiener" else "wiener"
    out.append((f"method {other}", dataclasses.replace(base, method=other), False))
    if base.prior == "adaptive":       # the fixed prior's weight is on another scale: its former default
        out.append((f"prior fixed, weight {FIXED_PRIOR_WEIGHT:g}",
                    dataclasses.replace(base, prior="fixed", weight=FIXED_PRIOR_WEIGHT), False))
    out += [(f"layers {s:g} D", dataclasses.replace(base, layer_step_diopters=s), False) for s in (0.1, 0.2)]
    out.append(("noise given (the sensor's model)", dataclasses.replace(base, noise=NoiseModel.sensor(
        NOISE["full_well_electrons"], NOISE["read_noise_electrons"])), False))
    if traced:
        out.append(("traced PSFs", base, True))
    seen, kept = set(), []
    for label, opts, tr in out:                 # a variant equal to the default is the default's row
        if (opts, tr) not in seen:
            seen.add((opts, tr))
            kept.append((label, opts, tr))
    return kept


def sweep_frames(frames: list[Frame], quick: bool) -> dict[str, list[Frame]]:
    """{source: its 12.2 um frames the settings are measured on}: the first
    synthetic seed's and every data frame's (quick: one frame)."""
    crops = [f for f in frames if f.group == CROPS]
    first = crops[0].scene
    out = {}
    for f in crops:
        if f.source != SYNTHETIC or f.scene == first:
            out.setdefault(f.source, []).append(f)
    return {SYNTHETIC: crops[:1]} if quick else out


def sweep(lens, frames: list[Frame], traced: bool, log, quick: bool = False) -> dict:
    """{source: {variant: scores}} over the 12.2 um frames (``sweep_frames``)."""
    return {src: sweep_source(lens, fs, traced, log) for src, fs in sweep_frames(frames, quick).items()}


def sweep_source(lens, crops: list[Frame], traced: bool, log) -> dict:
    k = crops[0].library.kernel_size
    res = {}
    for label, opts, tr in variants(k, traced and crops[0].traced is not None):
        sc = Scores()
        for frame in crops:
            out, secs = timed(_deconv(lens, opts, tr), frame)
            sc.add(out, frame, {"all": ~np.isnan(frame.depth)}, highlights(frame.capture, k // 2), secs)
        res[label] = sc.result()
        log(f"    setting {label}: {res[label]['linear']['all']['psnr']} dB, "
            f"{res[label]['seconds_per_megapixel']['wall']} s/Mpx")
    return res


# ------------------------------------------------------------------ the report
def _picture(picture: dict, path: Path) -> str | None:
    from dcdi_core.io.images import write_image
    if not picture:
        return None
    frame = picture["frame"]
    names = ["capture", "deconvolution, depth per patch"] + (["DACN (shipped)"] if "DACN (shipped)" in picture
                                                             else [])
    panels = [picture[n] for n in names] + [frame.sharp]
    gap = np.ones((frame.sharp.shape[0], 4, 3), np.float32)
    strip = np.concatenate(sum(([np.clip(p, 0, 1).astype(np.float32), gap] for p in panels), [])[:-1], axis=1)
    write_image(path, strip)
    return f"{' | '.join(names + ['truth'])}: {frame.case}, {frame.scene}"


def lens_report(lens_id: str, options: ReportOptions, data_scenes, out: Path, log) -> dict:
    from dcdi_core.optics.lens import load_lens
    lens = load_lens(lens_id)
    libs = Libraries(lens)
    frames = all_frames(lens, libs, options, data_scenes, log)
    model, net_msg = load_network(lens.id, options.threads)
    rows, picture = score_methods(frames, methods(lens, model, options.traced), log)
    res = {"rows": rows, "simulation_seconds_per_megapixel": simulation_times(frames),
           "settings": sweep(lens, frames, options.traced, log, options.quick), "network": net_msg,
           "settings_frames": {src: [f"{f.case[len('12.2 um, '):]}, {f.scene}" for f in fs]
                               for src, fs in sweep_frames(frames, options.quick).items()},
           "psf_sources": {f"{k * 1000:.4g} um": m for k, m in libs.messages.items()},
           "kernel_px": {f"{k * 1000:.4g} um": lib.kernel_size for k, (lib, _) in libs.olf.items()},
           "frames": {c: [f.scene for f in frames if f.case == c] for c in dict.fromkeys(f.case for f in frames)}}
    res["picture"] = None
    if picture:
        name = f"correction-{lens.id}.jpg"
        res["picture"] = {"file": name, "shows": _picture(picture, out / name)}
    return res


def run_report(options: ReportOptions, out, log=print) -> dict:
    """Every lens's rows, the settings table and a picture each; writes
    report.md, results.json and the pictures to ``out``; returns the results."""
    from dcdi_core.optics.lens import load_lens
    for lens_id in options.lenses:               # bad ids and folders fail before any work
        load_lens(lens_id)
    data_scenes = load_data_scenes(options.data, options.frames)
    out = Path(out)
    results = {"options": {"lenses": list(options.lenses), "data": [str(d) for d in options.data],
                           "quick": options.quick, "seeds": list(options.seeds),
                           "crop_px": list(options.crop_px), "full_px": list(options.full_px),
                           "noise": NOISE, "cpus": os.cpu_count(), "load_average": round(os.getloadavg()[0], 2)},
               "lenses": {}}
    for lens_id in options.lenses:
        log(f"{lens_id}:")
        results["lenses"][lens_id] = lens_report(lens_id, options, data_scenes, out, log)
    write_text(out / "results.json", json.dumps(results, indent=1) + "\n")
    write_text(out / "report.md", markdown(results))
    return results


# ------------------------------------------------------------------ markdown
def _cell(s: dict, key: str = "psnr") -> str:
    v = s.get(key) if s else None
    return "-" if v is None else (f"{v:.2f}" if key == "psnr" else f"{v:.4f}")


def _pair(s: dict) -> str:
    return f"{_cell(s)} / {_cell(s, 'ssim')}" if s else "-"


def _method_names(rows: dict) -> list[str]:
    names = []
    for v in rows.values():
        names += [n for n in v if n not in names]
    return names


def summary_table(title: str, rows: dict) -> list[str]:
    cols = [c for c in rows if c.startswith("12.2 um,")] + [c for c in (CROPS, FULL) if c in rows]
    md = [f"| {title}: PSNR dB / SSIM, linear | " + " | ".join(cols) + " |", "|---|" + "---|" * len(cols)]
    for n in _method_names(rows):
        md.append(f"| {n} | " + " | ".join(_pair(rows[c].get(n, {}).get("linear", {}).get("all")) for c in cols)
                  + " |")
    return md


def views_table(title: str, v: dict, sim: dict | None) -> list[str]:
    md = [f"| {title} | " + " | ".join(VIEWS) + " | wall s / Mpx | CPU s / Mpx |",
          "|---|" + "---|" * (len(VIEWS) + 2)]
    for n in _method_names({0: v}):
        t = v[n]["seconds_per_megapixel"]
        md.append(f"| {n} | " + " | ".join(_pair(v[n][view].get("all")) for view in VIEWS)
                  + (f" | {t['wall']:.2f} | {t['cpu']:.2f} |" if t["wall"] else " | - | - |"))
    if sim:
        md.append("| (the simulation that made the captures) | " + " | ".join("" for _ in VIEWS)
                  + f" | {sim['wall']:.2f} | {sim['cpu']:.2f} |")
    return md


def band_table(title: str, v: dict, kind: str) -> list[str]:
    first = next(iter(v.values()))["linear"]
    bands = [r for r in first if r.startswith(kind + " ")]
    md = [f"| {title}, PSNR dB / SSIM (linear) | " + " | ".join(b[len(kind) + 1:] for b in bands) + " |",
          "|---|" + "---|" * len(bands)]
    for n in _method_names({0: v}):
        md.append(f"| {n} | " + " | ".join(_pair(v[n]["linear"].get(b)) for b in bands) + " |")
    total = max(first["all"]["pixels"], 1)
    md.append("| share of pixels | " + " | ".join(f"{100 * first[b]['pixels'] / total:.1f} %" for b in bands) + " |")
    return md


def settings_table(title: str, res: dict) -> list[str]:
    md = [f"| {title} | PSNR dB / SSIM linear | highlights masked | sRGB | wall s / Mpx | CPU s / Mpx |",
          "|---|---|---|---|---|---|"]
    for label, s in res.items():
        t = s["seconds_per_megapixel"]
        md.append(f"| {label} | {_pair(s['linear']['all'])} | {_pair(s['linear, highlights masked']['all'])} | "
                  f"{_pair(s['sRGB']['all'])} | {t['wall']:.2f} | {t['cpu']:.2f} |")
    return md


def source_section(lens_id: str, source: str, res: dict) -> list[str]:
    rows, sim = res["rows"][source], res["simulation_seconds_per_megapixel"].get(source, {})
    md = [f"### {lens_id}, {source}", ""] + summary_table(f"{lens_id}, {source}", rows) + [""]
    for group in (CROPS, FULL):
        if group in rows:
            title = f"{lens_id}, {source}, {group}"
            md += views_table(title, rows[group], sim.get(group)) + [""]
            md += band_table(title, rows[group], "depth") + [""] + band_table(title, rows[group], "field") + [""]
    if source in res["settings"]:
        md += ["Settings of the deconvolution, one changed at a time from the default (12.2 um crops: "
               + ", ".join(res["settings_frames"][source]) + "):", ""]
        md += settings_table(f"{lens_id}, {source}", res["settings"][source]) + [""]
    return md


def markdown(results: dict) -> str:
    o = results["options"]
    md = ["# Correction without training", "",
          f"Frames: the synthetic scene (seeds {', '.join(map(str, o['seeds']))}; {o['crop_px'][0]} x "
          f"{o['crop_px'][1]} crops at 12.2 um, {o['full_px'][0]} x {o['full_px'][1]} on the full sensor)"
          + (f" and the frames of {', '.join(o['data'])} (their own size)" if o["data"] else "")
          + f"; sensor noise: full well {o['noise']['full_well_electrons']:g} e-, read noise "
            f"{o['noise']['read_noise_electrons']:g} e-. {o['cpus']} CPU(s), load average {o['load_average']} "
            "at the start. Scores over the imaged pixels, pooled over the frames; times per megapixel of frame, "
            "the PSF bins computed beforehand.", ""]
    for lens_id, res in results["lenses"].items():
        md += [f"## {lens_id}", "", "PSF sources: " + "; ".join(f"{k}: {m}" for k, m in res["psf_sources"].items())
               + f". Network: {res['network']}.", ""]
        for source in res["rows"]:
            md += source_section(lens_id, source, res)
        if res.get("picture"):
            md += [f"![{res['picture']['shows']}]({res['picture']['file']})", ""]
    return "\n".join(md)
