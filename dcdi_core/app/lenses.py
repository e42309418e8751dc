"""The lens catalogue's answers for a front end: the lens folders, a lens
file read, a camera's stop and iris applied to a lens, a Zemax file
imported, and a picture of a lens's character (its PSF grid, the lens
list's thumbnails). The figures a panel shows are the lens report's
(``optics.report.lens_info``).

Units: lengths in mm, depths in metres, angles in degrees (a rotation given
in radians says so).
"""
from __future__ import annotations

import math
import warnings
from pathlib import Path

import numpy as np

from ..errors import InputRangeError
from ..names import check_name
from ..optics import zemax
from ..optics.aperture import MAX_BLADES, MAX_F_NUMBER, MIN_BLADES, Aperture, stopped_down, wide_open_f_number
from ..optics.lens import Lens, lens_dirs
from ..psf import compute

__all__ = ["Lens", "lens_dirs", "read_lens", "wide_open_f_number", "camera_stop", "import_zemax", "psf_thumbnail", "thumbnail_ball",
           "THUMBNAIL_FIELDS", "THUMBNAIL_DEPTHS_M", "THUMBNAIL_TILE_PX"]


def read_lens(path) -> Lens:
    """The lens of a TOML file; a broken file raises ``LensFileError`` naming file, surface and field."""
    return Lens.from_toml(path)


def camera_stop(lens, f_stop: float, blades: int, rotation_rad: float) -> tuple[Lens, str]:
    """(``lens`` stopped down to a camera's ``f_stop`` with its iris's
    ``blades`` (0 round, 3 or more a polygon, as Blender's) turned by
    ``rotation_rad``; a note, or ''). An F-Stop at or wider than the lens's
    widest leaves it wide open, said in the note (a camera's F-Stop is the
    artist's, not the lens's: it is never refused); one beyond
    ``MAX_F_NUMBER`` is that, and more than ``MAX_BLADES`` blades that many."""
    n0 = wide_open_f_number(lens)
    blades = int(blades) if int(blades) >= MIN_BLADES else 0
    note = ""
    if not (math.isfinite(f_stop) and f_stop > n0 * (1.0 + 1e-3)):
        if f_stop < n0 * (1.0 - 1e-3):
            note = f"F-Stop {f_stop:.3g} is wider than this lens's widest, f/{n0:.3g}: the lens wide open"
        f_stop = None
    else:
        f_stop = min(float(f_stop), MAX_F_NUMBER)
    rotation = math.degrees(float(rotation_rad)) if math.isfinite(rotation_rad) else 0.0
    return stopped_down(lens, Aperture(f_stop, min(blades, MAX_BLADES), rotation if blades else 0.0)), note


def import_zemax(zmx_path, out_dir) -> str:
    """Convert a Zemax .zmx file to a lens TOML in ``out_dir`` (validated
    before anything is written; written atomically); returns the TOML path."""
    d = zemax.read_zmx(zmx_path)
    Lens.from_dict(d, zmx_path)      # raises with file / surface / field
    out = Path(out_dir) / f"{check_name(d['id'], 'id', zmx_path, error=InputRangeError)}.toml"   # a name, not a path
    zemax.write_toml(d, out)
    return str(out)


# the thumbnails: PSFs at these fields (rows) and depths (columns, metres from
# the lens; inf: infinity), the lens as prescribed
THUMBNAIL_FIELDS = (0.0, 0.5, 0.9)
THUMBNAIL_DEPTHS_M = (1.0, 3.0, math.inf)
THUMBNAIL_TILE_PX = 31
THUMBNAIL_RAYS_PER_PX = 4


def psf_thumbnail(lens, tile: int = THUMBNAIL_TILE_PX) -> np.ndarray:
    """A grid of the lens's RGB PSFs (THUMBNAIL_FIELDS x THUMBNAIL_DEPTHS_M),
    each tile ``tile`` px at the pixel pitch of a 600-px-diagonal image on
    its sensor, or at the coarser one that holds the widest of them (a fast
    photographic lens focused at infinity blurs a point at 1 m over many
    times the tile: clipped, every tile would be a flat square), scaled to
    its own peak and gamma-encoded (1/2.2) so that halos show: float32 (H,
    W, 3) in [0, 1], rows top to bottom, 1-px gaps. Quick settings (four
    pupil rays a pixel across the widest; 5 wavelengths): a picture of the
    lens's character, not its exact PSFs."""
    pitch = 2.0 * lens.sensor.semi_diagonal_mm / 600.0
    _, needed = _thumbnail_kernels(lens, tile, pitch)          # how wide the widest is (a quick look)
    # one pitch for the grid (its tiles compare), the widest as wide as the tile; four rays a pixel across the
    # pupil, so that the balls are the lens's and not the ray grid's moire (two left it in every wide disc)
    kernels, _ = _thumbnail_kernels(lens, tile, pitch * max(needed, tile) / tile, rays=THUMBNAIL_RAYS_PER_PX * tile)
    nf, nd = len(THUMBNAIL_FIELDS), len(THUMBNAIL_DEPTHS_M)
    out = np.zeros((nf * (tile + 1) - 1, nd * (tile + 1) - 1, 3), np.float32)
    for (i, j), k in kernels.items():
        img = np.moveaxis(np.nan_to_num(k, nan=0.0), 0, -1)
        peak = float(img.max())
        tile_img = (img / peak) ** (1.0 / 2.2) if peak > 0 else img
        out[i * (tile + 1):i * (tile + 1) + tile, j * (tile + 1):j * (tile + 1) + tile] = tile_img
    return out


def thumbnail_ball(grid: np.ndarray, tile: int = THUMBNAIL_TILE_PX) -> np.ndarray:
    """The icon of a lens in a list: one tile of its :func:`psf_thumbnail`
    grid, the ball a light at 1 m makes toward the frame's corner (field
    0.9), where lenses differ most (cat's eyes, oval or clipped balls,
    rims): (tile, tile, 3)."""
    i, j = len(THUMBNAIL_FIELDS) - 1, 0
    return grid[i * (tile + 1):i * (tile + 1) + tile, j * (tile + 1):j * (tile + 1) + tile]


def _thumbnail_kernels(lens, tile: int, pitch: float, rays: int = 32) -> tuple[dict, int]:
    """({(row, column): RGB kernel (3, tile, tile)} of the thumbnail's grid at
    ``pitch`` mm with ``rays`` per pupil side, the widest kernel any of them
    needs (99 % of its rays), px)."""
    settings = compute.PSFSettings(kernel_size=tile, pupil_samples=rays, n_wavelengths=5, pixel_pitch_mm=pitch)
    kernels, needed = {}, 0
    for i, f in enumerate(THUMBNAIL_FIELDS):
        for j, d in enumerate(THUMBNAIL_DEPTHS_M):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")         # a PSF larger than the tile is clipped: measured below
                b = compute.psf(lens, depth_m=d, field=f, settings=settings)
            kernels[i, j] = b.psf
            needed = max(needed, int(b.kernel_size_needed))
    return kernels, needed
