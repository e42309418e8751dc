"""Depth-aware aberration simulation on an all-in-focus RGB-D image.

simulate() / LensSimulator: the paper's training-data degradation. The
sharp image and its depth are first moved to where the lens puts them (its
geometric distortion; the moved sharp image is the aligned target), then
every m x m patch is blurred with the lens's PSF for its real field, azimuth
and depth (depth-aware), or with one depth for the whole image
(``fixed_depth_m``: the paper's depth-unaware baseline), and, optionally,
sensor noise is added. LensSimulator's docstring gives the order and why;
:class:`SimulateOptions` says how (checked when made, before any work).

What it shares with the bokeh (the result, cancel, the input checks, the
move onto the sensor) is in ``render.base``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from ..errors import InputRangeError
from ..psf.compute import PSFSettings
from ..psf.library import LibraryGrid, PSFLibrary
from ..psf.sources import lens_library
from .base import (DEFAULT_INTERPOLATION, RenderResult, sensor_mapping, check_flag, check_image, check_library_pitch,
                   check_patch, check_within_sensor, on_sensor)
from .convolve import ConvolveOptions, patch_convolve
from .geometry import ImageGeometry
from .inputs import check_rgbd
from .psfmap import PSFMap, psf_map


SIM_CONVOLUTIONS = ("fast", "windows")
ACCELERATORS = ("torch",)


def check_convolution(convolution, accelerator) -> tuple[str, str | None]:
    """The simulation's convolution method and accelerator, checked before any work."""
    if convolution not in SIM_CONVOLUTIONS:
        raise InputRangeError("convolution", convolution, " or ".join(SIM_CONVOLUTIONS))
    if accelerator is not None:
        from . import accel_torch
        if accelerator not in ACCELERATORS:
            raise InputRangeError("accelerator", accelerator, "none (numpy) or " + ", ".join(ACCELERATORS))
        if convolution != "fast":
            raise InputRangeError("accelerator", accelerator, "none with convolution 'windows' (torch runs 'fast')")
        if not accel_torch.available():
            raise InputRangeError("accelerator", accelerator, "none here: torch cannot be imported (Blender's "
                                  "Python has none)")
    return convolution, accelerator


@dataclass(frozen=True)
class SimulateOptions:
    """How :class:`LensSimulator` and :func:`simulate` form an image,
    checked when made (before any work; ``replace`` checks again).

    geometry: the output frame on the sensor (must lie within it, field <=
    1). None: the source's frame (``source_geometry``); with neither,
    :func:`simulate` takes the image spanning the sensor's diagonal
    (``ImageGeometry.full_sensor``) while :class:`LensSimulator`, which sees
    no image until it is called, refuses (InputRangeError naming
    'geometry'). source_geometry: the input's frame if it differs (an
    over-scan render: larger, same pitch, axis at its own pixel position).

    patch: the patch size m (px, even, >= 2; 16 is the paper's).
    distortion: move the image to where the lens's real chief rays put it
    first, resampled with ``interpolation`` (one of
    ``distortion.INTERPOLATIONS``).

    settings, grid, response, cache: the PSF library opened when none is
    given (``psf.sources.lens_library``: the lens's ray map where one ships,
    else traced; settings' pixel pitch, if set, must be the geometry's;
    response None: the shipped sensor response; cache: read and
    write the library's cache on disk).

    baseline_depth_m: metres (> 0, or inf): also form the depth-unaware
    baseline, every patch blurred as at this depth
    (``RenderResult.baseline``); None: none.

    convolution: 'fast' (default: the windows method laid out for speed, the
    same result to float32 rounding) or 'windows' (the exact form it is
    tested against). accelerator: None (numpy: Blender's path) or 'torch'
    (PSF map and convolution in torch, ``accel_torch.py``; the same result
    to float32 rounding). fft_backend: 'scipy' or 'numpy' (None: the fastest
    installed, ``fft.backend``). blend: half-width (px) of the ramps between
    patches, 1 to m / 2 (None: m / 2, the tent; see ``patch_convolve`` and
    the report's blend rows).
    """

    geometry: ImageGeometry | None = None
    source_geometry: ImageGeometry | None = None
    patch: int = 16
    distortion: bool = True
    interpolation: str = DEFAULT_INTERPOLATION
    settings: PSFSettings | None = None
    grid: LibraryGrid | None = None
    response: object = None                    # psf.spectral.SpectralResponse, or None for the shipped one
    cache: bool = True
    baseline_depth_m: float | None = None
    fft_backend: str | None = None
    convolution: str = "fast"
    accelerator: str | None = None
    blend: int | None = None

    def __post_init__(self):
        from . import fft
        from .distortion import check_interpolation
        for name in ("geometry", "source_geometry"):
            if getattr(self, name) is not None and not isinstance(getattr(self, name), ImageGeometry):
                raise InputRangeError(name, getattr(self, name), "an ImageGeometry, or None")
        for name in ("distortion", "cache"):
            check_flag(name, getattr(self, name))
        if self.settings is not None and not isinstance(self.settings, PSFSettings):
            raise InputRangeError("settings", self.settings, "PSFSettings, or None for the defaults")
        if self.grid is not None and not isinstance(self.grid, LibraryGrid):
            raise InputRangeError("grid", self.grid, "LibraryGrid, or None for the default grid")
        fft.backend(self.fft_backend)                     # its own message: the backends this Python has
        check_convolution(self.convolution, self.accelerator)
        object.__setattr__(self, "patch", check_patch(self.patch))
        blend, patch = self.blend, self.patch
        if blend is not None and (isinstance(blend, bool) or not isinstance(blend, (int, np.integer))
                                  or not 1 <= blend <= patch // 2):
            raise InputRangeError("blend", blend, f"an integer in [1, {patch // 2}] px (the patch's half), or none")
        if blend is not None:
            object.__setattr__(self, "blend", int(blend))
        check_interpolation(self.interpolation)
        b = self.baseline_depth_m
        if b is not None and not (isinstance(b, (int, float)) and b > 0 and not math.isnan(b)):
            raise InputRangeError("baseline depth", b, "> 0 metres, or inf")
        if self.frame is not None:
            check_within_sensor(self.frame)

    @property
    def frame(self) -> ImageGeometry | None:
        """The output frame on the sensor: ``geometry``, else ``source_geometry`` (None if neither)."""
        return self.geometry or self.source_geometry


class LensSimulator:
    """The aberration simulation of one lens on one image geometry, with
    everything that does not change between images built once: the PSF
    library at the image's pixel pitch, the distortion table and, if asked
    for, the depth-unaware baseline's PSF map.

    How an image is formed (in this order): the ideal all-in-focus image
    (pinhole at the entrance pupil, area-integrated pixels) and its depth
    map are moved to where the lens's real chief rays put them (distortion);
    each m x m patch of that is blurred with the PSF of its real field,
    azimuth and depth (depth-aware) or of one depth (baseline); the kernel
    is the ray histogram over pixels, which with the area-integrated input
    is what the sensor integrates (psf/deposit.py); sensor noise last.
    Relative illumination is not applied (PSFs sum to 1): the target and the
    capture stay radiometrically aligned, as in the paper.

    options: how (:class:`SimulateOptions`); the output frame is
    ``options.geometry``, else ``options.source_geometry`` (one is needed).
    library: the PSFs at the frame's pixel pitch (default: opened from the
    options' settings, grid, response and cache). fit_depth_m: a depth map
    (metres) whose blur the opened library's kernel grows to hold
    (``lens_library``). progress(done, total): called as PSF bins are
    computed.
    """

    def __init__(self, lens, options: SimulateOptions, *, library: PSFLibrary | None = None, fit_depth_m=None,
                 progress=None):
        from . import fft
        from .distortion import chief_ray_map

        if not isinstance(options, SimulateOptions):
            raise InputRangeError("options", options, "SimulateOptions (how to simulate)")
        geometry = options.frame
        if geometry is None:
            # the default frame (the image spanning the sensor's diagonal) needs
            # the image's size, which only simulate() sees
            raise InputRangeError("geometry", None, "the output frame on the sensor (SimulateOptions.geometry or "
                                  "source_geometry), or simulate() to take the image's own size")
        self.options = options
        self.fft_backend = fft.backend(options.fft_backend)
        self.convolution, self.accelerator = options.convolution, options.accelerator
        self.blend = options.blend
        self.patch = options.patch
        self.convolve_options = ConvolveOptions(method=self.convolution, blend=self.blend, fft_backend=self.fft_backend,
                                                accelerator=self.accelerator)
        self.interpolation = options.interpolation
        self.lens, self.geometry = lens, geometry
        self.source_geometry = options.source_geometry or geometry
        if library is None:
            library = lens_library(lens, geometry, options.settings, options.grid, response=options.response,
                                   cache=options.cache, fit_depth_m=fit_depth_m, progress=progress)
        check_library_pitch(library, geometry)
        self.library = library
        # the lens's chief rays at the PSFs' own focus, per depth (breathing and
        # depth-dependent distortion); depths nearer than the library's use its near limit
        focus = (options.settings.focus_distance_m if options.settings is not None
                 else library.settings.focus_distance_m)
        self.table = chief_ray_map(lens, focus_m=focus, near_m=library.grid.near_m) if options.distortion else None
        self.margin = self._scene_margin()
        m = self.margin
        self.work_geometry = geometry if m == 0 else replace(
            geometry, height=geometry.height + 2 * m, width=geometry.width + 2 * m,
            center_px=(geometry.center_px[0] + m, geometry.center_px[1] + m))
        self.baseline_depth_m = options.baseline_depth_m
        self.baseline = None if self.baseline_depth_m is None else self._fixed_map(self.baseline_depth_m)

    def _scene_margin(self) -> int:
        """Pixels of scene around the frame that its border's blur reads (a
        whole number of patches), when an over-scan source holds them all;
        else 0 (the frame's border is reflected)."""
        if self.source_geometry == self.geometry:
            return 0
        from .distortion import _source_positions
        m = self.patch * math.ceil((self.patch // 2 + self.library.kernel_size // 2) / self.patch)
        g = self.geometry
        grown = replace(g, height=g.height + 2 * m, width=g.width + 2 * m,
                        center_px=(g.center_px[0] + m, g.center_px[1] + m))
        radius, reach, _ = sensor_mapping(self.table)
        try:
            _, _, valid = _source_positions(grown, self.source_geometry, radius, reach)
        except InputRangeError:
            return 0
        return m if valid.all() else 0

    def _crop(self, a):
        m = self.margin
        return a if m == 0 or a is None else a[m:a.shape[0] - m, m:a.shape[1] - m]

    def _fixed_map(self, depth_m: float) -> PSFMap:
        g = self.work_geometry
        return psf_map(self.library, g, np.ones((g.height, g.width)), self.patch, fixed_depth_m=depth_m,
                       clamp_field=self.margin > 0, method=self._map_method, accelerator=self.accelerator)

    @property
    def _map_method(self) -> str:
        return "exact" if self.convolution == "windows" else "fast"

    def _blur(self, sharp, pm: PSFMap):
        """The patch-wise blur of ``sharp`` with ``pm``'s kernels (>= 0)."""
        out = patch_convolve(sharp, pm.kernels, self.patch, self.convolve_options, identity=pm.identity)
        # non-negative kernels on a non-negative image: below 0 is FFT round-off (~1e-7)
        return np.maximum(out, 0.0)

    def on_sensor(self, image, depth):
        """(image, depth, valid) on the sensor, with the scene margin if any:
        see :func:`on_sensor`."""
        return on_sensor(image, depth, self.lens, self.work_geometry, source_geometry=self.source_geometry,
                         distortion=self.table, interpolation=self.interpolation)

    def __call__(self, image, depth, *, fixed_depth_m: float | None = None, noise: dict | None = None,
                 seed: int | None = None) -> RenderResult:
        """Aberrated image of an all-in-focus ``image`` (H, W, 3) with metric
        ``depth`` (H, W) on the source geometry. fixed_depth_m: one depth
        for every patch instead (the paper's depth-unaware baseline). noise:
        keyword arguments of ``noise.add_sensor_noise`` (needs ``seed``),
        added to the aberrated image only."""
        img, d = check_image(image, depth, self.source_geometry)
        check_rgbd(img, None if fixed_depth_m is not None else d)
        return self._run(img, d, fixed_depth_m, noise, seed)

    def _run(self, img, d, fixed_depth_m, noise, seed) -> RenderResult:
        if noise is not None and seed is None:
            raise InputRangeError("seed", None, "an integer: noise needs an explicit seed")
        sharp, d_s, valid = self.on_sensor(img, d)
        if fixed_depth_m is not None:
            pm = self._fixed_map(fixed_depth_m)
        else:
            pm = psf_map(self.library, self.work_geometry, d_s, self.patch, clamp_field=self.margin > 0,
                         method=self._map_method, accelerator=self.accelerator)
        out = self._blur(sharp, pm)
        info = dict(pm.info, depth_aware=fixed_depth_m is None, distortion=self.table is not None,
                    interpolation=self.interpolation, not_imaged_pixels=int((~self._crop(valid)).sum()))
        baseline = None
        if self.baseline is not None:
            baseline = self._blur(sharp, self.baseline)
            info["baseline_depth_m"] = self.baseline_depth_m
        if noise is not None:
            from .noise import add_sensor_noise
            out = add_sensor_noise(out, seed=seed, **noise)
            info["noise"] = dict(noise, seed=seed)
        info["border"] = "scene" if self.margin else "reflected"
        c = self._crop
        return RenderResult(c(out).astype(np.float32), info, c(sharp).astype(np.float32), pm,
                            None if baseline is None else c(baseline).astype(np.float32), c(d_s))


def simulate(image, depth, lens, options: SimulateOptions | None = None, *, library: PSFLibrary | None = None,
             fixed_depth_m: float | None = None, noise: dict | None = None, seed: int | None = None) -> RenderResult:
    """Aberrated image of an all-in-focus ``image`` (H, W, 3) float32 linear
    with metric ``depth`` (H, W) through ``lens``: :class:`LensSimulator`
    used once. options: how (:class:`SimulateOptions`; None: the defaults);
    without a geometry (nor a source geometry) the image spans the sensor's
    diagonal. library: the PSFs at the frame's pixel pitch (default: opened,
    its kernel grown to hold this depth map's blur). fixed_depth_m, noise,
    seed: as :meth:`LensSimulator.__call__`."""
    if options is None:
        options = SimulateOptions()
    elif not isinstance(options, SimulateOptions):
        raise InputRangeError("options", options, "SimulateOptions (how to simulate), or None for the defaults")
    img, d = check_image(image, depth, options.source_geometry)
    check_rgbd(img, None if fixed_depth_m is not None else d)
    if options.frame is None:
        options = replace(options, geometry=ImageGeometry.full_sensor(lens, img.shape[0], img.shape[1]))
    sim = LensSimulator(lens, options, library=library, fit_depth_m=d if library is None else None)
    return sim._run(img, d, fixed_depth_m, noise, seed)


