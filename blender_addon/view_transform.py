"""The scene's colour management for the viewport preview: a linear image
shown as F12 shows the render (the view transform, its look, exposure,
gamma, curves and white balance, the display device), within a measured
bound (docs/addon.md, "Colours").

How: Blender itself maps a grid of scene-linear colours to display values
once per change of the scene's view settings (:func:`bake`: the grid as a
float image, ``Image.save_render`` with a copy of the scene writing a 16-bit
PNG, which applies the scene's view and display settings as a rendered
frame's file gets them, read back as stored), and numpy applies that 3D
table to each preview image (:func:`apply`: tetrahedral interpolation,
vectorised). The grid's levels per channel are 0, then
``STEPS_PER_STOP`` a stop from ``2**LOWEST_STOP`` to ``2**HIGHEST_STOP``
(mid grey 0.18 / 2**12.5 to 0.18 * 2**12.5: Filmic's range, AgX's
and more), divided by 2**exposure. An input between 0 and the first level
after it is interpolated linearly, one above the last is clipped to it;
negative values and NaN are taken as 0, +inf as the top.
Outputs are display values in [0, 1] (what an 8- or 16-bit file holds:
an HDR display's values above 1 are clipped).

The tables are kept by the view settings' values (:func:`settings_key`):
changing any of them bakes a new one on the next use; the last
``KEPT_TABLES`` are kept, and dropped with the session (``SESSION.clear``).
Blender's API for this runs on the main thread only.
"""
from __future__ import annotations

import shutil
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import bpy
import numpy as np

from .session import SESSION

STEPS_PER_STOP = 4        # grid levels per stop (a factor 2 of scene-linear light)
LOWEST_STOP = -15         # the lowest level after 0: 2**LOWEST_STOP (2**-15 = mid grey 0.18 / 2**12.5) ...
HIGHEST_STOP = 10         # ... the highest 2**HIGHEST_STOP (1024 = mid grey * 2**12.5); both / 2**exposure
CHUNK = 1 << 16           # pixels interpolated at a time (their temporaries stay in the CPU's caches)
KEPT_TABLES = 2
TEMP_NAME = "dcdi-view-transform"


@dataclass(frozen=True)
class Table:
    """A baked 3D table: ``values[r, g, b]`` (N, N, N, 3) float32 display
    values of the scene-linear colour (levels[r], levels[g], levels[b])."""
    key: tuple
    values: np.ndarray
    levels: np.ndarray        # (N,) float64: 0, then log2-spaced from ``low`` to ``high``
    low: float
    high: float
    steps_per_stop: int
    bake_s: float


# ------------------------------------------------------------------ what the table depends on
def _rna_values(struct) -> tuple:
    """(identifier, value) of every property of ``struct`` that is a value
    (numbers, booleans, enums, strings; arrays as tuples), sorted: new
    properties of a later Blender are included without naming them."""
    out = []
    for p in struct.bl_rna.properties:
        if p.identifier == "rna_type" or p.type in ("POINTER", "COLLECTION"):
            continue
        v = getattr(struct, p.identifier, None)
        if p.type == "ENUM" and getattr(p, "is_enum_flag", False):
            v = tuple(sorted(v))
        elif not isinstance(v, (int, float, str, bool, type(None))):
            try:
                v = tuple(v)
            except TypeError:
                v = repr(v)
        out.append((p.identifier, v))
    return tuple(sorted(out))


def _curves(view) -> tuple:
    """The view's RGB curves (only while they are used): the mapping's
    settings, each curve's settings and points."""
    if not view.use_curve_mapping:
        return ()
    cm = view.curve_mapping
    curves = tuple((_rna_values(c), tuple((tuple(p.location), p.handle_type) for p in c.points)) for c in cm.curves)
    return _rna_values(cm), tuple(cm.black_level), tuple(cm.white_level), curves


def settings_key(scene) -> tuple:
    """What the display of a scene-linear colour depends on: the scene's
    view settings (view transform, look, exposure, gamma, white balance, the
    curves while used), its display settings (device, emulation) and the
    file's working colour space. The sequencer's colour space is not in it:
    it does not enter a rendered frame's display."""
    view, display = scene.view_settings, scene.display_settings
    working = getattr(getattr(bpy.data, "colorspace", None), "working_space", "")
    return _rna_values(view), _curves(view), _rna_values(display), working


# ------------------------------------------------------------------ Blender's own display of an image
def blender_display(scene, rgb: np.ndarray) -> np.ndarray:
    """(H, W, 3) float32 display values of the scene-linear (H, W, 3) image
    ``rgb`` as Blender writes a rendered frame of ``scene``: a float image
    saved with ``save_render`` through a copy of the scene (its view and
    display settings; output set to a 16-bit RGB PNG, following the scene's
    colour management, no dither) and read back as stored (Non-Color).
    Nothing of ``scene`` changes. Main thread only."""
    rgb = np.asarray(rgb, np.float32)
    h, w = rgb.shape[:2]
    work = Path(tempfile.mkdtemp(prefix="dcdi-view-"))
    path = work / "display.png"
    img = loaded = tmp = None
    try:
        img = bpy.data.images.new(TEMP_NAME, w, h, alpha=True, float_buffer=True)
        rgba = np.ones((h, w, 4), np.float32)
        rgba[..., :3] = rgb[::-1]                        # Blender's rows run bottom to top
        img.pixels.foreach_set(rgba.ravel())
        img.update()
        tmp = scene.copy()
        tmp.name = TEMP_NAME
        r = tmp.render
        fmt = r.image_settings
        if hasattr(fmt, "media_type"):                   # Blender 5 groups formats by media type
            fmt.media_type = "IMAGE"
        fmt.file_format = "PNG"
        fmt.color_mode = "RGB"
        fmt.color_depth = "16"
        fmt.compression = 0
        if hasattr(fmt, "color_management"):
            fmt.color_management = "FOLLOW_SCENE"
        r.dither_intensity = 0.0
        img.save_render(str(path), scene=tmp)
        if not path.exists():
            raise RuntimeError(f"Blender wrote no file to {path}")
        loaded = bpy.data.images.load(str(path), check_existing=False)
        loaded.colorspace_settings.name = "Non-Color"    # the stored values, not decoded to linear
        if tuple(loaded.size) != (w, h) or loaded.channels < 3:
            raise RuntimeError(f"{path} reads back as {tuple(loaded.size)} x {loaded.channels}, not {(w, h)}")
        px = np.empty(w * h * loaded.channels, np.float32)
        loaded.pixels.foreach_get(px)
        return px.reshape(h, w, loaded.channels)[::-1, :, :3].copy()
    finally:
        for block, coll in ((loaded, bpy.data.images), (img, bpy.data.images), (tmp, bpy.data.scenes)):
            if block is not None:
                coll.remove(block)
        shutil.rmtree(work, ignore_errors=True)


# ------------------------------------------------------------------ the table
def grid_levels(scene, steps_per_stop: int = STEPS_PER_STOP) -> np.ndarray:
    """The grid's levels per channel for ``scene``: 0, then 2**(k / steps_per_stop)
    from 2**LOWEST_STOP to 2**HIGHEST_STOP, divided by 2**exposure (the
    range follows the display's; 1 / 2**exposure, where Standard clips, is
    a level)."""
    if steps_per_stop < 1:
        raise ValueError(f"a table needs at least one level per stop, not {steps_per_stop}")
    ev = float(scene.view_settings.exposure)
    k = np.arange(LOWEST_STOP * steps_per_stop, HIGHEST_STOP * steps_per_stop + 1)
    return np.concatenate([[0.0], np.exp2(k / steps_per_stop - ev)])


def bake(scene, steps_per_stop: int = STEPS_PER_STOP) -> Table:
    """The table of ``scene``'s display, baked by Blender (:func:`blender_display`
    of the n^3 grid colours, an (n*n) x n image). Main thread only."""
    t0 = time.perf_counter()
    levels = grid_levels(scene, steps_per_stop)
    n = len(levels)
    r, g, b = np.meshgrid(levels, levels, levels, indexing="ij")
    grid = np.stack([r, g, b], axis=-1).astype(np.float32).reshape(n * n, n, 3)
    values = blender_display(scene, grid).reshape(n, n, n, 3)
    return Table(settings_key(scene), np.ascontiguousarray(values, np.float32), levels,
                 float(levels[1]), float(levels[-1]), steps_per_stop, time.perf_counter() - t0)


def table(scene) -> Table:
    """The table for ``scene``'s view settings now: kept, or baked when they
    changed since (the last ``KEPT_TABLES`` are kept)."""
    key = settings_key(scene)
    tables = SESSION.view_tables                        # settings_key -> Table, newest last
    t = tables.pop(key, None)
    if t is None:
        t = bake(scene)
        while len(tables) >= KEPT_TABLES:
            tables.pop(next(iter(tables)))
    tables[key] = t
    return t


# ------------------------------------------------------------------ applying it
def _coordinates(x: np.ndarray, t: Table) -> np.ndarray:
    """Each value's fractional grid index in [0, N - 1] (float32): linear
    between 0 and the first level, log2 above; NaN and negatives at 0, above
    the top (+inf included) at N - 1."""
    x = np.nan_to_num(x, nan=0.0, posinf=t.high, neginf=0.0)
    np.clip(x, 0.0, t.high, out=x)
    c = np.log2(np.maximum(x, np.float32(t.low)))
    c -= np.float32(np.log2(t.low))
    c *= np.float32(t.steps_per_stop)
    c += 1.0
    below = x < t.low
    c[below] = x[below] * np.float32(1.0 / t.low)
    return np.clip(c, 0.0, len(t.levels) - 1, out=c)


def apply(t: Table, image: np.ndarray, chunk: int = CHUNK) -> np.ndarray:
    """Float32 display values in [0, 1] of the scene-linear (..., 3)
    ``image`` through the table ``t`` (tetrahedral interpolation: a grey
    stays on the grid's grey axis), ``chunk`` pixels at a time."""
    image = np.asarray(image, np.float32)
    pixels = image.reshape(-1, 3)
    out = np.empty_like(pixels)
    for a in range(0, len(pixels), chunk):
        out[a:a + chunk] = _tetrahedral(t, pixels[a:a + chunk])
    return out.reshape(image.shape)


def _tetrahedral(t: Table, rgb: np.ndarray) -> np.ndarray:
    n = len(t.levels)
    c = _coordinates(rgb, t)
    i = np.minimum(c.astype(np.int32), n - 2)             # c >= 0: truncation is floor
    f = c - i
    flat = t.values.reshape(-1, 3)
    sr, sg, sb = n * n, n, 1
    base = i[:, 0] * sr + i[:, 1] * sg + i[:, 2]
    fr, fg, fb = f[:, 0], f[:, 1], f[:, 2]
    # the tetrahedron holding the point: its fractions ordered, largest first;
    # the path from the cell's corner 0 goes along their axes in that order
    rg, gb, rb = fr >= fg, fg >= fb, fr >= fb
    is_r = rg & rb
    first = np.where(is_r, sr, np.where(gb, sg, sb))                 # the largest's axis (its stride)
    last = np.where(~rg & ~rb, sr, np.where(gb & rb, sb, sg))        # the smallest's
    f1 = np.maximum(np.maximum(fr, fg), fb)[:, None]
    f3 = np.minimum(np.minimum(fr, fg), fb)[:, None]
    f2 = (fr + fg + fb)[:, None] - f1 - f3
    v0 = np.take(flat, base, axis=0)
    v1 = np.take(flat, base + first, axis=0)
    v2 = np.take(flat, base + (sr + sg + sb) - last, axis=0)
    v3 = np.take(flat, base + (sr + sg + sb), axis=0)
    out = v0
    out += f1 * (v1 - v0)      # v0 (1 - f1) + v1 (f1 - f2) + v2 (f2 - f3) + v3 f3, as differences
    out += f2 * (v2 - v1)
    out += f3 * (v3 - v2)
    return np.clip(out, 0.0, 1.0, out=out)


def display_rows(t: Table, image: np.ndarray) -> tuple:
    """``(t.key, RGBA rows bottom-up)`` of the linear (H, W, 3) image through
    ``t``, as a texture takes them: pure numpy, so the preview makes them on
    its lens stage's thread (on the main thread they held Blender 0.1-0.3 s
    at 480 x 270)."""
    h, w = image.shape[:2]
    rgba = np.ones((h, w, 4), np.float32)
    rgba[..., :3] = apply(t, image)
    return t.key, np.ascontiguousarray(rgba[::-1])


def to_display(image: np.ndarray, scene=None) -> np.ndarray:
    """The scene-linear (H, W, 3) ``image`` as ``scene`` (default: the
    context's) displays a rendered frame: float32 display values in [0, 1]."""
    return apply(table(scene if scene is not None else bpy.context.scene), image)


def kept(scene) -> Table | None:
    """The kept table of ``scene``'s view settings now, or None (nothing is
    baked): what a thread may apply, with :func:`apply`, off the main thread."""
    return SESSION.view_tables.get(settings_key(scene))


def has_table(scene) -> bool:
    """Whether the table of ``scene``'s view settings now is kept (no bake needed)."""
    return settings_key(scene) in SESSION.view_tables


def keep(t: Table) -> None:
    """Keep a table baked elsewhere (the preview's render worker, a second
    Blender that opened the same scene) under its key, as :func:`table` would."""
    tables = SESSION.view_tables
    tables.pop(t.key, None)
    while len(tables) >= KEPT_TABLES:
        tables.pop(next(iter(tables)))
    tables[t.key] = t


def forget() -> None:
    """Drop the kept tables (the tests; the session's end drops them too)."""
    SESSION.view_tables.clear()


def tables_kept() -> int:
    """How many tables are kept now (for the tests)."""
    return len(SESSION.view_tables)
