"""RGB point spread functions of a lens at (field, depth), from real rays.

One PSF: a square grid of ``pupil_samples``^2 rays over the real stop (ray
aiming), traced at ``n_wavelengths`` wavelengths over the visible band,
deposited on the sensor's pixel grid (see ``deposit``) and weighted per
channel by the sensor's spectral response. The kernel is centred on the chief
ray's landing point at the design wavelength, so distortion stays out of the
blur. Each channel sums to 1; what that normalisation hides is reported
beside it: the vignetted fraction, the relative illumination and the energy
that falls outside the k x k window.
"""
from __future__ import annotations

import math
import warnings
from dataclasses import asdict, dataclass, field, replace

import numpy as np

from ..optics.aiming import (Aimed, aim_chief, chief_jacobian, chief_ray_sensor_y, launch, pupil_rays,
                             sources, stop_grid)
from ..errors import InputRangeError
from ..optics.errors import OpticsError
from ..optics.lens import Lens
from ..optics.paraxial import refocused
from ..optics.trace import trace
from .deposit import deposit
from .spectral import SpectralResponse, default_response, visible_wavelengths

# a kernel clipping more than this fraction of a channel's energy gets a warning
CLIP_WARNING = 0.01
# rays traced per batch (bounds memory: ~100 bytes per ray)
BATCH_RAYS = 750_000


# peak memory per traced ray (bytes): measured with `dcdi psf --rays 1024 / 2048
# --wavelengths 31` (float32: 113 and 109 B; float64 adds its wider coordinates)
BYTES_PER_RAY = {"float32": 120, "float64": 160}


def stop_ray_count(pupil_samples: int) -> int:
    """Rays of an N x N grid that fall in a circular stop (about pi / 4 N^2)."""
    return max(1, math.ceil(math.pi / 4.0 * pupil_samples * pupil_samples))


def psf_memory_bytes(settings: "PSFSettings", n_sources: int, n_wavelengths: int | None = None, *,
                     library_psfs: int = 0, map_kernels: int = 0) -> float:
    """Peak memory (bytes, an estimate) of computing ``n_sources`` PSFs with
    these settings: the rays of one batch, the kernels computed, the
    library's arrays (``library_psfs`` kernels) and an image's PSF map
    (``map_kernels`` kernels)."""
    w = settings.n_wavelengths if n_wavelengths is None else n_wavelengths
    per_source = stop_ray_count(settings.pupil_samples) * w
    sources_per_batch = min(max(1, n_sources), max(1, BATCH_RAYS // per_source))
    rays = BYTES_PER_RAY[settings.precision] * sources_per_batch * per_source
    k2 = 3 * settings.kernel_size ** 2
    # float32 kernels (computed, the library's, the map's: measured 2.07 GB peak for
    # simulate 1280 x 1920 at --kernel 129, estimated 2.45 GB) and a batch's float64 deposits
    kernels = 4.0 * k2 * (n_sources + library_psfs + map_kernels) + 8.0 * k2 * 3 * sources_per_batch
    return rays + kernels


def check_psf_memory(settings: "PSFSettings", n_sources: int, n_wavelengths: int | None = None, *,
                     library_psfs: int = 0, map_kernels: int = 0, available: int | None = None) -> None:
    """Refuse, before the work, PSFs that would not fit in memory, naming the
    options that size them (--rays, --wavelengths, --kernel)."""
    from ..memory import check_fits
    w = settings.n_wavelengths if n_wavelengths is None else n_wavelengths
    need = psf_memory_bytes(settings, n_sources, w, library_psfs=library_psfs, map_kernels=map_kernels)
    n = settings.pupil_samples
    what = (f"{n_sources} PSF{'s' if n_sources != 1 else ''} of --rays {n} (pupil_samples: {n} x {n} grid) x "
            f"--wavelengths {w} (n_wavelengths) x --kernel {settings.kernel_size} (kernel_size)"
            + (f" with a PSF map of {map_kernels} patches" if map_kernels else ""))
    check_fits(need, what, "lower --rays (memory grows as its square), --wavelengths or --kernel",
               available=available)


def _finite_positive(v) -> bool:
    """A real number (not a bool), finite and > 0."""
    return (isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, (bool, np.bool_))
            and math.isfinite(v) and v > 0)


class KernelTooSmallWarning(UserWarning):
    """The k x k kernel clips more than 1 % of a PSF's energy."""


@dataclass(frozen=True)
class PSFSettings:
    """How PSFs are computed. Lengths in mm, wavelengths in nm."""

    # Defaults chosen from `python -m lab report psf-accuracy` (docs/psf.md):
    # the wavelength count dominates the error, float32 costs nothing measurable
    kernel_size: int = 41
    pupil_samples: int = 64
    n_wavelengths: int = 31
    band_nm: tuple[float, float] = (400.0, 700.0)
    precision: str = "float32"          # ray tracing precision: float64 or float32
    oversample: int = 5                 # sub-pixel binning of ray positions (odd: pixel centres are bin centres)
    # Gaussian spread of each ray (px) on top of the pixel it lands in; 0 =
    # the ray histogram, which is what a sensor records (deposit.py derives
    # it); the paper's sqrt(2)/3 blurs by itself
    deposit_sigma_px: float = 0.0
    wavelength_nm: float | None = None   # one wavelength for all three channels (monochrome); None: the band
    pixel_pitch_mm: float | None = None  # default: the lens's sensor
    focus_distance_m: float | None = None  # None: the sensor where the prescription puts it

    def __post_init__(self):
        if self.kernel_size < 1 or self.kernel_size % 2 == 0:
            raise InputRangeError("kernel_size", self.kernel_size, "odd integer >= 1")
        if self.pupil_samples < 1:
            raise InputRangeError("pupil_samples", self.pupil_samples, ">= 1")
        if self.n_wavelengths < 1:
            raise InputRangeError("n_wavelengths", self.n_wavelengths, ">= 1")
        lo, hi = self.band_nm
        if not (300.0 <= lo < hi <= 1100.0):
            raise InputRangeError("band_nm", self.band_nm, "300 <= lo < hi <= 1100 nm")
        if self.precision not in ("float64", "float32"):
            raise InputRangeError("precision", self.precision, "'float64' or 'float32'")
        if self.oversample < 1:
            raise InputRangeError("oversample", self.oversample, ">= 1")
        if not (isinstance(self.deposit_sigma_px, (int, float)) and math.isfinite(self.deposit_sigma_px)
                and 0.0 <= self.deposit_sigma_px <= 3.0):
            raise InputRangeError("deposit_sigma_px", self.deposit_sigma_px, "0 <= sigma <= 3 pixels")
        if self.wavelength_nm is not None and not (200.0 < self.wavelength_nm < 2500.0):
            raise InputRangeError("wavelength_nm", self.wavelength_nm, "(200, 2500) nm, or None for the band")
        if self.pixel_pitch_mm is not None and not _finite_positive(self.pixel_pitch_mm):
            raise InputRangeError("pixel_pitch_mm", self.pixel_pitch_mm, "a finite number > 0 mm")

    def as_dict(self) -> dict:
        d = asdict(self)
        d["band_nm"] = list(self.band_nm)
        return d


def pixel_pitch_mm(lens: Lens, settings: PSFSettings) -> float:
    """The pixel pitch PSFs are sampled at: the setting, else the lens's sensor."""
    if settings.pixel_pitch_mm is not None:
        return settings.pixel_pitch_mm
    s = lens.sensor
    if s.pixel_pitch_mm:
        return s.pixel_pitch_mm
    if s.resolution_px:
        return 2.0 * s.semi_diagonal_mm / math.hypot(*s.resolution_px)
    raise OpticsError(f"{lens.path}: [sensor] has neither pixel_pitch_mm nor resolution_px; "
                      "give a pixel pitch (PSFSettings.pixel_pitch_mm / --pixel-pitch)")


# The largest kernel side (px) the sane range of a pitch allows for, where the
# kernel a run ends with is not known yet (a library grows its kernel to hold
# the blur): a recorded PSF setting holds at most 4095 px (psf.basis), and one
# 4095 px RGB kernel is 200 MB (a library of 1344 of them, 270 GB).
LARGEST_KERNEL_PX = 4095
# Airy's first dark ring: its diameter is AIRY_DIAMETER x wavelength x F-number
AIRY_DIAMETER = 2.44
# No F-number in air is below 0.5 (sin u' <= 1): the floor where a lens gives none
SMALLEST_F_NUMBER = 0.5


def shortest_wavelength_nm(settings: PSFSettings) -> float:
    """The shortest wavelength (nm) PSFs of ``settings`` are traced at (or above):
    the single wavelength, else the band's lower edge."""
    return float(settings.wavelength_nm if settings.wavelength_nm is not None else settings.band_nm[0])


def smallest_blur_mm(lens: Lens, settings: PSFSettings) -> float:
    """Diameter (mm) of the smallest spot ``lens`` can form with ``settings``:
    the diffraction-limited Airy disc (first dark ring) 2.44 lambda N at the
    shortest wavelength traced and the lens's working F-number for an object
    at infinity on the axis. A nearer object, a refocus or an off-axis field
    raise the working F-number (a larger disc) in any ordinary lens, and no
    real lens beats diffraction, so no PSF of the lens is smaller: a kernel
    that cannot span this spot cannot hold any of them. (The tracer's geometric spot is no
    floor: it ignores diffraction, and a well-corrected lens's is as small as
    its aberrations.) One real ray is traced (milliseconds)."""
    from ..optics.analysis import working_f_number
    from ..optics.paraxial import first_order
    wl = shortest_wavelength_nm(settings)
    try:              # (a refocus moves the sensor, not the marginal ray's angle: the lens as it is)
        n = working_f_number(lens, wl)
        if not (math.isfinite(n) and n > 0):             # the marginal ray failed: the paraxial figure
            n = first_order(lens, wl).f_number
    except OpticsError:
        n = SMALLEST_F_NUMBER
    n = max(abs(n), SMALLEST_F_NUMBER) if math.isfinite(n) else SMALLEST_F_NUMBER
    return AIRY_DIAMETER * wl * 1e-6 * n


def pixel_pitch_range_mm(lens: Lens, settings: PSFSettings, kernel_size: int) -> tuple[float, float]:
    """(smallest, largest) pixel pitch (mm) PSFs of ``lens`` may be sampled
    at with kernels of at most ``kernel_size`` px: a kernel must span the
    smallest spot of the lens (:func:`smallest_blur_mm`: below that every
    kernel clips nearly all its light), and a pixel may be at most the
    sensor's diagonal (a larger one holds the whole image: no geometry)."""
    sd = lens.sensor.semi_diagonal_mm
    return smallest_blur_mm(lens, settings) / kernel_size, (2.0 * sd if sd and math.isfinite(sd) else math.inf)


def check_pixel_pitch(lens: Lens, settings: PSFSettings, pitch_mm: float, *, kernel_size: int | None = None,
                      name: str = "pixel_pitch_mm") -> float:
    """Refuse, before any tracing, a pixel pitch (mm) outside
    :func:`pixel_pitch_range_mm` for kernels of at most ``kernel_size`` px
    (default: the settings'); ``name`` is the field or option named in the
    error. Every size derived from the pitch (kernel sizes, positions in
    pixels) is then a bounded number. Returns the pitch."""
    k = settings.kernel_size if kernel_size is None else int(kernel_size)
    if not _finite_positive(pitch_mm):
        raise InputRangeError(name, pitch_mm, "a finite number > 0 mm")
    lo, hi = pixel_pitch_range_mm(lens, settings, k)
    if not lo <= pitch_mm <= hi:
        raise InputRangeError(name, pitch_mm, pitch_range_text(lens, settings, k, lo, hi))
    return float(pitch_mm)


def pitch_range_text(lens: Lens, settings: PSFSettings, kernel_size: int, lo: float, hi: float) -> str:
    """The allowed range of :func:`check_pixel_pitch`, with why, on one line."""
    blur_um = lo * kernel_size * 1000.0
    return (f"{lo:.3g} to {hi:.4g} mm: a kernel of at most {kernel_size} px must span {lens.id}'s smallest "
            f"spot ({blur_um:.3g} um, the diffraction limit at {shortest_wavelength_nm(settings):g} nm), and a "
            "pixel cannot exceed the sensor's diagonal")


def focused_lens(lens: Lens, settings: PSFSettings) -> Lens:
    if settings.focus_distance_m is None:
        return lens
    return refocused(lens, settings.focus_distance_m)


def spectral_samples(settings: PSFSettings, response: SpectralResponse | None,
                     wavelength_nm: float | None = None):
    """(wavelengths (W,), channel weights (W, 3)); a single wavelength
    (``wavelength_nm`` or the settings') gives a monochromatic kernel (all
    three channels alike)."""
    if wavelength_nm is not None and settings.wavelength_nm is not None \
            and float(wavelength_nm) != float(settings.wavelength_nm):
        raise InputRangeError("wavelength_nm", wavelength_nm,
                              f"the settings' own wavelength {settings.wavelength_nm} nm (give one, not two)")
    if wavelength_nm is None:
        wavelength_nm = settings.wavelength_nm
    if wavelength_nm is not None:
        if not (200.0 < wavelength_nm < 2500.0):
            raise InputRangeError("wavelength_nm", wavelength_nm, "(200, 2500) nm")
        return np.array([float(wavelength_nm)]), np.ones((1, 3))
    wl = visible_wavelengths(settings.n_wavelengths, *settings.band_nm)
    resp = response if response is not None else default_response()
    return wl, resp.channel_weights(wl)


@dataclass
class PSFBatch:
    """PSFs of a set of sources (leading shape ``shape``)."""

    psf: np.ndarray                    # (..., 3, k, k) float32, channels sum to 1 (0 where zero_energy)
    energy_outside: np.ndarray         # (..., 3) fraction of the arriving energy outside k x k
    vignetted_fraction: np.ndarray     # (..., 3) fraction of the stop's rays that do not arrive
    relative_illumination: np.ndarray  # (...) image irradiance relative to an unvignetted axial beam, same depth
    chief_ray_height_mm: np.ndarray    # (...) design-wavelength chief ray on the sensor
    centroid_mm: np.ndarray            # (..., 3, 2) ray centroid per channel [x, y] on the sensor
    rms_radius_mm: np.ndarray          # (..., 3) ray RMS radius about the channel centroid
    zero_energy: np.ndarray            # (...) bool: no ray arrived (fully vignetted / aiming failed)
    kernel_size_needed: np.ndarray     # (...) odd k holding 99 % of the rays (0 where not checked)
    aim_residual_mm: float = 0.0
    timings_s: dict = field(default_factory=dict)


@dataclass
class RayKernels:
    """The kernels of a batch of sources from their rays (``rays_to_kernels``)."""

    psf: np.ndarray                    # (b, 3, k, k) float32
    energy_outside: np.ndarray         # (b, 3)
    vignetted_fraction: np.ndarray     # (b, 3)
    centroid_mm: np.ndarray            # (b, 3, 2)
    rms_radius_mm: np.ndarray          # (b, 3)
    kernel_size_needed: np.ndarray     # (b,) 0 where the kernel does not clip


def ray_spacing_px(nv: np.ndarray, sx: np.ndarray, sy: np.ndarray, s2: np.ndarray, pitch: float) -> np.ndarray:
    """(b,) the spacing (pixels) of each source's rays on the sensor: the
    area a wavelength's rays cover, taken as a uniform disc of their RMS
    radius (area 2 pi rms^2), shared among them; the mean over wavelengths
    weighted by their rays. From the per-wavelength ray count ``nv``, sums
    of x, y and x^2 + y^2 (b, W), in mm."""
    safe = np.where(nv > 0, nv, 1.0)
    var = np.maximum(s2 / safe - (sx / safe) ** 2 - (sy / safe) ** 2, 0.0)
    spacing = np.sqrt(2.0 * math.pi * var / safe) / pitch
    total = nv.sum(-1)
    return np.where(total > 0, (spacing * nv).sum(-1) / np.where(total > 0, total, 1.0), 0.0)


def rays_to_kernels(x: np.ndarray, y: np.ndarray, valid: np.ndarray, cy: np.ndarray, weights: np.ndarray,
                    n_p: int, pitch: float, settings: PSFSettings) -> RayKernels:
    """Kernels of ``b`` sources from their rays on the sensor: ``x``, ``y``
    (b, W, P) mm (float64; overwritten), ``valid`` (b, W, P) the rays that
    arrived, ``cy`` (b,) the kernel centre (the chief ray's height, mm),
    ``weights`` (W, 3) a ray's channel energy per wavelength, ``n_p`` the
    pupil samples launched per wavelength. The one place rays become kernels,
    whether they were traced or read from a ray map (``psf.raymap``)."""
    k = settings.kernel_size
    x_px, y_px = x / pitch, (y - cy[:, None, None]) / pitch
    # per-wavelength sums -> per-channel ray statistics (dead rays are finite: zero them)
    vf = valid.astype(np.float64)
    nv = vf.sum(-1)                                              # (b, W)
    x *= vf
    y *= vf
    sx, sy = x.sum(-1), y.sum(-1)
    s2 = (x * x + y * y).sum(-1)
    raw = deposit(x_px, y_px, valid, weights, k, settings.oversample, settings.deposit_sigma_px,
                  footprint_px=ray_spacing_px(nv, sx, sy, s2, pitch))
    del x_px, y_px
    arrived = nv @ weights                                       # (b, 3) energy that reached the sensor
    safe = np.where(arrived > 0, arrived, 1.0)
    cx_c, cy_c = (sx @ weights) / safe, (sy @ weights) / safe
    centroid = np.stack([cx_c, cy_c], -1)
    rms = np.sqrt(np.maximum((s2 @ weights) / safe - cx_c ** 2 - cy_c ** 2, 0.0))
    vig = 1.0 - arrived / (n_p * weights.sum(0))
    inside = raw.sum(axis=(-1, -2))
    outside = np.where(arrived > 0, 1.0 - inside / safe, 0.0)
    norm = np.where(inside > 0, inside, 1.0)[..., None, None]
    kern = np.where(inside[..., None, None] > 0, raw / norm, 0.0)
    # light that reached the sensor but fell wholly outside the kernel (a
    # kernel far too small, warned about): all of it at the chief ray's
    # pixel, so that each channel still sums to 1 (never a black kernel)
    lost = (inside <= 0) & (arrived > 0)
    if lost.any():
        kern[..., k // 2, k // 2] = np.where(lost, 1.0, kern[..., k // 2, k // 2])
    needed = np.zeros(len(cy), np.int64)
    for i in np.flatnonzero(outside.max(-1) > CLIP_WARNING):   # only where the kernel clips: a quantile per source
        v = valid[i]
        cheb = np.maximum(np.abs(x[i][v]), np.abs(y[i][v] - cy[i])) / pitch
        q = np.quantile(cheb, 0.99) if cheb.size else 0.0
        needed[i] = 2 * int(math.ceil(q + 1.5)) + 1
    return RayKernels(kern.astype(np.float32), outside, vig, centroid, rms, needed)


def _illumination_geometry(lens: Lens, aimed: Aimed, h_mm: np.ndarray) -> np.ndarray:
    """Unnormalised image irradiance per unit object radiance, from the chief
    rays (first order in pupil aberration): pupil area seen through the lens
    (1/|det J|), the obliquity factors and the object-to-image area ratio
    (sagittal p/h x tangential dp/dh); at infinity this is the cos^4 law with
    the lens's real pupil and distortion."""
    j = chief_jacobian(lens, aimed)
    det = np.abs(j[..., 0, 0] * j[..., 1, 1] - j[..., 0, 1] * j[..., 1, 0])
    dp = 1e-6
    a2 = aim_chief(lens, aimed.depth_mm, aimed.p + dp)
    h2, ok2 = chief_ray_sensor_y(lens, a2)
    dh_dp = (h2 - h_mm) / dp
    ok = aimed.ok & ok2 & (np.abs(dh_dp) > 0) & (det > 0)
    dh_dp = np.where(ok, dh_dp, 1.0)
    dp_dh = 1.0 / dh_dp
    sag = np.where(np.abs(h_mm) > 1e-9, aimed.p / np.where(np.abs(h_mm) > 1e-9, h_mm, 1.0), dp_dh)
    p2 = aimed.p * aimed.p
    inf = np.isinf(aimed.depth_mm)
    d = np.where(inf, 1.0, aimed.depth_mm)
    oy = -aimed.p * (d + aimed.z_ep)
    r2 = d * d + (aimed.v_chief - oy) ** 2
    finite_geo = d * d * (d + aimed.z_ep) ** 2 / (r2 * r2)
    geo = np.where(inf, 1.0 / (1.0 + p2) ** 2, finite_geo) * sag * dp_dh / np.where(ok, det, 1.0)
    return np.where(ok, geo, 0.0)


def compute_sources(lens: Lens, aimed: Aimed, settings: PSFSettings, wavelengths_nm, weights,
                    *, progress=None, reference_geometry=None) -> PSFBatch:
    """PSFs of every source in ``aimed`` (any shape), batched over rays.

    ``weights`` (W, 3) are the channel energies of one ray per wavelength.
    ``progress(n_done, n_total)`` is called after each batch."""
    import time

    lens = focused_lens(lens, settings)
    k = settings.kernel_size
    pitch = pixel_pitch_mm(lens, settings)
    dtype = np.dtype(settings.precision)
    wl = np.asarray(wavelengths_nm, dtype=np.float64)
    weights = np.asarray(weights, dtype=np.float64)
    targets = stop_grid(lens, settings.pupil_samples)
    n_p = len(targets)
    shape = aimed.p.shape
    flat = Aimed(aimed.depth_mm.ravel(), aimed.p.ravel(), aimed.v_chief.ravel(), aimed.ok.ravel(), aimed.z_ep)
    n = flat.p.size
    per_batch = max(1, BATCH_RAYS // (n_p * wl.size))
    check_psf_memory(settings, int(np.prod(aimed.p.shape)), wl.size)
    # the sane range before a ray is traced: positions in pixels (and the
    # kernel sizes derived from them) stay bounded numbers; callers that know
    # the largest kernel of their run check the pitch against it first
    check_pixel_pitch(lens, settings, pitch, kernel_size=max(k, LARGEST_KERNEL_PX))
    psf = np.zeros((n, 3, k, k), np.float32)
    outside = np.zeros((n, 3))
    vig = np.ones((n, 3))
    centroid = np.zeros((n, 3, 2))
    rms = np.zeros((n, 3))
    needed = np.zeros(n, np.int64)
    chief_h = np.zeros(n)
    times = {"aim": 0.0, "trace": 0.0, "deposit": 0.0}
    resid = 0.0
    for start in range(0, n, per_batch):
        sl = slice(start, min(start + per_batch, n))
        sub = Aimed(flat.depth_mm[sl], flat.p[sl], flat.v_chief[sl], flat.ok[sl], flat.z_ep)
        t0 = time.perf_counter()
        o, d, status, r = pupil_rays(lens, sub, targets)
        resid = max(resid, r)
        oc, dc = launch(lens, sub.depth_mm, sub.p, 0.0, sub.v_chief, sub.z_ep)
        cb = trace(lens, oc, dc, lens.wavelength_nm, apertures=False)
        cy = np.where(cb.valid & sub.ok, cb.position_mm[..., 1], 0.0)
        chief_h[sl] = cy
        t1 = time.perf_counter()
        b = trace(lens, o[:, None], d[:, None], wl[None, :, None], dtype=dtype, status=status[:, None])
        t2 = time.perf_counter()
        x = b.position_mm[..., 0].astype(np.float64)
        y = b.position_mm[..., 1].astype(np.float64)
        kern = rays_to_kernels(x, y, b.valid, cy, weights, n_p, pitch, settings)
        psf[sl], outside[sl], vig[sl], centroid[sl], rms[sl] = (kern.psf, kern.energy_outside,
                                                               kern.vignetted_fraction, kern.centroid_mm,
                                                               kern.rms_radius_mm)
        needed[sl] = kern.kernel_size_needed
        times["aim"] += t1 - t0
        times["trace"] += t2 - t1
        times["deposit"] += time.perf_counter() - t2
        if progress:
            progress(sl.stop, n)
    outside = np.clip(outside, 0.0, 1.0)
    vig = np.clip(vig, 0.0, 1.0)
    zero = ~(vig < 1.0).any(-1) | ~flat.ok
    geo = _illumination_geometry(lens, flat, chief_h)
    trans = 1.0 - vig[:, 1]
    ri = geo * trans
    ref = reference_geometry
    if ref is None:
        ref_aim = aim_chief(lens, flat.depth_mm, np.zeros(n))
        ref = _illumination_geometry(lens, ref_aim, np.zeros(n))
    ri = np.where(ref > 0, ri / np.where(ref > 0, ref, 1.0), 0.0)
    return PSFBatch(psf.reshape(shape + (3, k, k)), outside.reshape(shape + (3,)),
                    vig.reshape(shape + (3,)), ri.reshape(shape), chief_h.reshape(shape),
                    centroid.reshape(shape + (3, 2)), rms.reshape(shape + (3,)),
                    zero.reshape(shape), needed.reshape(shape), resid, times)


def clip_message(energy_outside, kernel_size_needed, k: int, what: str = "PSF") -> str | None:
    """The warning of kernels that clip more than :data:`CLIP_WARNING` of a
    channel's energy (``energy_outside``: fractions, any shape;
    ``kernel_size_needed``: px, 0 where not measured), or None where none
    does. One text for the PSFs computed now and the same PSFs served later
    (``psf.library``)."""
    outside = np.asarray(energy_outside, dtype=np.float64)
    worst = float(outside.max()) if outside.size else 0.0
    if not worst > CLIP_WARNING:
        return None
    needed = np.asarray(kernel_size_needed)
    need = int(needed.max()) if needed.size else 0
    return (f"{what}: the {k} x {k} kernel clips up to {worst:.1%} of a channel's energy; "
            f"a kernel of {need} x {need} holds 99 % of the rays")


def warn_if_clipped(batch: PSFBatch, k: int, what: str = "PSF") -> None:
    text = clip_message(batch.energy_outside, batch.kernel_size_needed, k, what)
    if text:
        warnings.warn(text, KernelTooSmallWarning, stacklevel=3)


def psf(lens: Lens, *, depth_m: float, field: float | None = None, angle_deg: float | None = None,
        settings: PSFSettings | None = None, response: SpectralResponse | None = None,
        wavelength_nm: float | None = None) -> PSFBatch:
    """The RGB PSF of one field (normalised image height, or object-space angle
    in degrees) at one depth (metres from the first vertex, ``inf`` allowed).

    Returns a :class:`PSFBatch` of shape () : ``.psf`` is (3, k, k) float32.
    A field the lens cannot image comes back with ``zero_energy`` True and a
    zero kernel (never NaN)."""
    settings = settings or PSFSettings()
    lens_f = focused_lens(lens, settings)
    kw = {"field": [field]} if field is not None else {"angle_deg": [angle_deg]}
    aimed = sources(lens_f, [depth_m], **kw)                 # shape (1, 1)
    wl, w = spectral_samples(settings, response, wavelength_nm)
    batch = compute_sources(lens_f, aimed, replace(settings, focus_distance_m=None), wl, w)
    out = PSFBatch(*(getattr(batch, f)[0, 0] for f in ("psf", "energy_outside", "vignetted_fraction",
                                                     "relative_illumination", "chief_ray_height_mm",
                                                     "centroid_mm", "rms_radius_mm", "zero_energy",
                                                     "kernel_size_needed")),
                   batch.aim_residual_mm, batch.timings_s)
    warn_if_clipped(out, settings.kernel_size)
    return out

