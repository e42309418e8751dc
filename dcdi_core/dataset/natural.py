"""Textures with the statistics of photographs, in numpy: for training and
judging what must hold on real pictures without leaning on one look.

A texture is built in log luminance and two colour-opponent axes, the way
natural images vary (luminance carries most of the variance; chromatic
contrast is a fraction of it, Ruderman et al. 1998):

* **spectrum**: random-phase noise whose power falls as ``1 / |f| ** slope``,
  the slope drawn per texture in ``slope_range`` (photographs: about 1.6 to
  3 about a mean of 2; van der Schaaf and van Hateren 1996);
* **edges**: occluding patches (ellipses, rectangles, half planes) of
  power-law sizes, each its own brightness and colour, mixed in with a
  drawn weight: their steps line up in phase across scales as an object's
  outline does, which random-phase noise never does;
* **contrast**: the log luminance's spread drawn log-uniform in
  ``contrast_range`` (near-flat walls and skies to foliage);
* **colour**: a base reflectance drawn from materials a camera meets
  (foliage, bark, soil, brick, concrete, sky, skin, paint), jittered, and
  opponent variations of ``chroma_share`` times the luminance's.

Linear RGB in [0, 1] (highlights clip, as in photographs). Everything is
drawn from one ``numpy.random.Generator``: the same seed gives the same
bytes. ``write_textures`` puts a seeded set in a folder, as PNGs, for any
``--textures DIR`` (the factory's and the dead-leaves recipe's).
"""
from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from ..errors import DcdiError, InputRangeError

# linear-RGB reflectances of surfaces a camera meets (approximate, sRGB primaries)
MATERIALS = np.array([
    (0.05, 0.09, 0.03),   # foliage
    (0.11, 0.07, 0.04),   # bark, soil
    (0.30, 0.10, 0.06),   # brick
    (0.28, 0.27, 0.25),   # concrete, stone
    (0.36, 0.50, 0.78),   # sky
    (0.48, 0.30, 0.22),   # skin
    (0.40, 0.24, 0.11),   # wood
    (0.72, 0.71, 0.68),   # white paint, paper
    (0.03, 0.03, 0.035),  # dark cloth, asphalt
    (0.20, 0.22, 0.12),   # dry grass
])


@dataclass(frozen=True)
class NaturalTextureOptions:
    """What :func:`natural_texture` draws from; every field checked when made.
    slope_range: the power spectrum's exponent (1 / |f| ** slope), uniform in
    it; contrast_range: the log luminance's standard deviation (natural log
    units), log-uniform in it; edge_share_range: the weight of the occluding
    patches against the noise, uniform; patches: how many; chroma_share: the
    opponent axes' spread over the luminance's, uniform in it;
    saturated_share: the share of textures whose base colour is drawn
    anywhere in the RGB cube rather than from ``MATERIALS``."""
    slope_range: tuple = (1.6, 3.0)
    contrast_range: tuple = (0.05, 0.9)
    edge_share_range: tuple = (0.0, 0.8)
    patches: int = 40
    chroma_share: tuple = (0.05, 0.4)
    saturated_share: float = 0.15

    def __post_init__(self):
        for name, lo, hi in (("slope_range", 0.5, 4.0), ("contrast_range", 1e-3, 3.0),
                             ("edge_share_range", 0.0, 1.0), ("chroma_share", 0.0, 2.0)):
            v = getattr(self, name)
            try:
                a, b = (float(x) for x in v)
            except (TypeError, ValueError):
                raise InputRangeError(f"NaturalTextureOptions.{name}", v, f"two numbers {lo:g} <= low <= high <= {hi:g}")
            if not (math.isfinite(a) and math.isfinite(b) and lo <= a <= b <= hi):
                raise InputRangeError(f"NaturalTextureOptions.{name}", v, f"two numbers {lo:g} <= low <= high <= {hi:g}")
        if isinstance(self.patches, bool) or not isinstance(self.patches, int) or not 0 <= self.patches <= 1000:
            raise InputRangeError("NaturalTextureOptions.patches", self.patches, "an integer 0 to 1000")
        s = self.saturated_share
        if isinstance(s, bool) or not isinstance(s, (int, float)) or not 0.0 <= s <= 1.0:
            raise InputRangeError("NaturalTextureOptions.saturated_share", s, "a number 0 to 1")


def power_law_noise(rng, size: int, slope: float) -> np.ndarray:
    """(size, size) float64, zero mean, unit spread: random phases, power
    ``1 / |f| ** slope`` (|f| floored at one cycle per texture), periodic."""
    fy = np.fft.fftfreq(size)[:, None]
    fx = np.fft.rfftfreq(size)[None, :]
    f = np.maximum(np.hypot(fy, fx), 1.0 / size)
    amp = f ** (-slope / 2.0)
    amp[0, 0] = 0.0
    spec = amp * (rng.standard_normal(amp.shape) + 1j * rng.standard_normal(amp.shape))
    x = np.fft.irfft2(spec, (size, size))
    return (x - x.mean()) / max(x.std(), 1e-12)


def _patches(rng, size: int, count: int) -> np.ndarray:
    """Occluding patches, the later on top: the index map (size, size) int32
    of the patch at each pixel, -1 where none. Radii log-uniform from 2 % to
    60 % of the side."""
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float64)
    index = np.full((size, size), -1, np.int32)
    for k in range(count):
        cy, cx = rng.uniform(0, size, 2)
        r = size * math.exp(rng.uniform(math.log(0.02), math.log(0.6)))
        kind = rng.integers(3)
        if kind == 0:                                   # ellipse, turned
            t = rng.uniform(0, math.pi)
            a, b = r, r * rng.uniform(0.3, 1.0)
            u = (xx - cx) * math.cos(t) + (yy - cy) * math.sin(t)
            v = -(xx - cx) * math.sin(t) + (yy - cy) * math.cos(t)
            inside = (u / a) ** 2 + (v / b) ** 2 <= 1.0
        elif kind == 1:                                 # rectangle, turned
            t = rng.uniform(0, math.pi)
            a, b = r, r * rng.uniform(0.2, 1.0)
            u = (xx - cx) * math.cos(t) + (yy - cy) * math.sin(t)
            v = -(xx - cx) * math.sin(t) + (yy - cy) * math.cos(t)
            inside = (np.abs(u) <= a) & (np.abs(v) <= b)
        else:                                           # half plane through the point
            t = rng.uniform(0, 2 * math.pi)
            inside = (xx - cx) * math.cos(t) + (yy - cy) * math.sin(t) > 0
        index[inside] = k
    return index


def natural_texture(rng, size: int = 512, options: NaturalTextureOptions = NaturalTextureOptions()) -> np.ndarray:
    """One texture (size, size, 3) float32, linear RGB in [0, 1] (module docstring)."""
    if isinstance(size, bool) or not isinstance(size, (int, np.integer)) or not 16 <= size <= 8192:
        raise InputRangeError("texture size", size, "an integer 16 to 8192 px")
    o = options
    slope = rng.uniform(*o.slope_range)
    contrast = math.exp(rng.uniform(math.log(o.contrast_range[0]), math.log(o.contrast_range[1])))
    edges = rng.uniform(*o.edge_share_range)
    chroma = rng.uniform(*o.chroma_share)
    # three fields: log luminance and two opponent axes (each its own phases, the same slope)
    fields = np.stack([power_law_noise(rng, size, slope) for _ in range(3)])
    if o.patches and edges > 0:
        index = _patches(rng, size, o.patches)
        offsets = np.vstack([rng.standard_normal((o.patches, 3)), np.zeros((1, 3))])  # the last: no patch
        steps = offsets[index].transpose(2, 0, 1)
        fields = (1.0 - edges) * fields + edges * steps
        fields /= np.maximum(fields.std(axis=(1, 2), keepdims=True), 1e-12)
    if rng.random() < o.saturated_share:
        base = np.exp(rng.uniform(math.log(0.02), math.log(0.8), 3))
    else:
        base = MATERIALS[rng.integers(len(MATERIALS))] * np.exp(0.15 * rng.standard_normal(3))
    lum = contrast * fields[0]
    # opponent axes: red-green and blue-yellow, in log RGB
    rg, by = chroma * contrast * fields[1], chroma * contrast * fields[2]
    log_rgb = np.stack([lum + rg - by / 2, lum - rg - by / 2, lum + by], -1)
    img = base * np.exp(log_rgb - log_rgb.reshape(-1, 3).mean(0))
    return np.clip(img, 0.0, 1.0).astype(np.float32)


# peak bytes a texture holds per pixel while made and written (three float64 fields, their FFTs, the sRGB
# encoding), measured with tracemalloc at 512, 1024 and 2048 px: 160.0 each
TEXTURE_BYTES_PER_PIXEL = 160
RECORD = "textures.json"           # the settings a folder's textures were made with (resuming checks them)
RECORD_FORMAT = "dcdi-textures"


def write_textures(folder, count: int, seed: int = 0, size: int = 512,
                   options: NaturalTextureOptions = NaturalTextureOptions(), progress=None) -> list[Path]:
    """``count`` textures as ``natural-NNNN.png`` (8-bit sRGB) in ``folder``.
    Texture i is drawn from seed (``seed``, i): the same arguments give the
    same files. Checked before any work: the arguments, the PNG writer
    (OpenImageIO), the memory one texture takes
    (:data:`TEXTURE_BYTES_PER_PIXEL` x size^2). A folder holding textures
    resumes where its run stopped (the files there are kept, the missing
    made) when its record (``textures.json``) says they were made with this
    seed, size and options; otherwise it is refused (nothing overwritten,
    nothing mixed)."""
    from ..io.image_checks import check_image_output
    from ..io.images import write_image
    from ..memory import check_fits
    if isinstance(count, bool) or not isinstance(count, int) or not 1 <= count <= 100000:
        raise InputRangeError("--count", count, "an integer 1 to 100000")
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise InputRangeError("--seed", seed, "an integer >= 0")
    if isinstance(size, bool) or not isinstance(size, (int, np.integer)) or not 16 <= size <= 8192:
        raise InputRangeError("--size", size, "an integer 16 to 8192 px")
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise InputRangeError("--out", str(folder), "a folder (this is a file)")
    paths = [folder / f"natural-{i:04d}.png" for i in range(count)]
    check_image_output(paths[0])                            # the writer, before any texture is made
    check_fits(TEXTURE_BYTES_PER_PIXEL * float(size) ** 2, f"a --size {size} texture",
               "lower --size (its memory grows as its square)")
    # as the file will hold it (tuples read back as lists): compared field by field with a kept one
    record = json.loads(json.dumps({"format": RECORD_FORMAT, "seed": seed, "size_px": int(size),
                                    "options": asdict(options)}))
    _check_resumable(folder, record)
    folder.mkdir(parents=True, exist_ok=True)
    _write_record(folder / RECORD, record)
    for i, path in enumerate(paths):
        if not path.exists():                               # a resumed run's files are whole (written atomically)
            img = natural_texture(np.random.default_rng([seed, i]), size, options)
            write_image(path, img, bit_depth=8)
        if progress is not None:
            progress(i + 1, count)
    return paths


def _check_resumable(folder: Path, record: dict) -> None:
    """Refuse a folder holding textures unless its record is this run's settings."""
    made = sorted(folder.glob("natural-*.png")) if folder.is_dir() else []
    if not made:
        return
    from ..io.jsontext import loads
    side = folder / RECORD
    try:
        kept = loads(side.read_text(encoding="utf-8", errors="replace"), side) if side.is_file() else None
    except (DcdiError, OSError):
        kept = None
    if not isinstance(kept, dict):
        raise InputRangeError("--out", str(folder), f"a folder without natural-NNNN.png files, or one a run of "
                              f"this command left ({made[0].name} is there without a readable {RECORD}: nothing "
                              "is overwritten)")
    differ = [k for k in ("seed", "size_px", "options") if kept.get(k) != record[k]]
    if kept.get("format") != RECORD_FORMAT or differ:
        what = ", ".join(f"{k} {kept.get(k)!r}" for k in differ) or "another format"
        raise InputRangeError("--out", str(folder), f"a folder of textures made with these settings (its "
                              f"{RECORD} says {what}: resuming would mix them)")


def _write_record(path: Path, record: dict) -> None:
    from ..atomic import atomic_path
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(record, sort_keys=True), encoding="utf-8")
