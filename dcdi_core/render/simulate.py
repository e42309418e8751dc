"""Depth-aware aberration simulation on an all-in-focus RGB-D image, and what the renders share.

simulate() / LensSimulator: the paper's training-data degradation. The
sharp image and its depth are first moved to where the lens puts them (its
geometric distortion; the moved sharp image is the aligned target), then
every m x m patch is blurred with the lens's PSF for its real field, azimuth
and depth (depth-aware), or with one depth for the whole image
(``fixed_depth_m``: the paper's depth-unaware baseline), and, optionally,
sensor noise is added. LensSimulator's docstring gives the order and why;
:class:`SimulateOptions` says how (checked when made, before any work).

Shared with the bokeh (``render.bokeh``, which imports them from here): the
result (:class:`RenderResult`), :class:`Cancelled`, the input checks, the
library opened at the image's pixel pitch (:func:`open_library`) and the
move onto the sensor (:func:`on_sensor`).
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field, replace

import numpy as np

from ..errors import InputRangeError
from ..psf.compute import KernelTooSmallWarning, PSFSettings
from ..psf.library import LibraryGrid, PSFLibrary
from .convolve import ConvolveOptions, patch_convolve
from .geometry import ImageGeometry
from .inputs import check_rgbd
from .psfmap import PSFMap, psf_map, valid_depth_mask


class Cancelled(Exception):
    """Raised by a render (``render.bokeh.bokeh``) when its ``cancelled()`` callback returns True."""


@dataclass
class RenderResult:
    """What a simulation or a bokeh render returns; images on the sensor's frame."""

    image: np.ndarray                 # (H, W, 3) float32, linear
    info: dict = field(default_factory=dict)
    sharp: np.ndarray | None = None   # simulate(): the sharp image on the sensor (distorted alike)
    psf_map: PSFMap | None = None
    baseline: np.ndarray | None = None  # LensSimulator with baseline_depth_m: the depth-unaware image
    depth: np.ndarray | None = None   # the depth map on the sensor (NaN where nothing was imaged)


def check_image(image, depth, geometry: ImageGeometry | None = None):
    """(image float32 (H, W, 3), depth float64 (H, W) metres), checked:
    shapes, finite light, and the frame ``geometry`` says if one is given."""
    img = np.asarray(image, dtype=np.float32)
    if img.ndim != 3 or img.shape[2] != 3:
        raise InputRangeError("image shape", img.shape, "(H, W, 3)")
    if not np.isfinite(img).all():
        raise InputRangeError("image", "non-finite values", "finite linear RGB")
    d = np.asarray(depth, dtype=np.float64)
    if d.shape != img.shape[:2]:
        raise InputRangeError("depth map shape", d.shape, f"{img.shape[:2]}, the image's")
    if geometry is not None and img.shape[:2] != (geometry.height, geometry.width):
        raise InputRangeError("image shape", img.shape[:2],
                              f"({geometry.height}, {geometry.width}), as its geometry says")
    return img, d


MAX_FITTED_KERNEL = 129      # px: beyond this a patch-wise FFT blur costs more than it is worth here
# the warp's interpolation of the sharp image (report simulation-accuracy,
# MOS-S1 at field 0.7: bilinear 62.3 dB, Keys 78.5, Lanczos-3 82.9, cubic
# B-spline 84.8 dB, for 0.42 / 0.90 / 1.86 / 1.38 s at 1280 x 1920)
DEFAULT_INTERPOLATION = "bspline"


def check_patch(patch) -> int:
    """The patch size m (pixels): even, >= 2 (the tent blend takes m / 2 from each side)."""
    if isinstance(patch, bool) or not isinstance(patch, (int, np.integer)) or patch < 2 or patch % 2:
        raise InputRangeError("patch", patch, "an even number of pixels >= 2 (16 is the paper's)")
    return int(patch)


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


def check_within_sensor(geometry: ImageGeometry, what: str = "the image") -> None:
    """Refuse a frame whose corners lie beyond the sensor (field > 1), before any work."""
    f = geometry.max_field
    if f > 1.0 + 1e-9:
        raise InputRangeError(
            f"field of {what}'s corner", round(f, 6),
            "<= 1 (the lens's sensor semi-diagonal): the frame is larger than the sensor; for an over-scan "
            "render give the sensor's frame (--sensor-size ROWS COLS, and --axis ROW COL) or the image's "
            "pixel pitch")


def check_flag(name: str, value) -> None:
    """Refuse an on/off option that is not a bool (a truthy string is not a yes)."""
    if not isinstance(value, (bool, np.bool_)):
        raise InputRangeError(name, value, "True or False")


def open_library(lens, geometry: ImageGeometry, settings: PSFSettings | None = None,
                 grid: LibraryGrid | None = None, *, response=None, cache: bool = True, fit_depth_m=None,
                 progress=None) -> PSFLibrary:
    """The lens's PSF library sampled at the image's pixel pitch.

    settings.pixel_pitch_mm, if set, must be the geometry's (the PSFs of an
    image are sampled at its own pitch). response: the sensor's spectral
    response (default: the shipped one).
    fit_depth_m: a depth map (metres) whose depth bins are computed now; if
    their PSFs spill out of the settings' kernel (less than 99 % of the rays
    inside, as a fast lens's defocus blur at full resolution does), the
    library is reopened with the odd kernel size that holds them, at most
    MAX_FITTED_KERNEL px (beyond that the usual KernelTooSmallWarning says
    how much is clipped). Without it the kernel size is the settings'.
    progress(done, total): called as PSF bins are computed."""
    s = settings or PSFSettings()
    if s.pixel_pitch_mm is not None and not math.isclose(s.pixel_pitch_mm, geometry.pixel_pitch_mm, rel_tol=1e-9):
        raise InputRangeError("pixel pitch", s.pixel_pitch_mm,
                              f"{geometry.pixel_pitch_mm:.6g} mm, the image's own pixel pitch (give one, not two)")
    s = replace(s, pixel_pitch_mm=geometry.pixel_pitch_mm)
    library = PSFLibrary.open(lens, s, grid, response, cache=cache)
    library.progress = progress
    if fit_depth_m is None:
        return library
    d = np.asarray(fit_depth_m, dtype=np.float64)
    d = d[valid_depth_mask(d)]
    if d.size == 0:
        return library
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", KernelTooSmallWarning)       # answered below by a larger kernel
        library.ensure(d, clamp_near=True, progress=progress)
    need = int(library.kernel_size_needed[library.computed].max())
    if need <= library.kernel_size or library.kernel_size >= MAX_FITTED_KERNEL:
        return library
    library = PSFLibrary.open(lens, replace(s, kernel_size=min(need | 1, MAX_FITTED_KERNEL)), grid, response,
                              cache=cache)
    library.progress = progress
    library.ensure(d, clamp_near=True)
    return library


def check_library_pitch(library: PSFLibrary, geometry: ImageGeometry) -> None:
    """A given library must be sampled at the image's pixel pitch (mm)."""
    if not math.isclose(library.pixel_pitch_mm, geometry.pixel_pitch_mm, rel_tol=1e-9):
        raise InputRangeError("library pixel pitch", library.pixel_pitch_mm,
                              f"{geometry.pixel_pitch_mm:.6g} mm, the image's (open it with open_library)")


def _sensor_mapping(distortion):
    """(ideal radius of a real radius, the table's reach in mm, its name) for
    a RadialDistortion table, or the identity for None."""
    if distortion is None:
        return (lambda r: r), math.inf, "identity"
    return distortion.ideal_from_real, distortion.reach_real_mm, "real-height"


def on_sensor(image, depth, lens, geometry: ImageGeometry, *, source_geometry: ImageGeometry | None = None,
              distortion=None, interpolation: str = DEFAULT_INTERPOLATION):
    """An ideal (pinhole) image and its depth map moved to where the lens puts
    them on the sensor: (image (H, W, C) float32, depth (H, W) float64, valid
    (H, W) bool) on ``geometry``'s grid.

    distortion: a RadialDistortion table (the lens's real chief rays), or
    None for none (then the output is the source resampled onto
    ``geometry``: a crop of an over-scan render, say). The image is
    interpolated with ``interpolation``; the depth map by its nearest
    sample (a blend of two depths is no depth). Pixels whose source lies
    outside the input are 0 with depth NaN (invalid)."""
    from .distortion import _warp

    src = source_geometry or geometry
    if distortion is None and src == geometry:
        d = np.asarray(depth, dtype=np.float64)
        return np.asarray(image, np.float32), d, np.ones(d.shape, bool)
    radius, reach, table = _sensor_mapping(distortion)
    img, valid = _warp(image, geometry, src, radius, "the sensor", reach, table, interpolation=interpolation)
    # higher-order interpolation rings below 0 at edges; light is never negative
    np.maximum(img, 0.0, out=img)
    # depths travel as finite codes (nearest copies them): -1 infinity, -2 invalid
    d = np.asarray(depth, dtype=np.float64)
    code = np.where(np.isinf(d) & (d > 0), -1.0, np.where(valid_depth_mask(d), d, -2.0))
    dep, _ = _warp(code, geometry, src, radius, "the sensor", reach, table, interpolation="nearest")
    dep = dep.astype(np.float64)
    dep = np.where(dep == -1.0, np.inf, np.where(valid & (dep > 0), dep, np.nan))
    return img, dep, valid


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
    given (``open_library``: settings' pixel pitch, if set, must be the
    geometry's; response None: the shipped sensor response; cache: read and
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
    (``open_library``). progress(done, total): called as PSF bins are
    computed.
    """

    def __init__(self, lens, options: SimulateOptions, *, library: PSFLibrary | None = None, fit_depth_m=None,
                 progress=None, **old):
        from . import fft
        from .distortion import radial_distortion

        options = _old_spelling("LensSimulator", options, old, geometry_needed=True)
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
        self.table = radial_distortion(lens) if options.distortion else None
        if library is None:
            library = open_library(lens, geometry, options.settings, options.grid, response=options.response,
                                   cache=options.cache, fit_depth_m=fit_depth_m, progress=progress)
        check_library_pitch(library, geometry)
        self.library = library
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
        radius, reach, _ = _sensor_mapping(self.table)
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
             fixed_depth_m: float | None = None, noise: dict | None = None, seed: int | None = None,
             **old) -> RenderResult:
    """Aberrated image of an all-in-focus ``image`` (H, W, 3) float32 linear
    with metric ``depth`` (H, W) through ``lens``: :class:`LensSimulator`
    used once. options: how (:class:`SimulateOptions`; None: the defaults);
    without a geometry (nor a source geometry) the image spans the sensor's
    diagonal. library: the PSFs at the frame's pixel pitch (default: opened,
    its kernel grown to hold this depth map's blur). fixed_depth_m, noise,
    seed: as :meth:`LensSimulator.__call__`."""
    options = _old_spelling("simulate", options, old)
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


def _old_spelling(where: str, options, old: dict, geometry_needed: bool = False):
    """The options of the old spelling (an ImageGeometry in the options'
    place, SimulateOptions' fields as keywords), kept one release with a
    warning; unknown keywords are refused as Python refuses them."""
    names = set(SimulateOptions.__dataclass_fields__)
    unknown = sorted(set(old) - names)
    if unknown:
        raise TypeError(f"{where}() got an unexpected keyword argument {unknown[0]!r}")
    if not old and not isinstance(options, ImageGeometry):
        return options
    if isinstance(options, ImageGeometry):
        old = {"geometry": options, **old}
        options = None
    if options is not None:
        raise TypeError(f"{where}(): give SimulateOptions or its fields as keywords, not both")
    given = ", ".join(f"{k}=" for k in sorted(old))
    warnings.warn(f"{where}(..., {given}...) is the old spelling: pass SimulateOptions({given}...); it goes in "
                  "the next release",
                  DeprecationWarning, stacklevel=3)
    return SimulateOptions(**old)


def __getattr__(name):
    # the bokeh moved to render/bokeh.py; its old import keeps working one release
    if name in ("BokehOptions", "bokeh"):
        warnings.warn(f"dcdi_core.render.simulate.{name} is now dcdi_core.render.bokeh.{name}; the old name goes "
                      "in the next release", DeprecationWarning, stacklevel=2)
        from . import bokeh as module
        return getattr(module, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
