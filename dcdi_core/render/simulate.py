"""Depth-aware aberration simulation and lens bokeh on an all-in-focus RGB-D image.

simulate() / LensSimulator: the paper's training-data degradation. The
sharp image and its depth are first moved to where the lens puts them (its
geometric distortion; the moved sharp image is the aligned target), then
every m x m patch is blurred with the lens's PSF for its real field, azimuth
and depth (depth-aware), or with one depth for the whole image
(``fixed_depth_m``: the paper's depth-unaware baseline), and, optionally,
sensor noise is added. LensSimulator's docstring gives the order and why.

bokeh(): the depth of field of a target lens on a sharp image, as one
:class:`BokehOptions` says. What is kept sharp is a depth range [near, far]
(the paper's mask: identity PSF inside it), a focus distance (the library
refocused there) or the lens as prescribed; optionally with the lens's
distortion first. Two renderers:
``occlusion=False`` is the plain patch-wise blur; ``occlusion=True`` (the
default) splits the scene into depth layers and composites them back to
front, each blurred with its own PSFs and carrying its blurred coverage, so
a sharp subject does not bleed into a blurred background nor get a halo.
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field, replace

import numpy as np

from ..errors import InputRangeError
from ..psf.compute import KernelTooSmallWarning, PSFSettings
from ..psf.library import LibraryGrid, PSFLibrary
from .convolve import METHODS, ConvolveOptions, grow_square, patch_convolve
from .geometry import ImageGeometry
from .inputs import check_rgbd
from .psfmap import PSFMap, psf_map, valid_depth_mask


class Cancelled(Exception):
    """Raised by :func:`bokeh` when its ``cancelled()`` callback returns True."""


@dataclass
class RenderResult:
    image: np.ndarray                 # (H, W, 3) float32, linear
    info: dict = field(default_factory=dict)
    sharp: np.ndarray | None = None   # simulate(): the sharp image on the sensor (distorted alike)
    psf_map: PSFMap | None = None
    baseline: np.ndarray | None = None  # LensSimulator with baseline_depth_m: the depth-unaware image
    depth: np.ndarray | None = None   # the depth map on the sensor (NaN where nothing was imaged)


def _check(image, depth, geometry: ImageGeometry | None = None):
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


def _check_library(library: PSFLibrary, geometry: ImageGeometry) -> None:
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

    geometry: the output frame on the sensor (must lie within it).
    source_geometry: the input's frame if it differs (an over-scan render:
    larger, same pitch, axis at its own pixel position).
    convolution: 'fast' (default: the windows method laid out for speed, the
    same result to float32 rounding) or 'windows' (the exact form it is
    tested against). accelerator: None (numpy: Blender's path) or 'torch'
    (PSF map and convolution in torch, ``accel_torch.py``; the same result
    to float32 rounding). blend: half-width (px) of the ramps between
    patches (default m / 2, the tent; see ``patch_convolve`` and the report's
    blend rows).
    """

    def __init__(self, lens, geometry: ImageGeometry, *, source_geometry: ImageGeometry | None = None,
                 library: PSFLibrary | None = None, settings: PSFSettings | None = None,
                 grid: LibraryGrid | None = None, response=None, patch: int = 16, distortion: bool = True,
                 interpolation: str = DEFAULT_INTERPOLATION, baseline_depth_m: float | None = None,
                 fit_depth_m=None, cache: bool = True, progress=None, fft_backend: str | None = None,
                 convolution: str = "fast", accelerator: str | None = None, blend: int | None = None):
        from . import fft
        from .distortion import check_interpolation, radial_distortion

        self.fft_backend = fft.backend(fft_backend)
        self.convolution, self.accelerator = check_convolution(convolution, accelerator)
        if blend is not None and (isinstance(blend, bool) or not isinstance(blend, (int, np.integer))
                                  or not 1 <= blend <= patch // 2):
            raise InputRangeError("blend", blend, f"an integer in [1, {patch // 2}] px (the patch's half), or none")
        self.blend = None if blend is None else int(blend)

        self.patch = check_patch(patch)
        self.convolve_options = ConvolveOptions(method=self.convolution, blend=self.blend, fft_backend=self.fft_backend,
                                                accelerator=self.accelerator)
        self.interpolation = check_interpolation(interpolation)
        check_within_sensor(geometry)
        if baseline_depth_m is not None and not (isinstance(baseline_depth_m, (int, float))
                                                 and baseline_depth_m > 0 and not math.isnan(baseline_depth_m)):
            raise InputRangeError("baseline depth", baseline_depth_m, "> 0 metres, or inf")
        self.lens, self.geometry = lens, geometry
        self.source_geometry = source_geometry or geometry
        self.table = radial_distortion(lens) if distortion else None
        if library is None:
            library = open_library(lens, geometry, settings, grid, response=response, cache=cache,
                                   fit_depth_m=fit_depth_m, progress=progress)
        _check_library(library, geometry)
        self.library = library
        self.margin = self._scene_margin()
        m = self.margin
        self.work_geometry = geometry if m == 0 else replace(
            geometry, height=geometry.height + 2 * m, width=geometry.width + 2 * m,
            center_px=(geometry.center_px[0] + m, geometry.center_px[1] + m))
        self.baseline_depth_m = baseline_depth_m
        self.baseline = None if baseline_depth_m is None else self._fixed_map(baseline_depth_m)

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
        img, d = _check(image, depth, self.source_geometry)
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


def simulate(image, depth, lens, *, geometry: ImageGeometry | None = None,
             source_geometry: ImageGeometry | None = None, patch: int = 16,
             library: PSFLibrary | None = None, settings: PSFSettings | None = None, response=None,
             fixed_depth_m: float | None = None, distortion: bool = True,
             interpolation: str = DEFAULT_INTERPOLATION, noise: dict | None = None,
             seed: int | None = None, fft_backend: str | None = None, convolution: str = "fast",
             accelerator: str | None = None, blend: int | None = None) -> RenderResult:
    """Aberrated image of an all-in-focus ``image`` (H, W, 3) with metric
    ``depth`` (H, W) through ``lens``: :class:`LensSimulator` used once.
    geometry: the output frame on the sensor (default: the image spans the
    sensor's diagonal); source_geometry: the input's, if it differs.
    fft_backend: 'scipy' or 'numpy' (default: the fastest installed).
    convolution, accelerator, blend: as :class:`LensSimulator`."""
    check_convolution(convolution, accelerator)
    img, d = _check(image, depth, source_geometry)
    check_rgbd(img, None if fixed_depth_m is not None else d)
    geometry = geometry or source_geometry or ImageGeometry.full_sensor(lens, img.shape[0], img.shape[1])
    sim = LensSimulator(lens, geometry, source_geometry=source_geometry, library=library, settings=settings,
                        response=response, patch=patch, distortion=distortion, interpolation=interpolation,
                        fit_depth_m=d if library is None else None, fft_backend=fft_backend,
                        convolution=convolution, accelerator=accelerator, blend=blend)
    return sim._run(img, d, fixed_depth_m, noise, seed)


PRESCRIBED = "prescribed"     # BokehOptions(focus_m=PRESCRIBED): the sensor where the prescription puts it
LAYER_PAIRS = ((0, 0), (1, 1), (2, 2), (3, 0), (3, 1), (3, 2))   # a layer's colour, and its coverage per colour PSF


def _check_flag(name: str, value) -> None:
    if not isinstance(value, (bool, np.bool_)):
        raise InputRangeError(name, value, "True or False")


@dataclass(frozen=True)
class BokehOptions:
    """What :func:`bokeh` renders, checked when made (before any work).

    What is sharp, at least one of: ``keep`` (near, far) metres, 0 < near <=
    far, kept sharp (the paper's mask: identity PSF inside it), and
    ``focus_m``: the lens focused at this distance (metres, > 0, or inf), or
    :data:`PRESCRIBED` ('prescribed', the lens as its prescription stands:
    full physical defocus everywhere). Both: the lens focused at ``focus_m``
    and the range ``keep`` exactly sharp (the add-on's Kept Sharp). Invalid
    depths (NaN, 0, negative) are left sharp.

    geometry: the output frame on the sensor (default: the image spans the
    sensor's diagonal); source_geometry: the input's frame if it differs (as
    :func:`simulate`). distortion: also apply the lens's distortion (before
    the blur, as the lens does), the image resampled with ``interpolation``
    (one of ``distortion.INTERPOLATIONS``). patch: the patch size m (px, even,
    >= 2).

    occlusion: True (the occlusion-aware renderer): the scene split into
    ``n_layers`` depth layers (1 to 256, equal widths in diopters)
    composited back to front, each blurred with its own PSFs and carrying
    its blurred coverage, so a sharp subject does not bleed into a blurred
    background nor get a halo; False: the plain patch-wise blur.

    settings, response: the PSF settings and sensor spectral response
    (default: the shipped one) of the library opened when :func:`bokeh` is
    given none; settings' own focus, if any, must be ``focus_m``. fit_kernel:
    grow that library's kernel to hold the depth map's blur.

    convolution, rank_eps, fft_backend: :class:`ConvolveOptions`' method
    ('fast', 'windows' or 'lowrank'), low-rank tolerance (in [0, 0.5):
    each kernel within rank_eps in L1 of its own) and FFT backend
    (:meth:`convolve_options`).

    multires: the level rule's c (px, > 0) of the multi-resolution blur
    (``render.multires``): a patch of a depth layer (or of the plain blur)
    whose kernel's half-energy radius is >= c 2^s px is blurred at 1/2^s of
    the resolution, s <= ``max_level`` (0 to 4; None: ``multires.
    DEFAULT_MAX_LEVEL``), with ``coarse_patch``-px patches there (even, >=
    2); None: every layer at full resolution (the exact path). Not with
    convolution 'lowrank' (its groups are convolved by windows).
    """

    keep: tuple[float, float] | None = None
    focus_m: float | str | None = None
    geometry: ImageGeometry | None = None
    source_geometry: ImageGeometry | None = None
    distortion: bool = False
    interpolation: str = DEFAULT_INTERPOLATION
    patch: int = 16
    occlusion: bool = True
    n_layers: int = 12
    settings: PSFSettings | None = None
    response: object = None                    # psf.spectral.SpectralResponse, or None for the shipped one
    fit_kernel: bool = True
    convolution: str = "fast"
    rank_eps: float = 2e-2
    fft_backend: str | None = None
    multires: float | None = None
    max_level: int | None = None
    coarse_patch: int = 16

    def __post_init__(self):
        from . import multires as mr
        from .distortion import check_interpolation
        self._check_sharpness()
        for name in ("geometry", "source_geometry"):
            if getattr(self, name) is not None and not isinstance(getattr(self, name), ImageGeometry):
                raise InputRangeError(name, getattr(self, name), "an ImageGeometry, or None")
        for name in ("distortion", "occlusion", "fit_kernel"):
            _check_flag(name, getattr(self, name))
        check_interpolation(self.interpolation)
        check_patch(self.patch)
        if isinstance(self.n_layers, bool) or not isinstance(self.n_layers, (int, np.integer)) \
                or not 1 <= self.n_layers <= 256:
            raise InputRangeError("n_layers", self.n_layers, "an integer in [1, 256]")
        if self.convolution not in METHODS:
            raise InputRangeError("convolution", self.convolution, " or ".join(METHODS))
        self.convolve_options()                           # checks rank_eps and fft_backend
        if self.max_level is None:
            object.__setattr__(self, "max_level", mr.DEFAULT_MAX_LEVEL)
        mr.check_multires(self.multires, self.max_level, self.coarse_patch)
        if self.multires is not None and self.convolution == "lowrank":
            # the multi-resolution blur convolves its groups by windows ('fast' equals them to rounding)
            raise InputRangeError("multires with convolution", self.convolution,
                                  "'fast' or 'windows' (or multires None)")

    def _check_sharpness(self) -> None:
        keep, focus_m = self.keep, self.focus_m
        if keep is None and focus_m is None:
            raise InputRangeError("keep / focus", (keep, focus_m),
                                  f"a keep range, a focus distance or focus {PRESCRIBED!r} (or a keep range "
                                  "and a focus)")
        if keep is not None:
            if not (isinstance(keep, (tuple, list, np.ndarray)) and len(keep) == 2 and 0 < keep[0] <= keep[1]):
                raise InputRangeError("keep (--keep)", keep, "(near, far) with 0 < near <= far metres")
            object.__setattr__(self, "keep", tuple(keep))
        if focus_m is not None and (focus_m != PRESCRIBED if isinstance(focus_m, str) else not focus_m > 0):
            raise InputRangeError("focus", focus_m, f"a distance in metres (> 0, or inf) or {PRESCRIBED!r}")
        if self.settings is not None and not isinstance(self.settings, PSFSettings):
            raise InputRangeError("settings", self.settings, "PSFSettings, or None for the defaults")
        have = None if self.settings is None else self.settings.focus_distance_m
        if focus_m is not None and have is not None and have != self.focus_distance_m:
            raise InputRangeError("focus", focus_m, f"the settings' own focus_distance_m {have} m (give one, not two)")

    @property
    def focus_distance_m(self) -> float | None:
        """The PSFs' focus distance (m): ``focus_m``, None when prescribed or with ``keep``."""
        return None if self.focus_m in (None, PRESCRIBED) else float(self.focus_m)

    def library_settings(self) -> PSFSettings:
        """The PSF settings a library is opened with: ``settings``, focused at ``focus_m``."""
        s = self.settings or PSFSettings()
        return s if self.focus_m is None else replace(s, focus_distance_m=self.focus_distance_m)

    def convolve_options(self) -> ConvolveOptions:
        """The patch-wise convolution's options (``patch_convolve``)."""
        return ConvolveOptions(method=self.convolution, rank_eps=self.rank_eps, fft_backend=self.fft_backend)


def _check_library_focus(options: BokehOptions, library: PSFLibrary) -> None:
    """A given library must be focused where ``options`` say."""
    have = library.settings.focus_distance_m
    if options.focus_m is not None and have != options.focus_distance_m:
        raise InputRangeError("focus", options.focus_m,
                              f"the library's own focus ({have if have is not None else PRESCRIBED}"
                              f"{' m' if have is not None else ''}): open the library focused there, or "
                              "leave the focus out")


def bokeh(image, depth, lens, options: BokehOptions, *, library: PSFLibrary | None = None,
          cancelled=None, progress=None, layer_progress=None) -> RenderResult:
    """``image`` (H, W, 3) float32 linear light with ``depth`` (H, W) metres
    as ``lens`` would take it, kept sharp or focused as ``options`` say
    (:class:`BokehOptions`).

    library: the PSFs, at the image's pixel pitch, focused where the options
    say (without one it is opened from ``options.settings`` and
    ``options.response``). cancelled(): called before each layer's
    convolution; when it returns True, :class:`Cancelled` is raised.
    progress(done, total): called as PSF bins are computed;
    layer_progress(done, total): after each depth layer of the
    occlusion-aware renderer."""
    if not isinstance(options, BokehOptions):
        raise InputRangeError("options", options, "BokehOptions (what to keep sharp, and how to render)")
    if library is not None:
        _check_library_focus(options, library)
    scene = _bokeh_scene(image, depth, lens, options, library, progress)
    if not options.occlusion:
        return _plain_bokeh(scene, options, cancelled)
    return _layered_bokeh(scene, options, cancelled, layer_progress)


@dataclass
class _BokehScene:
    """bokeh's input on the sensor, with what both renderers read."""

    img: np.ndarray            # (H, W, 3) float32 on the sensor
    depth: np.ndarray          # (H, W) float64 metres on the sensor
    moved: bool                # resampled onto the sensor (then returned with the result)
    geometry: ImageGeometry
    library: PSFLibrary
    valid: np.ndarray          # (H, W) bool: a valid depth
    inv: np.ndarray            # (H, W) diopters, 0 at and beyond the library's far limit
    kept: np.ndarray           # (H, W) bool: in the keep range
    grow: int                  # px around a layer's pixels that its blur reaches (whole patches)
    info: dict

    def result(self, image: np.ndarray, info: dict, pm: PSFMap | None = None) -> RenderResult:
        return RenderResult(image, info, self.img if self.moved else None, pm,
                            depth=self.depth if self.moved else None)


def _bokeh_scene(image, depth, lens, options: BokehOptions, library: PSFLibrary | None, progress) -> _BokehScene:
    """The checked input moved onto the sensor (distortion, over-scan), and
    the library (opened if none is given)."""
    img, d = _check(image, depth, options.source_geometry)
    check_rgbd(img, d)
    source = options.source_geometry
    geometry = options.geometry or source or ImageGeometry.full_sensor(lens, img.shape[0], img.shape[1])
    check_within_sensor(geometry)
    moved = options.distortion or (source is not None and source != geometry)
    if moved:
        from .distortion import radial_distortion
        table = radial_distortion(lens) if options.distortion else None
        img, d, _ = on_sensor(img, d, lens, geometry, source_geometry=source, distortion=table,
                              interpolation=options.interpolation)
    if library is None:
        library = open_library(lens, geometry, options.library_settings(), response=options.response,
                               fit_depth_m=d if options.fit_kernel else None, progress=progress)
    _check_library(library, geometry)
    valid = valid_depth_mask(d)
    inv = np.where(valid & (d < library.grid.far_m), 1.0 / np.where(valid, d, 1.0), 0.0)
    keep = options.keep
    kept = np.zeros(d.shape, bool) if keep is None else valid & (d >= keep[0]) & (d <= keep[1])
    info = {"convolution": options.convolution, "occlusion": options.occlusion,
            "distortion": bool(options.distortion), "kept_pixels": int(kept.sum()),
            "invalid_depth_pixels": int((~valid).sum()), "multires": options.multires}
    # each layer (plain: each patch group) is blurred on its own patch-aligned
    # bounding box, grown by the kernel's reach: outside it the blur is zero
    m = options.patch
    grow = m * math.ceil((library.kernel_size // 2 + m) / m)
    return _BokehScene(img, d, moved, geometry, library, valid, inv, kept, grow, info)


def _plain_bokeh(sc: _BokehScene, options: BokehOptions, cancelled) -> RenderResult:
    """The plain patch-wise blur (``occlusion=False``)."""
    if cancelled is not None and cancelled():
        raise Cancelled("bokeh cancelled")
    if options.multires is not None:
        from . import multires as mr
        out, mi = mr.plain_blur(sc.img, sc.depth, sc.library, sc.geometry, options.patch, options.keep,
                                options.multires, options.max_level, options.coarse_patch, sc.grow,
                                fft_backend=options.fft_backend)
        return sc.result(out, dict(sc.info, **mi))
    pm = psf_map(sc.library, sc.geometry, sc.depth, options.patch, keep_range_m=options.keep)
    out = patch_convolve(sc.img, pm.kernels, options.patch, options.convolve_options(), identity=pm.identity)
    return sc.result(out, dict(sc.info, **pm.info), pm)


def _layers(inv: np.ndarray, valid: np.ndarray, n_layers: int):
    """Split valid pixels into depth layers of equal width in diopters,
    ordered far to near: list of boolean masks."""
    lo, hi = float(inv[valid].min()), float(inv[valid].max())
    if hi - lo < 1e-12:
        return [valid]
    edges = np.linspace(lo, hi, n_layers + 1)
    idx = np.clip(np.searchsorted(edges, inv, side="right") - 1, 0, n_layers - 1)
    return [valid & (idx == i) for i in range(n_layers) if (valid & (idx == i)).any()]


def _layer_order(sc: _BokehScene, n_layers: int) -> list[tuple[np.ndarray, bool]]:
    """The layers far to near, as (mask, sharp): the blurred depth layers,
    and the kept (sharp) pixels with the invalid ones as one layer at their
    depth (first when nothing is kept)."""
    sharp_mask = sc.kept | ~sc.valid
    blurred = sc.valid & ~sc.kept
    layers = _layers(sc.inv, blurred, n_layers) if blurred.any() else []
    order = [(float(sc.inv[m_].mean()), m_, False) for m_ in layers]
    if sharp_mask.any():
        order += [(float(sc.inv[sc.kept].mean()) if sc.kept.any() else -1.0, sharp_mask, True)]
    order.sort(key=lambda t: t[0])                        # far (small diopters) first
    return [(m_, s_) for _, m_, s_ in order]


def _box(mask: np.ndarray, m: int, grow: int) -> tuple[slice, slice]:
    """Rows and columns of ``mask``'s bounding box grown by ``grow`` px and
    aligned to the m-px patch grid (so its patches are the image's)."""
    h, w = mask.shape
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    y0, x0 = max(0, (rows[0] - grow) // m * m), max(0, (cols[0] - grow) // m * m)
    y1, x1 = min(h, -(-(rows[-1] + 1 + grow) // m) * m), min(w, -(-(cols[-1] + 1 + grow) // m) * m)
    return slice(int(y0), int(y1)), slice(int(x0), int(x1))


def _box_geometry(geometry: ImageGeometry, ys: slice, xs: slice) -> ImageGeometry:
    """The geometry of the box (ys, xs) of ``geometry``'s frame."""
    return replace(geometry, height=ys.stop - ys.start, width=xs.stop - xs.start,
                   center_px=(geometry.center_px[0] - ys.start, geometry.center_px[1] - xs.start))


def _layered_bokeh(sc: _BokehScene, options: BokehOptions, cancelled, layer_progress) -> RenderResult:
    """The occlusion-aware renderer: the layers, back to front, each layer's
    colour and coverage blurred alike and composited over what lies behind."""
    from . import multires as mr
    # ``col`` is the colour seen so far, un-premultiplied, where ``seen``: what
    # lies behind a layer where nothing farther was seen (hidden by a nearer
    # layer, or the farthest layer's own holes) takes the colour spread from
    # around it (normalised blur) instead of black: no dark seam where a
    # continuous surface crosses from one layer to the next, no dark halo.
    col = np.zeros_like(sc.img)
    seen = np.zeros(sc.img.shape[:2] + (1,), bool)
    order = _layer_order(sc, options.n_layers)
    table = None
    if options.multires is not None and sc.valid.any():
        sc.library.ensure(bins=sc.library.bins_needed(sc.depth[sc.valid], clamp_near=True))
        table = mr.radius_table(sc.library)
    info = dict(sc.info, layer_levels=[])            # multires: per layer, its patches at each level
    for n_done, (mask, is_sharp) in enumerate(order):
        if layer_progress is not None:
            layer_progress(n_done, len(order))
        if cancelled is not None and not is_sharp and cancelled():
            raise Cancelled("bokeh cancelled")
        ys, xs = _box(mask, options.patch, sc.grow if not is_sharp else 0)
        if is_sharp:
            a = mask[ys, xs][..., None]
            col[ys, xs] = np.where(a, sc.img[ys, xs], col[ys, xs])
            seen[ys, xs] |= a
            continue
        blurred, levels = _blur_layer(sc, options, mask, ys, xs, table)
        if levels is not None:
            info["layer_levels"].append([int((levels == s_).sum()) for s_ in range(options.max_level + 1)])
            if int(levels.max()) > 0:
                _clamp_overshoot(blurred, sc.img[ys, xs][mask[ys, xs]].max(axis=0))
        _composite(col, seen, ys, xs, blurred)
    if layer_progress is not None:
        layer_progress(len(order), len(order))
    info["layers"] = len(order)
    return sc.result(col, info)


def _blur_layer(sc: _BokehScene, options: BokehOptions, mask, ys: slice, xs: slice, table):
    """The layer ``mask``'s premultiplied colour and coverage, blurred on its
    box (ys, xs): (float32 (h, w, 6): three colours, then the coverage blurred
    with each colour's PSF; the multires levels of its patches, or None)."""
    from . import multires as mr
    af = mask[ys, xs][..., None].astype(np.float32)
    # each colour's coverage blurred with that colour's own PSF: the
    # normalisation of the composite is then exact for any colour fringe
    layer = np.concatenate([sc.img[ys, xs] * af, af], axis=-1)
    # every patch of the box gets the layer's kernel, also those holding
    # none of its pixels: a gather takes each output pixel's kernel from
    # its own patch, so an identity there would cut the blur spilling out
    # of the layer's patches (a bright light's halo ended after the tent)
    fill_inv = float(sc.inv[ys, xs][mask[ys, xs]].mean())
    d_layer = np.where(mask[ys, xs], sc.depth[ys, xs], np.inf if fill_inv <= 0 else 1.0 / fill_inv)
    sub = _box_geometry(sc.geometry, ys, xs)
    m = options.patch
    if options.multires is None:
        # a patch whose window (the patch and its blend margin) lies beyond
        # the kernel's reach of every layer pixel gathers nothing whatever its
        # kernel: it gets none (NaN depth: the identity, copying zeros)
        reach = sc.library.kernel_size // 2 + options.convolve_options().blend_px(m)
        d_layer[~_within_reach(mask[ys, xs], m, reach)] = np.nan
        pm = psf_map(sc.library, sub, d_layer, m, crop=True)
        blurred = patch_convolve(layer, pm.kernels, m, options.convolve_options(), identity=pm.identity,
                                 pairs=LAYER_PAIRS)
        return blurred, None
    every = np.ones(d_layer.shape, bool)                # every pixel has the layer's depth now
    no_copy = np.zeros((math.ceil(every.shape[0] / m), math.ceil(every.shape[1] / m)), bool)
    return mr.grouped_blur(layer, d_layer, every, no_copy, sc.library, sub, m, options.multires, options.max_level,
                           options.coarse_patch, sc.grow, pairs=LAYER_PAIRS, table=table,
                           fft_backend=options.fft_backend)


def _within_reach(mask: np.ndarray, m: int, reach_px: int) -> np.ndarray:
    """(H, W) bool: the pixels of the m-px patches that lie within
    ``reach_px`` of a pixel of ``mask`` (H, W), dilated at patch level
    (a square of patches, so it holds every pixel within the reach)."""
    h, w = mask.shape
    nph, npw = math.ceil(h / m), math.ceil(w / m)
    has = np.pad(mask, ((0, nph * m - h), (0, npw * m - w))).reshape(nph, m, npw, m).any(axis=(1, 3))
    grown = grow_square(has, math.ceil(reach_px / m))
    return np.repeat(np.repeat(grown, m, axis=0), m, axis=1)[:h, :w]


def _clamp_overshoot(blurred: np.ndarray, top: np.ndarray) -> None:
    """The cubic interpolation's over- and undershoot (a layer blurred at a
    coarser level): each colour kept within [0, its coverage x the layer's
    brightest value of it ``top``], as the exact blur of a non-negative layer
    is, and scaled with its coverage where that is clipped to 1 (a constant
    stays constant)."""
    raw = blurred[..., 3:]
    blurred[..., :3] = np.clip(blurred[..., :3], 0.0, np.maximum(raw, 0.0) * top) \
        * np.where(raw > 1.0, 1.0 / np.maximum(raw, 1.0), 1.0)


def _composite(col: np.ndarray, seen: np.ndarray, ys: slice, xs: slice, blurred: np.ndarray) -> None:
    """A blurred layer (colour premultiplied, coverage) over the colour seen
    behind it on its box; ``col`` and ``seen`` updated in place."""
    cover = np.clip(blurred[..., 3:], 0.0, 1.0)
    behind = seen[ys, xs]
    premultiplied = blurred[..., :3] + (1.0 - cover) * np.where(behind, col[ys, xs], 0.0)
    total = np.where(behind, 1.0, cover)
    seen[ys, xs] = (total > 1e-4).all(axis=-1, keepdims=True)
    col[ys, xs] = np.where(total > 1e-4, premultiplied / np.maximum(total, 1e-4), 0.0)
