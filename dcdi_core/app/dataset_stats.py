"""`dcdi dataset stats`: what the factory's frames hold, per scene recipe.

Frames. The finished samples (manifest records) of one or more factory
folders (``dataset.factory_folder``), grouped by their recipe across the
folders; at most ``frames`` a recipe, chosen evenly through them. Each
frame's all-in-focus image (aif/<id>.exr, linear RGB) and depth
(depth/<id>.exr, metres) are read once.

Measures (``dataset.statistics``, so that a recipe's author measures alike):

1. texture: the share of the luminance spectral energy above 0.1 cycles/px,
   pooled over a recipe's frames (energies summed), with the least and
   most of any frame;
2. depth mix: the share of pixels per depth band (0.7-1, 1-2, 2-5, 5-10,
   > 10 m, infinity included in the last), below 0.7 m, and with no valid
   depth (NaN, <= 0), and the 1-5 m share (indoor recipes aim at >= 60 %);
3. clipping: the share of pixels whose brightest channel exceeds 1.0,
   pooled and the worst frame's;
4. blur: the share of 128 x 128 crops whose capture is already above 40 dB
   PSNR for each lens at the paper's pitch. Each frame is placed as a crop
   of the paper's 1280 x 1920 sensor at 12.2 um, at a seeded random
   position (one per frame, the same for every lens), so that the frames
   cover every field between them; it is simulated by
   ``render.simulate.LensSimulator`` with the PSFs the source rule picks
   (``psf.rule``; every bin built at once but a trace's), without sensor noise: the measure is the blur's
   (and the distortion's resampling), not the sensor's. PSNR (data range
   1) of the capture against its aligned sharp target (the simulator's
   ``sharp``), both linear and clipped to [0, 1], over a grid of
   non-overlapping crops centred on the usable pixels. Usable: farther
   than the kernel's radius from any pixel the lens does not image (the
   distortion leaves a crop's border and outer corner dark) or with no
   valid depth, for the blur spreads that black into its neighbours,
   which says nothing of the lens; a crop of the grid holding an unusable
   pixel is skipped and counted. A frame larger than the sensor is
   skipped and named.

Outputs: report.md (a row per recipe), results.json (every number, per
frame too) and a picture per recipe (<recipe>.jpg: sample frames in sRGB
above, their depth below on one log scale 0.7-10 m).
"""
from __future__ import annotations

import dataclasses
import json
import math
import os
import time
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from ..atomic import atomic_path, read_back_picture, write_text
from ..dataset import factory_folder as ff
from ..dataset.statistics import (DEPTH_BANDS_M, HIGH_FREQUENCY_CYCLES_PER_PX, clipped_mask, depth_band_counts,
                                  spectral_energy)
from ..errors import DatasetError, InputRangeError
from ..render.geometry import ImageGeometry
from ..render.simulate import LensSimulator, SimulateOptions
from ..render.base import check_within_sensor

PAPER_PITCH_MM = 0.0122              # the paper's pixel pitch
SENSOR_PX = (1280, 1920)              # the paper's sensor at 12.2 um
INDOOR_BAND_M = (1.0, 5.0)            # the depth range indoor recipes should mostly fill
PICTURE_MAX_BYTES = 300_000
PICTURE_PANEL_PX = 320                # width of one frame in the picture
PICTURE_DEPTH_M = (0.7, 10.0)         # the depth colour map's log scale


def band_name(lo: float, hi: float, unit: str = " m") -> str:
    return f"> {lo:g}{unit}" if math.isinf(hi) else f"{lo:g}-{hi:g}{unit}"


@dataclass(frozen=True)
class DatasetReportOptions:
    """What the report measures (checked when made).

    lenses: lens ids for the blur measure. frames: at most this many frames
    a recipe, chosen evenly (None: all). seed: the frames' random positions
    on the sensor. crop_px: the side of the PSNR crops (pixels). psnr_db:
    the threshold a crop's capture must pass. pictures: sample frames in a
    recipe's picture (0: no pictures)."""

    lenses: tuple = ("mos-s1", "mos-s2")
    frames: int | None = None
    seed: int = 0
    crop_px: int = 128
    psnr_db: float = 40.0
    pictures: int = 6

    def __post_init__(self):
        if not self.lenses:
            raise InputRangeError("--lens", "none", "one or more lens ids, e.g. mos-s1")
        if self.frames is not None and not (_is_int(self.frames) and self.frames >= 1):
            raise InputRangeError("--frames", self.frames, "an integer >= 1 (frames per recipe), or none for all")
        if not _is_int(self.seed):
            raise InputRangeError("--seed", self.seed, "an integer")
        if not (_is_int(self.crop_px) and 2 <= self.crop_px <= min(SENSOR_PX)):
            raise InputRangeError("crop size", self.crop_px, f"an integer in [2, {min(SENSOR_PX)}] px")
        if not (isinstance(self.psnr_db, (int, float)) and math.isfinite(self.psnr_db) and self.psnr_db > 0):
            raise InputRangeError("PSNR threshold", self.psnr_db, "a finite number of dB > 0")
        if not (_is_int(self.pictures) and 0 <= self.pictures <= 12):
            raise InputRangeError("pictures", self.pictures, "an integer in [0, 12] frames a recipe")


def _is_int(v) -> bool:
    return isinstance(v, (int, np.integer)) and not isinstance(v, bool)


# ------------------------------------------------------------------ frames
@dataclass(frozen=True)
class FrameRef:
    """One finished sample of a factory folder."""

    layout: ff.FolderLayout
    sid: str
    recipe: str
    folder_name: str = ""      # how the report names its folder (default: the folder's name)

    @property
    def label(self) -> str:
        return f"{self.folder_name or self.layout.root.name}/{self.sid}"


def _recipe_of(record: dict, manifest: Path) -> str:
    recipe = record.get("recipe")
    if isinstance(recipe, str) and recipe:
        return recipe
    try:
        return ff.parse_sample_id(record["id"])[0]
    except ValueError:
        raise DatasetError(f"{manifest}: record {record['id']!r} has no \"recipe\" and its id is not "
                           "<recipe>-<index>") from None


def folder_frames(folder) -> list[FrameRef]:
    """The finished samples of one factory folder, in id order; a folder that
    is not a factory folder, or has none, is refused (DatasetError)."""
    root = Path(folder)
    if not root.is_dir():
        raise DatasetError(f"{root}: not a folder (a factory folder holds {ff.MANIFEST}, aif/ and depth/)")
    if not ff.is_factory_folder(root):
        raise DatasetError(f"{root}: not a factory folder (no {ff.MANIFEST}; make one with "
                           "`python -m blender_addon.factory`)")
    layout = ff.FolderLayout(root)
    records = ff.finished_samples(root)
    if not records:
        raise DatasetError(f"{layout.manifest}: no finished frames (the manifest holds no complete record)")
    return [FrameRef(layout, sid, _recipe_of(rec, layout.manifest)) for sid, rec in sorted(records.items())]


def evenly(items: list, n: int | None) -> list:
    """At most ``n`` of ``items``, spread evenly from the first to the last."""
    if n is None or len(items) <= n:
        return list(items)
    if n == 1:
        return [items[0]]
    return [items[round(i * (len(items) - 1) / (n - 1))] for i in range(n)]


def recipe_frames(folders, frames: int | None) -> dict[str, list[FrameRef]]:
    """{recipe: its frames} over every folder (recipes in name order), each
    at most ``frames`` long; every chosen frame's files checked to exist."""
    if not folders:
        raise InputRangeError("DIR", None, "one or more factory folders")
    seen = {}
    for folder in folders:
        key = Path(folder).resolve()
        if key in seen:
            raise DatasetError(f"{folder}: given twice (also as {seen[key]}); give each factory folder once")
        seen[key] = str(folder)
    names = [Path(f).name for f in folders]
    by_recipe: dict[str, list[FrameRef]] = {}
    for folder, name in zip(folders, names):
        # two folders of one name are told apart by their paths as given
        shown = name if names.count(name) == 1 else str(folder)
        for ref in folder_frames(folder):
            by_recipe.setdefault(ref.recipe, []).append(dataclasses.replace(ref, folder_name=shown))
    chosen = {r: evenly(by_recipe[r], frames) for r in sorted(by_recipe)}
    for refs in chosen.values():
        for ref in refs:
            for path in (ref.layout.aif(ref.sid), ref.layout.depth(ref.sid)):
                if not path.is_file():
                    raise DatasetError(f"{path}: missing (the manifest lists {ref.sid} as finished)")
    return chosen


# ------------------------------------------------------------------ image statistics
def frame_statistics(image: np.ndarray, depth: np.ndarray) -> dict:
    """Sums of one frame that pool over frames: spectral energy above the
    cutoff and in all, pixels per depth band, below the first band, with no
    valid depth, and clipped."""
    high, total = spectral_energy(image)
    d = np.asarray(depth, np.float64)
    invalid = int(np.count_nonzero(~(d > 0)))              # NaN compares False
    below = int(np.count_nonzero((d > 0) & (d < DEPTH_BANDS_M[0][0])))
    return {"pixels": int(d.size), "hf_energy": high, "energy": total,
            "bands": depth_band_counts(d).tolist(), "below_first_band": below, "invalid_depth": invalid,
            "clipped": int(np.count_nonzero(clipped_mask(image)))}


def _share(num: float, den: float):
    return num / den if den > 0 else None


def _hf_share(high: float, total: float) -> float:
    """A flat image has no energy, and none of it high: 0 (as ``statistics.high_frequency_share``)."""
    return high / total if total > 0 else 0.0


# ------------------------------------------------------------------ blur on the sensor
def fits_sensor(h: int, w: int) -> bool:
    return h <= SENSOR_PX[0] and w <= SENSOR_PX[1]


def sensor_position(h: int, w: int, seed: int, label: str) -> tuple[int, int]:
    """(top row, left column) of an h x w frame on the 1280 x 1920 sensor,
    uniform over the places it fits; seeded by ``seed`` and the frame's
    label, so that a frame keeps its place whichever others are chosen."""
    rng = np.random.default_rng([seed & 0xFFFFFFFF, zlib.crc32(label.encode("utf-8"))])
    return int(rng.integers(0, SENSOR_PX[0] - h + 1)), int(rng.integers(0, SENSOR_PX[1] - w + 1))


def placed_geometry(lens, h: int, w: int, top_left: tuple[int, int]) -> ImageGeometry:
    """The geometry of an h x w crop of the sensor at 12.2 um whose top-left
    pixel is sensor pixel ``top_left`` (refused if it leaves the sensor)."""
    if not fits_sensor(h, w):
        raise InputRangeError("frame size at 12.2 um", (h, w), f"at most {SENSOR_PX[0]} x {SENSOR_PX[1]} px "
                                                              "(the sensor)")
    r0, c0 = top_left
    centre = ((SENSOR_PX[0] - 1) / 2 - r0, (SENSOR_PX[1] - 1) / 2 - c0)
    geom = ImageGeometry.from_pixel_pitch(lens, h, w, PAPER_PITCH_MM, center_px=centre)
    check_within_sensor(geom, f"the crop at sensor pixel {top_left}")
    return geom


def near(mask: np.ndarray, radius: int) -> np.ndarray:
    """Pixels within ``radius`` px (a square) of a True pixel of ``mask``."""
    if radius <= 0 or not mask.any():
        return mask.copy()
    s = np.pad(np.cumsum(np.cumsum(mask.astype(np.int64), 0), 1), ((1, 0), (1, 0)))
    h, w = mask.shape
    r0, r1 = np.clip(np.arange(h) - radius, 0, h), np.clip(np.arange(h) + radius + 1, 0, h)
    c0, c1 = np.clip(np.arange(w) - radius, 0, w), np.clip(np.arange(w) + radius + 1, 0, w)
    return (s[r1][:, c1] - s[r0][:, c1] - s[r1][:, c0] + s[r0][:, c0]) > 0


def crop_grid(usable: np.ndarray, crop: int) -> tuple[int, int, int, int]:
    """(top row, left column, rows, columns) of the grid of crop x crop
    squares that fits the bounding box of the ``usable`` pixels, centred in
    it (the distortion leaves a crop's border unimaged: a grid from the
    frame's corner would lose a row and a column of crops to it)."""
    rows, cols = np.flatnonzero(usable.any(axis=1)), np.flatnonzero(usable.any(axis=0))
    if rows.size == 0:
        return 0, 0, 0, 0
    out = []
    for idx in (rows, cols):
        span = int(idx[-1] - idx[0] + 1)
        out.append((int(idx[0]) + (span % crop) // 2, span // crop))
    (r0, nr), (c0, nc) = out
    return r0, c0, nr, nc


def crop_psnr(capture: np.ndarray, sharp: np.ndarray, usable: np.ndarray, crop: int) -> tuple[np.ndarray, int]:
    """(PSNR dB of each usable crop, crops skipped): the grid of
    non-overlapping crop x crop squares of :func:`crop_grid`; a crop with
    any pixel not ``usable`` is skipped. Images linear, clipped to [0, 1],
    data range 1; an exact crop scores inf."""
    r0, c0, nr, nc = crop_grid(usable, crop)
    if nr == 0 or nc == 0:
        return np.zeros(0), 0
    rs, cs = slice(r0, r0 + nr * crop), slice(c0, c0 + nc * crop)
    a = np.clip(np.asarray(capture[rs, cs], np.float64), 0.0, 1.0)
    b = np.clip(np.asarray(sharp[rs, cs], np.float64), 0.0, 1.0)
    err = ((a - b) ** 2).sum(axis=2).reshape(nr, crop, nc, crop).sum(axis=(1, 3)) / (3 * crop * crop)
    ok = usable[rs, cs].reshape(nr, crop, nc, crop).all(axis=(1, 3))
    with np.errstate(divide="ignore"):
        psnr = 10.0 * np.log10(1.0 / err[ok])
    return psnr, int((~ok).sum())


class LensBlur:
    """One lens's simulation at 12.2 um: its PSF library built once per
    pixel pitch, a frame simulated without noise."""

    def __init__(self, lens_id: str):
        from ..optics.lens import load_lens
        self.lens = load_lens(lens_id)
        self.libraries = {}                     # pixel pitch: (library, the PSF source's message)
        self.psf_source = None

    def library(self, geometry: ImageGeometry):
        """(library, message) of ``geometry``'s pitch by the source rule
        (``psf.rule``): every bin built now (cheap) but a trace's, made as
        the frames need them."""
        key = round(geometry.pixel_pitch_mm, 9)
        if key not in self.libraries:
            from . import PSFRequest, open_source
            src = open_source(self.lens, geometry, PSFRequest(fit_kernel=False))
            if src.kind != "trace":
                src.library.build()
            self.libraries[key] = (src.library, src.message)
        return self.libraries[key]

    def measure(self, image, depth, top_left, crop: int) -> dict:
        """PSNR of the crops of one frame placed at ``top_left``, and the
        fields its corners and centre reach."""
        h, w = depth.shape
        geom = placed_geometry(self.lens, h, w, top_left)
        lib, self.psf_source = self.library(geom)
        r = LensSimulator(self.lens, SimulateOptions(geometry=geom), library=lib)(image, depth)
        # the blur spreads the unimaged pixels' black into their neighbours (the target has none of it):
        # a crop within the kernel's reach of them measures the crop's edge, not the lens
        unusable = near(~(r.depth > 0), lib.kernel_size // 2)          # NaN: not imaged
        psnr, skipped = crop_psnr(r.image, r.sharp, ~unusable, crop)
        return {"psnr_db": psnr, "skipped_crops": skipped,
                "field_centre": round(float(geom.field((h - 1) / 2, (w - 1) / 2)), 4),
                "field_max": round(geom.max_field, 4)}


# ------------------------------------------------------------------ one recipe
@dataclass
class RecipeSums:
    """A recipe's pooled sums and its per-frame rows."""

    frames: list = field(default_factory=list)
    pixels: int = 0
    hf_energy: float = 0.0
    energy: float = 0.0
    bands: np.ndarray = field(default_factory=lambda: np.zeros(len(DEPTH_BANDS_M), np.int64))
    below: int = 0
    invalid: int = 0
    clipped: int = 0
    crops: dict = field(default_factory=dict)        # lens: list of crop PSNRs
    skipped_crops: dict = field(default_factory=dict)
    too_large: list = field(default_factory=list)
    samples: list = field(default_factory=list)      # (label, image, depth) of the picture's frames

    def add(self, stats: dict) -> None:
        self.pixels += stats["pixels"]
        self.hf_energy += stats["hf_energy"]
        self.energy += stats["energy"]
        self.bands += np.asarray(stats["bands"], np.int64)
        self.below += stats["below_first_band"]
        self.invalid += stats["invalid_depth"]
        self.clipped += stats["clipped"]

    def add_crops(self, lens_id: str, psnr: np.ndarray, skipped: int) -> None:
        self.crops.setdefault(lens_id, []).extend(float(v) for v in psnr)
        self.skipped_crops[lens_id] = self.skipped_crops.get(lens_id, 0) + skipped

    def result(self, lenses, psnr_db: float) -> dict:
        hf = [f["hf_share"] for f in self.frames]
        clip = [(f["clipped_fraction"], f["frame"]) for f in self.frames]
        worst = max(clip)
        bands = {band_name(lo, hi): _share(int(n), self.pixels) for (lo, hi), n in zip(DEPTH_BANDS_M, self.bands)}
        lo_i, hi_i = (next(i for i, (lo, _) in enumerate(DEPTH_BANDS_M) if lo == b) for b in INDOOR_BAND_M)
        blur = {lens_id: crop_summary(self.crops.get(lens_id, []), self.skipped_crops.get(lens_id, 0), psnr_db)
                for lens_id in lenses}
        return {"frames": len(self.frames),
                "hf_share": {"pooled": _hf_share(self.hf_energy, self.energy), "min": min(hf), "max": max(hf)},
                "depth_shares": bands,
                "depth_below_first_band": _share(self.below, self.pixels),
                "depth_invalid": _share(self.invalid, self.pixels),
                "depth_1_5_m": _share(int(self.bands[lo_i:hi_i].sum()), self.pixels),
                "clipped": {"pooled": _share(self.clipped, self.pixels), "worst": worst[0], "worst_frame": worst[1]},
                "crops_above": blur, "frames_too_large_for_sensor": list(self.too_large),
                "frame_rows": self.frames}


def _finite(v):
    v = float(v)
    return round(v, 4) if math.isfinite(v) else ("inf" if v > 0 else None)


def crop_summary(psnr_db, skipped: int, threshold_db: float) -> dict:
    """Crops measured and above ``threshold_db``, their share and median PSNR, crops skipped."""
    v = np.asarray(psnr_db, np.float64)
    above = int((v > threshold_db).sum())
    return {"crops": int(v.size), "crops_above": above, "share_above": _share(above, v.size),
            "median_psnr_db": _finite(np.median(v)) if v.size else None, "skipped_crops": int(skipped)}


def statistics_row(label: str, shape, stats: dict) -> dict:
    """One frame's shares (0-1) from :func:`frame_statistics`."""
    n = stats["pixels"]
    return {"frame": label, "size": list(shape), "hf_share": _hf_share(stats["hf_energy"], stats["energy"]),
            "clipped_fraction": stats["clipped"] / n,
            "depth_shares": {band_name(lo, hi): c / n for (lo, hi), c in zip(DEPTH_BANDS_M, stats["bands"])},
            "depth_below_first_band": stats["below_first_band"] / n, "depth_invalid": stats["invalid_depth"] / n}


def blur_rows(image, depth, label: str, blurs: list[LensBlur], options: DatasetReportOptions,
              sums: "RecipeSums") -> tuple[list | None, dict]:
    """(the frame's top-left pixel on the sensor, {lens: its crops}); the
    crops' PSNRs also go to ``sums``. (None, {}) for a frame larger than
    the sensor."""
    h, w = depth.shape
    if not fits_sensor(h, w):
        return None, {}
    top_left = sensor_position(h, w, options.seed, label)
    rows = {}
    for blur in blurs:
        m = blur.measure(image, depth, top_left, options.crop_px)
        sums.add_crops(blur.lens.id, m["psnr_db"], m["skipped_crops"])
        rows[blur.lens.id] = dict(crop_summary(m["psnr_db"], m["skipped_crops"], options.psnr_db),
                                  field_centre=m["field_centre"], field_max=m["field_max"])
    return list(top_left), rows


def _progress(recipe: str, k: int, n: int, row: dict, threshold_db: float, seconds: float) -> str:
    crops = "".join(f", {lid} {r['crops_above']}/{r['crops']} crops > {threshold_db:g} dB"
                    for lid, r in row["lenses"].items())
    if row["sensor_top_left"] is None:
        crops = ", larger than the sensor: no blur measure"
    return (f"  {recipe} {k + 1}/{n} {row['frame']}: HF {100 * row['hf_share']:.1f} %, clipped "
            f"{100 * row['clipped_fraction']:.2f} %{crops} ({seconds:.1f} s)")


def measure_recipe(recipe: str, refs: list[FrameRef], blurs: list[LensBlur], options: DatasetReportOptions,
                   log: Callable) -> RecipeSums:
    """Every measure of one recipe's frames, read one at a time."""
    sums = RecipeSums()
    picture_labels = {r.label for r in evenly(refs, options.pictures)} if options.pictures else set()
    for k, ref in enumerate(refs):
        t = time.perf_counter()
        image, depth = ff.read_rgbd(ref.layout, ref.sid)
        stats = frame_statistics(image, depth)
        sums.add(stats)
        row = statistics_row(ref.label, depth.shape, stats)
        row["sensor_top_left"], row["lenses"] = blur_rows(image, depth, ref.label, blurs, options, sums)
        if row["sensor_top_left"] is None:
            sums.too_large.append(ref.label)
        sums.frames.append(row)
        if ref.label in picture_labels:
            sums.samples.append((ref.label, *_thumbnail(image, depth)))
        log(_progress(recipe, k, len(refs), row, options.psnr_db, time.perf_counter() - t))
    return sums


# ------------------------------------------------------------------ pictures
def _thumbnail(image: np.ndarray, depth: np.ndarray):
    """(sRGB image, depth) at most PICTURE_PANEL_PX wide: whole-pixel steps
    (the depth by its samples, a blend of two depths is no depth)."""
    from ..io.images import linear_to_srgb
    step = max(1, math.ceil(depth.shape[1] / PICTURE_PANEL_PX))
    img = np.clip(linear_to_srgb(np.clip(image[::step, ::step], 0.0, 1.0)), 0.0, 1.0).astype(np.float32)
    return img, np.asarray(depth[::step, ::step], np.float32)


def write_picture(path: Path, recipe: str, samples: list) -> None:
    """Sample frames in sRGB above, their depth below on one log colour scale
    (0.7-10 m; farther and infinity: the scale's top colour, white beyond;
    no valid depth: black), as a JPEG under PICTURE_MAX_BYTES."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import LogNorm

    n = len(samples)
    cmap = plt.get_cmap("viridis").with_extremes(over="white", under="magenta", bad="black")
    norm = LogNorm(*PICTURE_DEPTH_M)
    aspect = max(s[2].shape[0] / s[2].shape[1] for s in samples)
    fig = plt.figure(figsize=(2.6 * n + 0.8, 2 * 2.6 * aspect + 0.45))
    grid = fig.add_gridspec(2, n + 1, width_ratios=[1.0] * n + [0.07], wspace=0.04, hspace=0.04,
                            left=0.01, right=0.92, bottom=0.01, top=1 - 0.45 / (2 * 2.6 * aspect + 0.45))
    for j, (label, img, dep) in enumerate(samples):
        top, bottom = fig.add_subplot(grid[0, j]), fig.add_subplot(grid[1, j])
        top.imshow(img, interpolation="nearest")
        d = np.where(dep > 0, dep, np.nan)                       # NaN, 0 and negative: no depth
        im = bottom.imshow(np.ma.masked_invalid(d), cmap=cmap, norm=norm, interpolation="nearest")
        top.set_title(label, fontsize=7)
        top.set_axis_off()
        bottom.set_axis_off()
    bar = fig.colorbar(im, cax=fig.add_subplot(grid[1, n]), extend="both")
    ticks = [0.7, 1, 2, 5, 10]
    bar.set_ticks(ticks, labels=[f"{t:g}" for t in ticks])
    bar.minorticks_off()
    bar.set_label("depth (m)", fontsize=7)
    bar.ax.tick_params(labelsize=7)
    fig.suptitle(f"{recipe}: all-in-focus (sRGB) above, depth below", fontsize=9, y=0.995)
    try:
        for quality in (85, 70, 55, 40):            # a textured frame compresses worse: the size bound holds
            with atomic_path(path) as tmp:
                fig.savefig(tmp, dpi=100, format="jpeg", pil_kwargs={"quality": quality})
                read_back_picture(tmp, path)
            if path.stat().st_size <= PICTURE_MAX_BYTES:
                break
    finally:
        plt.close(fig)


# ------------------------------------------------------------------ the report
def run_report(folders, options: DatasetReportOptions, out, log: Callable = print) -> dict:
    """Every recipe's measures over the factory ``folders``; writes
    report.md, results.json and a picture per recipe to ``out``; returns
    the results. Bad folders and lens ids fail before any work."""
    chosen = recipe_frames(folders, options.frames)
    blurs = [LensBlur(lens_id) for lens_id in options.lenses]
    out = Path(out)
    t, c = time.perf_counter(), time.process_time()
    recipes = {}
    for recipe, refs in chosen.items():
        log(f"{recipe}: {len(refs)} frame(s)")
        sums = measure_recipe(recipe, refs, blurs, options, log)
        recipes[recipe] = sums.result(options.lenses, options.psnr_db)
        recipes[recipe]["picture"] = None
        if sums.samples:
            name = f"{recipe}.jpg"
            write_picture(out / name, recipe, sums.samples)
            recipes[recipe]["picture"] = {"file": name, "frames": [s[0] for s in sums.samples]}
    results = {"options": {"folders": [str(f) for f in folders], "lenses": list(options.lenses),
                           "frames_per_recipe": options.frames, "seed": options.seed, "crop_px": options.crop_px,
                           "psnr_threshold_db": options.psnr_db,
                           "hf_cutoff_cycles_per_px": HIGH_FREQUENCY_CYCLES_PER_PX,
                           "sensor_px": list(SENSOR_PX), "pixel_pitch_um": PAPER_PITCH_MM * 1000, "noise": "none"},
               "psf_sources": {b.lens.id: b.psf_source for b in blurs},
               "recipes": recipes,
               "seconds": {"wall": round(time.perf_counter() - t, 2), "cpu": round(time.process_time() - c, 2),
                           "cpus": os.cpu_count()}}
    write_text(out / "results.json", json.dumps(results, indent=1) + "\n")
    write_text(out / "report.md", markdown(results))
    return results


def _pct(v, digits: int = 1) -> str:
    return "-" if v is None else f"{100 * v:.{digits}f}"


def markdown(results: dict) -> str:
    o = results["options"]
    lenses = o["lenses"]
    bands = [band_name(lo, hi) for lo, hi in DEPTH_BANDS_M]
    head = (["recipe", "frames", "HF share % (min-max)", "clipped % (worst)"] + [f"{b} %" for b in bands]
            + ["< 0.7 m / no depth %", "1-5 m %"] + [f"crops > {o['psnr_threshold_db']:g} dB, {lid} %"
                                                     for lid in lenses])
    md = ["# What the data set's frames hold", "",
          f"Folders: {', '.join(o['folders'])}; "
          + ("every frame" if o["frames_per_recipe"] is None else f"at most {o['frames_per_recipe']} frames")
          + " a recipe (chosen evenly).", "",
          "HF share: the all-in-focus luminance's spectral energy above "
          f"{o['hf_cutoff_cycles_per_px']:g} cycles/px (Hann window), pooled over the frames, with the least and "
          "most of one frame. Clipped: pixels whose brightest channel exceeds 1.0, pooled, and the worst frame. "
          "Depth: shares of all pixels (> 10 m includes infinity; the pictures' colour scale is log 0.7-10 m, "
          "farther white, nearer magenta, no depth black). The recipes aim at an HF share >= 10 %, <= 0.5 % "
          "clipped, and (indoor) >= 60 % of pixels at 1-5 m.", "",
          f"Crops > {o['psnr_threshold_db']:g} dB: each frame placed as a crop of the {o['sensor_px'][0]} x "
          f"{o['sensor_px'][1]} sensor at {o['pixel_pitch_um']:g} um (a random place per frame, seed {o['seed']}, "
          f"the same for every lens), simulated without sensor noise (the measure is the lens's blur, not the "
          f"sensor's); the share of its {o['crop_px']} x {o['crop_px']} crops whose capture is already above "
          f"{o['psnr_threshold_db']:g} dB PSNR against the sharp target (linear, clipped to [0, 1]). The grid of crops "
          "is centred on the usable pixels: those farther than the kernel's radius from a pixel the lens does not "
          "image (the distortion leaves a frame's border and outer corner dark; the blur would spread that black) "
          "or with no depth; crops holding others are skipped.", "",
          "| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
    for recipe, r in results["recipes"].items():
        hf, cl = r["hf_share"], r["clipped"]
        cells = [recipe, str(r["frames"]), f"{_pct(hf['pooled'])} ({_pct(hf['min'])}-{_pct(hf['max'])})",
                 f"{_pct(cl['pooled'], 2)} ({_pct(cl['worst'], 2)})"]
        cells += [_pct(r["depth_shares"][b]) for b in bands]
        cells += [f"{_pct(r['depth_below_first_band'])} / {_pct(r['depth_invalid'])}", _pct(r["depth_1_5_m"])]
        for lid in lenses:
            b = r["crops_above"][lid]
            cells.append(f"{_pct(b['share_above'])} (of {b['crops']})")
        md.append("| " + " | ".join(cells) + " |")
    md.append("")
    for recipe, r in results["recipes"].items():
        if r["frames_too_large_for_sensor"]:
            md += [f"{recipe}: larger than the sensor, no blur measure: {', '.join(r['frames_too_large_for_sensor'])}.",
                   ""]
        skipped = {lid: r["crops_above"][lid]["skipped_crops"] for lid in lenses}
        if any(skipped.values()):
            md += [f"{recipe}: crops skipped (near pixels not imaged): "
                   + ", ".join(f"{lid} {n}" for lid, n in skipped.items()) + ".", ""]
    md += ["PSF sources: " + "; ".join(f"{lid}: {m}" for lid, m in results["psf_sources"].items()) + ".", ""]
    for recipe, r in results["recipes"].items():
        if r["picture"]:
            md += [f"![{recipe}: {', '.join(r['picture']['frames'])}]({r['picture']['file']})", ""]
    s = results["seconds"]
    md += [f"Measured in {s['wall']:.0f} s wall, {s['cpu']:.0f} s CPU ({s['cpus']} CPU(s)).", ""]
    return "\n".join(md)
