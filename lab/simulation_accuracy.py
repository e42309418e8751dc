"""`python -m lab report simulation-accuracy`: patch-wise rendering against references.

1. Simulation: the patch-wise depth-aware simulation against a per-pixel
   reference (every pixel convolved with its own PSF, for its own field,
   azimuth and depth: the limit of patch size 1) on the synthetic scene with
   depth edges, for patch sizes 8 / 16 / 32 / 64 and kernel sizes, with
   times. The image is a crop at the sensor's own pixel pitch, off axis
   (fields about 0.3 to 0.6), so that the PSFs are large and vary across it.
2. Bokeh at depth discontinuities: a sharp subject (kept range) in front of a
   blurred background. Ground truth: the subject pasted over the background
   scene rendered *without* the subject (which the synthetic scene knows).
   Plain patch-wise blur and occlusion-aware layers are compared with it in
   a band around the subject.
"""
from __future__ import annotations

import math
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from dcdi_core.atomic import write_text
from dcdi_core.optics.lens import load_lens
from dcdi_core.psf.compute import PSFSettings
from dcdi_core.psf.library import LibraryGrid, PSFLibrary
from dcdi_core.render.convolve import ConvolveOptions, patch_convolve
from dcdi_core.render.geometry import ImageGeometry
from dcdi_core.render.psfmap import psf_map, rotate_radial_kernels
from dcdi_core.render.bokeh import BokehOptions, bokeh
from dcdi_core.render.synthetic import synthetic_rgbd


def psnr(a, b, mask=None) -> float:
    d = (a - b) ** 2
    mse = float(d[mask].mean() if mask is not None else d.mean())
    return math.inf if mse == 0 else 10 * math.log10(1.0 / mse)


def per_pixel_reference(img, depth, library, geometry, chunk: int = 1024) -> np.ndarray:
    """Every pixel its own PSF (field, azimuth, depth), gather form, reflect borders."""
    h, w, _ = img.shape
    k = library.kernel_size
    r = k // 2
    pad = np.pad(img, ((r, r), (r, r), (0, 0)), mode="reflect")
    rows, cols = np.mgrid[0:h, 0:w]
    rows, cols = rows.ravel(), cols.ravel()
    field = np.minimum(geometry.field(rows, cols), 1.0)
    d = depth.ravel().astype(np.float64)
    d = np.where(d >= library.grid.far_m, np.inf, np.maximum(d, library.grid.near_m))
    vec = np.stack([rows - geometry.center_px[0], cols - geometry.center_px[1]], -1).astype(np.float64)
    norm = np.hypot(vec[:, 0], vec[:, 1])
    outward = np.where(norm[:, None] > 1e-9, vec / np.maximum(norm, 1e-12)[:, None], [1.0, 0.0])
    out = np.empty((h * w, 3), np.float32)
    dy, dx = np.meshgrid(np.arange(k), np.arange(k), indexing="ij")
    for s in range(0, h * w, chunk):
        sl = slice(s, min(s + chunk, h * w))
        kern = rotate_radial_kernels(library.at(field[sl], d[sl]), outward[sl])     # (n, 3, k, k)
        # out(y, x) = sum_t K(t) I(y - (t - r)): the padded input at (y + 2r - ty)
        yy = rows[sl, None, None] + 2 * r - dy
        xx = cols[sl, None, None] + 2 * r - dx
        nb = pad[yy, xx]                                                               # (n, k, k, 3)
        out[sl] = np.einsum("nckl,nklc->nc", kern, nb)
    return out.reshape(h, w, 3)


class SmoothScene:
    """An analytic, band-limited RGB-D scene on the ideal (pinhole) image
    plane, for references that must not depend on any resampling: colour
    and depth at any sensor position (mm from the axis). Colour: sinusoids
    of periods 4-24 px and soft-edged bright discs, in [0, 1]; depth: a
    ramp in inverse depth from ``near_m`` to ``far_m`` along x, smooth."""

    def __init__(self, pitch_mm: float, span_mm: tuple[float, float, float, float], seed: int = 0,
                 near_m: float = 0.8, far_m: float = 8.0):
        rng = np.random.default_rng(seed)
        self.pitch = pitch_mm
        self.y0, self.y1, self.x0, self.x1 = span_mm
        n = 6
        period = rng.uniform(4.0, 24.0, n) * pitch_mm
        angle = rng.uniform(0, math.pi, n)
        self.k = np.stack([np.sin(angle), np.cos(angle)], -1) * (2 * math.pi / period)[:, None]   # (n, 2) rad/mm
        self.phase = rng.uniform(0, 2 * math.pi, n)
        self.amp = rng.uniform(0.2, 1.0, (n, 3)) / n
        self.discs = [(rng.uniform(self.y0, self.y1), rng.uniform(self.x0, self.x1),
                       rng.uniform(3, 8) * pitch_mm, rng.uniform(0.5, 1.0, 3)) for _ in range(4)]
        self.near, self.far = near_m, far_m

    def colour(self, y_mm, x_mm) -> np.ndarray:
        y, x = np.asarray(y_mm, np.float64), np.asarray(x_mm, np.float64)
        arg = y[..., None] * self.k[:, 0] + x[..., None] * self.k[:, 1] + self.phase       # (..., n)
        c = 0.45 + 0.5 * np.sin(arg) @ self.amp                                             # (..., 3)
        for cy, cx, r, col in self.discs:     # soft edge, 1.5 px wide: band-limited enough to sample
            t = 0.5 * (1 - np.tanh((np.hypot(y - cy, x - cx) - r) / (1.5 * self.pitch)))
            c = c * (1 - 0.6 * t[..., None]) + 0.6 * t[..., None] * col
        return c

    def depth(self, y_mm, x_mm) -> np.ndarray:
        x = np.asarray(x_mm, np.float64)
        u = np.clip((x - self.x0) / max(self.x1 - self.x0, 1e-9), 0.0, 1.0) + 0.0 * np.asarray(y_mm)
        return 1.0 / (1.0 / self.near + u * (1.0 / self.far - 1.0 / self.near))

    def on_grid(self, geometry):
        """(image (H, W, 3) float32, depth (H, W) float32) sampled at the pixel centres of ``geometry``."""
        rows = np.arange(geometry.height, dtype=np.float64)[:, None]
        cols = np.arange(geometry.width, dtype=np.float64)[None, :]
        y = (rows - geometry.center_px[0]) * geometry.pixel_pitch_mm + 0.0 * cols
        x = (cols - geometry.center_px[1]) * geometry.pixel_pitch_mm + 0.0 * rows
        return self.colour(y, x).astype(np.float32), self.depth(y, x).astype(np.float32)


def distorted_reference(scene: SmoothScene, library, geometry, table, chunk: int = 512) -> np.ndarray:
    """What the sensor records, pixel by pixel, independently of any warp or
    patch: output pixel i (real position x_i on ``geometry``) is
    sum_t K_i(t) A(ideal(x_i - t)), where K_i is the PSF of x_i's own real
    field, azimuth and depth (the depth of the scene point imaged there),
    t runs over the kernel's pixels, and the sharp image A is evaluated
    exactly at the ideal position that the distortion ``table`` maps to
    the real position x_i - t."""
    h, w = geometry.height, geometry.width
    k = library.kernel_size
    r = k // 2
    pitch = geometry.pixel_pitch_mm
    rows, cols = np.mgrid[0:h, 0:w]
    rows, cols = rows.ravel(), cols.ravel()
    ry = (rows - geometry.center_px[0]) * pitch
    rx = (cols - geometry.center_px[1]) * pitch

    def ideal(yy, xx):
        rr = np.hypot(yy, xx)
        scale = np.where(rr > 0, table.ideal_from_real(rr) / np.where(rr > 0, rr, 1.0), 1.0)
        return yy * scale, xx * scale

    iy, ix = ideal(ry, rx)
    d = scene.depth(iy, ix)
    d = np.where(d >= library.grid.far_m, np.inf, np.maximum(d, library.grid.near_m))
    field = np.minimum(geometry.field(rows, cols), 1.0)
    vec = np.stack([rows - geometry.center_px[0], cols - geometry.center_px[1]], -1).astype(np.float64)
    norm = np.hypot(vec[:, 0], vec[:, 1])
    outward = np.where(norm[:, None] > 1e-9, vec / np.maximum(norm, 1e-12)[:, None], [1.0, 0.0])
    ty, tx = np.meshgrid(np.arange(k) - r, np.arange(k) - r, indexing="ij")
    out = np.empty((h * w, 3), np.float32)
    for s in range(0, h * w, chunk):
        sl = slice(s, min(s + chunk, h * w))
        kern = rotate_radial_kernels(library.at(field[sl], d[sl]), outward[sl])     # (n, 3, k, k)
        sy = ry[sl, None, None] - ty * pitch
        sx = rx[sl, None, None] - tx * pitch
        a = scene.colour(*ideal(sy, sx))                                              # (n, k, k, 3)
        out[sl] = np.einsum("nckl,nklc->nc", kern, a)
    return out.reshape(h, w, 3)


def distortion_case(lens, h: int, w: int, field_centre: float = 0.75):
    """A crop of h x w pixels at the lens's own pixel pitch centred at
    ``field_centre`` on the diagonal (where distortion squeezes the PSFs),
    and an over-scan source frame covering every ideal position its pixels
    and kernels need: (geometry, source_geometry, table, scene)."""
    from dcdi_core.render.distortion import radial_distortion

    pitch = lens.sensor.pixel_pitch_mm or 0.0122
    sd = lens.sensor.semi_diagonal_mm
    off = field_centre * sd / pitch / math.sqrt(2)
    geom = ImageGeometry.from_pixel_pitch(lens, h, w, pitch, center_px=((h - 1) / 2 + off, (w - 1) / 2 + off))
    table = radial_distortion(lens)
    # the ideal positions of the crop's corners, with a margin for the kernels and the warp's taps
    margin = 48
    ys = np.array([-margin, h - 1 + margin], float) - geom.center_px[0]
    xs = np.array([-margin, w - 1 + margin], float) - geom.center_px[1]
    yy, xx = np.meshgrid(ys * pitch, xs * pitch, indexing="ij")
    rr = np.hypot(yy, xx)
    scale = table.ideal_from_real(rr) / rr
    iy, ix = (yy * scale).ravel() / pitch, (xx * scale).ravel() / pitch
    lo_y, hi_y = math.floor(min(iy.min(), ys.min())), math.ceil(max(iy.max(), ys.max()))
    lo_x, hi_x = math.floor(min(ix.min(), xs.min())), math.ceil(max(ix.max(), xs.max()))
    src = ImageGeometry.from_pixel_pitch(lens, hi_y - lo_y + 1, hi_x - lo_x + 1, pitch,
                                         center_px=(float(-lo_y), float(-lo_x)))
    span = (lo_y * pitch, hi_y * pitch, lo_x * pitch, hi_x * pitch)
    return geom, src, table, SmoothScene(pitch, span, seed=1)


def blur_then_warp(img, depth, lens, library, geometry, source_geometry, table, patch=16,
                   interpolation="linear"):
    """The former order: PSFs looked up at the pinhole positions, the
    distortion warp afterwards (which squeezes each blur by the local
    stretch of the distortion)."""
    from dcdi_core.render.distortion import distort

    pm = psf_map(library, source_geometry, depth, patch)
    blurred = patch_convolve(img, pm.kernels, patch, identity=pm.identity)
    return distort(blurred, lens, geometry, distortion=table, source_geometry=source_geometry,
                   interpolation=interpolation)


def _edge_band(depth, width: int = 6):
    """Pixels within ``width`` of a depth edge (ratio > 1.5 between neighbours)."""
    inv = np.where(depth > 0, 1.0 / np.maximum(depth, 1e-9), 0.0)
    e = np.zeros(depth.shape, bool)
    e[:, 1:] |= np.abs(inv[:, 1:] - inv[:, :-1]) > 0.1
    e[1:, :] |= np.abs(inv[1:, :] - inv[:-1, :]) > 0.1
    band = e.copy()
    for _ in range(width):
        b = band.copy()
        b[1:] |= band[:-1]
        b[:-1] |= band[1:]
        b[:, 1:] |= band[:, :-1]
        b[:, :-1] |= band[:, 1:]
        band = b
    return band


ROTATION_CASES = ((0.05, 0.05, 0.0), (0.2, 0.1, 0.0), (0.4, 0.3, 0.0), (0.7, 0.5, 0.0), (1.0, 0.7, 0.0),
                  (2.0, 1.0, 0.0), (3.0, 1.5, 0.0), (1.0, 0.5, 2.0), (5.0, 5.0, 0.0))


def rotation_rows(*, quick: bool, seed: int = 0) -> list:
    """Kernel rotation against rotated rays: Gaussian ray clouds (sigma
    along x across the radial axis, px; offset along it, px) histogrammed
    along the radial line, rotated by the kernel rotation, against the
    histogram of the same rays rotated exactly; relative L1 at 30 and 45
    degrees, with and without the centre's peak kept in place."""
    rng = np.random.default_rng(seed)
    k, n = 41, (200_000 if quick else 2_000_000)
    r = k // 2

    def hist(y, x):
        h, _, _ = np.histogram2d(y, x, bins=k, range=[[-r - 0.5, r + 0.5], [-r - 0.5, r + 0.5]])
        return (h / h.sum()).astype(np.float32)

    rows = []
    for sa, sc, off in (ROTATION_CASES[::2] if quick else ROTATION_CASES):
        along, across = rng.normal(off, sa, n), rng.normal(0.0, sc, n)
        src = np.broadcast_to(hist(along, across), (1, 3, k, k)).copy()
        errs = []
        for deg in (30.0, 45.0):
            ur, uc = math.cos(math.radians(deg)), math.sin(math.radians(deg))
            truth = hist(along * ur - across * uc, along * uc + across * ur)
            for keep in (False, True):
                got = rotate_radial_kernels(src, np.array([[ur, uc]]), keep_peak=keep)[0, 1]
                errs.append(float(np.abs(got - truth).sum()))
        rows.append((sa, sc, off, *errs))
    return rows


def lowrank_rows(img, pm, library, geom, depth, ref, exact, eps_list=(0.005, 0.02, 0.05)) -> list:
    """Windows (the default) and the low-rank method at each rank eps, with the
    default support crop: PSNR against the per-pixel reference, max abs
    difference from the exact patch-wise result, time (PSF map included)."""
    rows = []
    for method, eps in [("windows", 0.0)] + [("lowrank", e) for e in eps_list]:
        t = time.perf_counter()
        pmd = psf_map(library, geom, depth, 16)
        res = patch_convolve(img, pmd.kernels, 16, ConvolveOptions(method=method, rank_eps=eps), identity=pmd.identity)
        dt = time.perf_counter() - t
        rows.append((method, eps, psnr(res, ref), float(np.abs(res - exact).max()), dt))
        print(f"  {method} rank eps {eps:g}: PSNR {rows[-1][2]:6.2f} dB, max |diff| vs exact {rows[-1][3]:.2e}, "
              f"{dt:.2f} s", flush=True)
    return rows


MULTIRES_RULES = ((8.0, 2), (4.0, 2), (3.0, 2), (2.0, 2))


def multires_rows(*, quick: bool, rules=MULTIRES_RULES) -> tuple[list, str]:
    """The multi-resolution bokeh (``BokehOptions(multires=c, max_level=)``) against
    the exact path (multires None) at the pitch of a 1280 x 1920 image on
    6P's sensor, where the defocus kernels are 10-30 px wide: the whole
    frame (PSNR and max abs difference against the exact result, peak 1),
    and for the occlusion-aware renderer the depth edge (PSNR in 8 px around
    the kept subject against the truth: the subject pasted over the
    subject-free background rendered by the exact path); times alternated
    with the exact path's in one process, wall and CPU seconds (the exact
    path's best of its runs). quick: a 320 x 480 crop (fields
    0.1-0.5) and a cheaper library; else the full 1280 x 1920 frame and the
    bench's library (PSFSettings defaults, 41 px kernels)."""
    from dcdi_core.psf.sources import open_library
    p6 = load_lens("6p")
    full = ImageGeometry.full_sensor(p6, 1280, 1920)
    if quick:
        h, w = 320, 480
        geom = ImageGeometry.from_pixel_pitch(p6, h, w, full.pixel_pitch_mm, center_px=(-100.0, 100.0))
        settings = PSFSettings(pupil_samples=32, n_wavelengths=15)
    else:
        h, w, geom, settings = 1280, 1920, full, None
    img, depth = synthetic_rgbd(h, w, seed=0)
    img_bg, depth_bg = synthetic_rgbd(h, w, seed=0, disk=False)
    lib = open_library(p6, geom, settings)
    lib.ensure(np.concatenate([depth.ravel(), depth_bg.ravel()]), clamp_near=True)
    keep = (1.1, 1.3)
    subject = (depth >= keep[0]) & (depth <= keep[1])
    ring = _edge_band(np.where(subject, 1.0, 100.0), width=8) & ~subject
    behind = bokeh(img_bg, depth_bg, p6, BokehOptions(keep=keep, geometry=geom), library=lib).image
    truth = np.where(subject[..., None], img, behind)
    peak = float(img.max())
    rows = []

    def timed(fn):
        """(result, wall s, CPU s of this process: what the load of other jobs changes least)"""
        t, c = time.perf_counter(), time.process_time()
        out = fn()
        return out, time.perf_counter() - t, time.process_time() - c

    for occ in (True, False):
        exact, t_exact, c_exact = timed(lambda: bokeh(img, depth, p6,
                                                      BokehOptions(keep=keep, geometry=geom, occlusion=occ),
                                                      library=lib).image)
        edge_exact = psnr(exact / peak, truth / peak, ring) if occ else math.nan
        first = len(rows)
        for c, max_level in rules:
            opts = BokehOptions(keep=keep, geometry=geom, occlusion=occ, multires=c, max_level=max_level)
            res, dt, dc = timed(lambda: bokeh(img, depth, p6, opts, library=lib))
            _, te, ce = timed(lambda: bokeh(img, depth, p6, BokehOptions(keep=keep, geometry=geom, occlusion=occ),
                                            library=lib))                                  # alternated
            t_exact, c_exact = min(t_exact, te), min(c_exact, ce)
            lv = res.info["layer_levels"] if occ else res.info["multires_patches_per_level"]
            edge = psnr(res.image / peak, truth / peak, ring) if occ else math.nan
            rows.append((occ, c, max_level, psnr(res.image / peak, exact / peak),
                         float(np.abs(res.image - exact).max()) / peak, edge, dt, dc, ce,
                         "patches per level 0/1/..: " + (" ".join("/".join(map(str, q)) for q in lv) if occ
                                                         else "/".join(map(str, lv)))))
            print(f"  multires {'layered' if occ else 'plain'} c {c:g} max level {max_level}: PSNR vs exact "
                  f"{rows[-1][3]:6.2f} dB, max |diff| {rows[-1][4]:.4f}, around the subject {edge:6.2f} dB, "
                  f"{dt:.2f} s, {dc:.2f} CPU s (exact alternated: {te:.2f} s, {ce:.2f} CPU s)", flush=True)
        rows.insert(first, (occ, "exact (None)", "-", math.inf, 0.0, edge_exact, t_exact, c_exact, c_exact,
                            "all at 0"))
    where = (f"6P, {h} x {w} at {geom.pixel_pitch_mm * 1000:.2f} um (the pitch of 1280 x 1920 on its sensor; fields "
             f"{geom.field(h // 2, w // 2):.2f} at the centre to {geom.max_field:.2f}), kernel {lib.kernel_size} px, "
             f"keep {keep[0]}-{keep[1]} m, load average {__import__('os').getloadavg()[0]:.1f}")
    return rows, where


def fast_path_rows(img, library, geom, depth, ref, blends=(6, 4)) -> list:
    """The simulation's fast paths (issue 15) against the windows method with
    the same settings (the exact form they are tested against) and against
    the per-pixel reference: PSF map + convolution time, PSNR vs per-pixel,
    max abs difference from windows. The fast layout and torch compute the
    same thing (differences are float32 rounding); a smaller blend is an
    approximation of its own (its PSNR is the row to read)."""
    from dcdi_core.render import accel_torch

    cases = [("windows (exact form)", dict(method="windows"), dict(method="exact")),
             ("fast", dict(method="fast"), {}),
             ("fast, numpy float64 FFT", dict(method="fast", fft_backend="numpy"), {})]
    if accel_torch.available():
        cases.append(("fast, torch", dict(method="fast", accelerator="torch"), dict(accelerator="torch")))
    cases += [(f"fast, blend {b} px", dict(method="fast", blend=b), {}) for b in blends]
    rows, base = [], None
    for name, conv_kw, map_kw in cases:
        dt = math.inf
        for _ in range(2):                     # best of 2: the first torch call also starts torch
            t = time.perf_counter()
            pm = psf_map(library, geom, depth, 16, **map_kw)
            res = patch_convolve(img, pm.kernels, 16, ConvolveOptions(**conv_kw), identity=pm.identity)
            dt = min(dt, time.perf_counter() - t)
        base = res if base is None else base
        rows.append((name, psnr(res, ref), float(np.abs(res - base).max()), dt))
        print(f"  {name}: PSNR {rows[-1][1]:6.2f} dB, max |diff| vs windows {rows[-1][2]:.2e}, {dt:.2f} s",
              flush=True)
    return rows


def deposit_rows(lens, img, depth, geom, *, quick: bool) -> tuple[list, str]:
    """Deposit width against ray count: the patch-wise simulation with each
    library against the same with a many-ray reference library (rays into
    the pixel they land in); library build time per PSF."""
    grid = LibraryGrid(n_fields=16, n_depths=5)
    base = PSFSettings(pupil_samples=64, n_wavelengths=15 if quick else 31, pixel_pitch_mm=geom.pixel_pitch_mm)
    ref_rays, rays = (64, (16, 32)) if quick else (256, (32, 64, 128))
    sigmas = (0.0, math.sqrt(2) / 3) if quick else (0.0, 0.25, math.sqrt(2) / 3)

    def render(settings):
        lib = PSFLibrary.open(lens, settings, grid, cache=False)
        t = time.perf_counter()
        lib.ensure(depth, clamp_near=True)
        n = int(lib.computed.sum()) * len(lib.fields)
        dt = (time.perf_counter() - t) / n
        pm = psf_map(lib, geom, depth, 16)
        return patch_convolve(img, pm.kernels, 16, identity=pm.identity), dt

    ref, _ = render(replace(base, pupil_samples=ref_rays, kernel_size=61))
    rows = []
    for n_rays in rays:
        for sigma in sigmas:
            res, dt = render(replace(base, pupil_samples=n_rays, deposit_sigma_px=sigma, kernel_size=61))
            rows.append((n_rays, sigma, psnr(res, ref), dt * 1000))
            print(f"  deposit sigma {sigma:.3f} px, {n_rays}^2 rays: PSNR {rows[-1][2]:6.2f} dB, "
                  f"{rows[-1][3]:.1f} ms/PSF", flush=True)
    return rows, f"{ref_rays}^2 rays, sigma 0"


def distortion_rows(lens, *, quick: bool) -> tuple[list, list, str]:
    """Warp order and interpolation against the per-pixel reference with
    distortion (:func:`distorted_reference`), on a crop at field ~0.7 where
    the distortion's radial stretch is ~0.75; and each interpolation's time
    for a 1280 x 1920 warp of three channels."""
    h, w = (40, 48) if quick else (96, 128)
    geom, src, table, scene = distortion_case(lens, h, w, 0.7)
    img, depth = scene.on_grid(src)
    settings = PSFSettings(pupil_samples=24, n_wavelengths=5, kernel_size=31) if quick else \
        PSFSettings(pupil_samples=48, n_wavelengths=15, kernel_size=41)
    lib = PSFLibrary.open(lens, replace(settings, pixel_pitch_mm=geom.pixel_pitch_mm),
                          LibraryGrid(n_fields=32, n_depths=10))
    lib.ensure(depth)
    ref = distorted_reference(scene, lib, geom, table)
    from dcdi_core.render.resample import METHODS
    from dcdi_core.render.simulate import LensSimulator, SimulateOptions
    rows = []
    for interp in ("linear", "keys"):
        res = blur_then_warp(img, depth, lens, lib, geom, src, table, interpolation=interp)
        rows.append(("blur, then warp (former)", interp, psnr(res, ref)))
    for interp in METHODS:
        res = LensSimulator(lens, SimulateOptions(geometry=geom, source_geometry=src, interpolation=interp),
                            library=lib)(img, depth)
        rows.append(("warp, then blur at the real positions", interp, psnr(res.image, ref)))
        print(f"  {rows[-1][0]}, {interp}: PSNR {rows[-1][2]:6.2f} dB", flush=True)
    from dcdi_core.render.distortion import distort
    big = ImageGeometry.full_sensor(lens, 320, 480) if quick else ImageGeometry.full_sensor(lens, 1280, 1920)
    frame = np.random.default_rng(0).uniform(0, 1, (big.height, big.width, 3)).astype(np.float32)
    times = []
    for interp in METHODS:
        best = math.inf
        for _ in range(1 if quick else 2):
            t = time.perf_counter()
            distort(frame, lens, big, distortion=table, interpolation=interp)
            best = min(best, time.perf_counter() - t)
        times.append((interp, best))
    where = (f"{h} x {w} crop at fields {geom.field(h - 1, w - 1):.2f}-{geom.field(0, 0):.2f}, over-scan source "
             f"{src.height} x {src.width}; analytic band-limited scene, depth {scene.near}-{scene.far} m; "
             f"kernel {lib.kernel_size}, the frame's border fed by the over-scan; warp times for "
             f"{big.height} x {big.width} x 3")
    return rows, times, where


def run_report(lens_id: str, out: str | Path, *, quick: bool = False) -> int:
    lens = load_lens(lens_id)
    out = Path(out)
    h, w = (64, 96) if quick else (160, 240)
    img, depth = synthetic_rgbd(h, w, seed=0)
    pitch = lens.sensor.pixel_pitch_mm or 0.0122
    off = 0.45 * lens.sensor.semi_diagonal_mm / pitch / math.sqrt(2)
    geom = ImageGeometry.from_pixel_pitch(lens, h, w, pitch, center_px=((h - 1) / 2 - off, (w - 1) / 2 - off))
    grid = LibraryGrid(n_fields=32, n_depths=10)
    base = PSFSettings(pupil_samples=32, n_wavelengths=15, pixel_pitch_mm=pitch) if quick else \
        PSFSettings(pixel_pitch_mm=pitch)
    sizes = [21, 31] if quick else [21, 31, 41]
    patches = [8, 16] if quick else [8, 16, 32, 64]
    band = _edge_band(depth)
    rows = []
    print(f"simulation-accuracy {lens.id}: {h} x {w} synthetic scene, fields "
          f"{geom.field(0, 0):.2f}..{geom.field(h - 1, w - 1):.2f}, pitch {pitch * 1000:.1f} um", flush=True)
    ref_k = max(sizes)
    lib_ref = PSFLibrary.open(lens, replace(base, kernel_size=ref_k), grid)
    lib_ref.ensure(depth)
    t = time.perf_counter()
    ref = per_pixel_reference(img, depth, lib_ref, geom)
    t_ref = time.perf_counter() - t
    rows.append(("per-pixel reference", ref_k, 1, math.inf, math.inf, 0.0, t_ref))
    for k in sizes:
        lib = lib_ref if k == ref_k else PSFLibrary.open(
            lens, replace(base, kernel_size=k), grid)
        lib.ensure(depth)
        for m in (patches if k == ref_k else [16]):
            t = time.perf_counter()
            pm = psf_map(lib, geom, depth, m)
            res = patch_convolve(img, pm.kernels, m, identity=pm.identity)
            dt = time.perf_counter() - t
            l1 = float(np.abs(res - ref).sum() / np.abs(ref).sum())
            rows.append(("patch-wise", k, m, psnr(res, ref), psnr(res, ref, band), l1, dt))
            print(f"  k {k:>2}  patch {m:>2}: PSNR {rows[-1][3]:6.2f} dB (edges {rows[-1][4]:6.2f} dB)  "
                  f"rel L1 {l1:.5f}  {dt:.2f} s", flush=True)
    # the convolution's own approximations: kernel support crop and float32 FFTs,
    # against the exact patch-wise result (no crop, numpy's float64 FFT)
    from dcdi_core.render import fft
    crop_rows = []
    pm = psf_map(lib_ref, geom, depth, 16, support_eps=0.0)
    exact = patch_convolve(img, pm.kernels, 16, ConvolveOptions(support_eps=0.0, fft_backend="numpy"),
                           identity=pm.identity)
    for backend in sorted(fft.available(), reverse=True):        # numpy first, then scipy if installed
        for eps in (0.0, 1e-4, 1e-3, 1e-2):
            t = time.perf_counter()
            pme = psf_map(lib_ref, geom, depth, 16, support_eps=eps)
            res = patch_convolve(img, pme.kernels, 16, ConvolveOptions(support_eps=eps, fft_backend=backend),
                                 identity=pme.identity)
            dt = time.perf_counter() - t
            crop_rows.append((backend, eps, psnr(res, ref), float(np.abs(res - exact).max()), dt))
            print(f"  support eps {eps:g}, {backend} FFT: PSNR {crop_rows[-1][2]:6.2f} dB, "
                  f"max |diff| vs exact {crop_rows[-1][3]:.2e}, {dt:.2f} s", flush=True)
    # the low-rank method (tiles of 8 x 8 patches, eigen-PSFs) against the same exact result
    lr_rows = lowrank_rows(img, pm, lib_ref, geom, depth, ref, exact)
    print("  fast paths of the simulation:", flush=True)
    fast_rows = fast_path_rows(img, lib_ref, geom, depth, ref)
    rot_rows = rotation_rows(quick=quick)
    print("  deposit width against rays:", flush=True)
    dep_rows, dep_ref = deposit_rows(lens, img, depth, geom, quick=quick)
    print("  warp order and interpolation:", flush=True)
    warp_rows, warp_times, warp_where = distortion_rows(lens, quick=quick)
    # bokeh at a depth edge, against ground truth with the hidden background known
    p6 = load_lens("6p")
    bgeom = ImageGeometry.full_sensor(p6, h, w)
    bsettings = PSFSettings(pupil_samples=32, n_wavelengths=15) if quick else PSFSettings()
    blib = PSFLibrary.open(p6, replace(bsettings, pixel_pitch_mm=bgeom.pixel_pitch_mm), grid)
    keep = (1.1, 1.3)
    subject = (depth >= keep[0]) & (depth <= keep[1])
    img_bg, depth_bg = synthetic_rgbd(h, w, seed=0, disk=False)
    blib.ensure(depth_bg)
    behind = bokeh(img_bg, depth_bg, p6, BokehOptions(keep=keep, occlusion=True), library=blib).image
    truth = np.where(subject[..., None], img, behind)
    ring = _edge_band(np.where(subject, 1.0, 100.0), width=8) & ~subject
    brows = []
    for occ in (False, True):
        t = time.perf_counter()
        res = bokeh(img, depth, p6, BokehOptions(keep=keep, occlusion=occ), library=blib).image
        dt = time.perf_counter() - t
        leak = float(np.abs(res - truth)[ring].mean())
        brows.append(("occlusion-aware layers" if occ else "plain patch-wise", psnr(res, truth),
                      psnr(res, truth, ring), leak, float(np.abs(res - truth)[subject].max()), dt))
        print(f"  bokeh {brows[-1][0]:<24} PSNR {brows[-1][1]:6.2f} dB, around the subject "
              f"{brows[-1][2]:6.2f} dB (mean abs {leak:.4f}), subject max change {brows[-1][4]:.4f}, {dt:.2f} s",
              flush=True)
    # layer count: occlusion handling against a truth rendered with the same
    # layers; and the subject-free background against the plain renderer, which
    # has no occlusion to get wrong there (the seams layers leave on continuous surfaces)
    layer_rows = []
    many = bokeh(img_bg, depth_bg, p6, BokehOptions(keep=keep, occlusion=False), library=blib).image
    for n_layers in ((4, 12) if quick else (2, 4, 8, 12, 16, 24)):
        t = time.perf_counter()
        res = bokeh(img, depth, p6, BokehOptions(keep=keep, occlusion=True, n_layers=n_layers), library=blib).image
        dt = time.perf_counter() - t
        bg_n = bokeh(img_bg, depth_bg, p6, BokehOptions(keep=keep, occlusion=True, n_layers=n_layers),
                     library=blib).image
        truth_n = np.where(subject[..., None], img, bg_n)
        layer_rows.append((n_layers, psnr(res, truth_n, ring), psnr(bg_n, many), dt))
        print(f"  bokeh layers {n_layers:>2}: around the subject {layer_rows[-1][1]:6.2f} dB, background vs plain "
              f"{layer_rows[-1][2]:6.2f} dB, {dt:.2f} s", flush=True)
    print("  multi-resolution bokeh against the exact path:", flush=True)
    mr_rows, mr_where = multires_rows(quick=quick)
    md = [f"# Simulation accuracy: {lens.id}", "",
          f"Synthetic RGB-D scene {h} x {w} with depth edges, off axis (fields {geom.field(0, 0):.2f}..."
          f"{geom.field(h - 1, w - 1):.2f}), pixel pitch {pitch * 1000:.1f} um; reference: every pixel its own PSF "
          f"(k = {ref_k}). 'edges' = pixels within 6 px of a depth edge.", "",
          "| method | kernel | patch | PSNR dB | PSNR at edges dB | rel. L1 | time s |", "|---|---|---|---|---|---|---|"]
    for r_ in rows:
        f = lambda v: "inf" if math.isinf(v) else f"{v:.2f}"
        md.append(f"| {r_[0]} | {r_[1]} | {r_[2]} | {f(r_[3])} | {f(r_[4])} | {r_[5]:.5f} | {r_[6]:.2f} |")
    md += ["", "## Kernel support crop and FFT precision (kernel 41, patch 16)", "",
           "Each kernel cropped to the centred square holding all but eps of its energy (rescaled to its sum); "
           "'exact' = no crop, float64 FFT.", "",
           "| FFT | support eps | PSNR vs per-pixel dB | max abs diff vs exact | time s |", "|---|---|---|---|---|"]
    for c_ in crop_rows:
        md.append(f"| {c_[0]} ({'float32' if c_[0] == 'scipy' else 'float64'}) | {c_[1]:g} | {c_[2]:.2f} | "
                  f"{c_[3]:.2e} | {c_[4]:.2f} |")
    md += ["", "## Low-rank tiles (kernel 41, patch 16, support eps 1e-3)", "",
           "`ConvolveOptions(method='lowrank')`: each tile of 8 x 8 patches convolved with its kernels' eigen-PSFs "
           "(truncated SVD, rank: every kernel within rank eps in L1); bound: max abs diff <= 2 eps max|image| "
           "against the same patch-wise result.", "",
           "| method | rank eps | PSNR vs per-pixel dB | max abs diff vs exact | time s |", "|---|---|---|---|---|"]
    for q in lr_rows:
        md.append(f"| {q[0]} | {q[1]:g} | {q[2]:.2f} | {q[3]:.2e} | {q[4]:.2f} |")
    md += ["", "## Fast paths of the simulation (kernel 41, patch 16, support eps 1e-3)", "",
           "PSF map and convolution as `simulate` runs them: 'fast' (the default) and torch are the windows "
           "method laid out for speed (the same result to float32 rounding); a blend narrower than the tent "
           "(8 px) is an approximation of its own. Max abs diff against the windows row.", "",
           "| path | PSNR vs per-pixel dB | max abs diff vs windows | time s |", "|---|---|---|---|"]
    for q in fast_rows:
        md.append(f"| {q[0]} | {q[1]:.2f} | {q[2]:.2e} | {q[3]:.2f} |")
    md += ["", "## Kernel rotation against rotated rays", "",
           "Gaussian ray clouds (sigma along x across the radial axis, offset along it; px) histogrammed on the "
           "radial line and rotated, against the histogram of the rays rotated exactly: relative L1.", "",
           "| sigma px | offset px | 30 deg bilinear | 30 deg peak kept | 45 deg bilinear | 45 deg peak kept |",
           "|---|---|---|---|---|---|"]
    for q in rot_rows:
        md.append(f"| {q[0]:g} x {q[1]:g} | {q[2]:g} | {q[3]:.4f} | {q[4]:.4f} | {q[5]:.4f} | {q[6]:.4f} |")
    md += ["", "## Deposit width against rays (kernel 61, patch 16)", "",
           f"Each ray's energy into the pixel it lands in (sigma 0) or spread by a Gaussian of sigma px; "
           f"the simulation against the same with a reference library ({dep_ref}); time per PSF of the library.", "",
           "| rays | deposit sigma px | PSNR dB | ms per PSF |", "|---|---|---|---|"]
    for d_ in dep_rows:
        md.append(f"| {d_[0]}^2 | {d_[1]:.3f} | {d_[2]:.2f} | {d_[3]:.1f} |")
    md += ["", f"## Distortion: warp order and interpolation ({lens.id})", "",
           "Reference: every pixel its own PSF at its real image position, applied to the sharp scene evaluated "
           f"exactly where the distortion takes it. {warp_where}.", "",
           "| order | interpolation | PSNR dB |", "|---|---|---|"]
    for w_ in warp_rows:
        md.append(f"| {w_[0]} | {w_[1]} | {w_[2]:.2f} |")
    md += ["", "| interpolation | warp time s |", "|---|---|"]
    for name, t_ in warp_times:
        md.append(f"| {name} | {t_:.2f} |")
    md += ["", f"## Bokeh at a depth edge (6P, keep {keep[0]}-{keep[1]} m, full sensor, {h} x {w})", "",
           "Ground truth: the kept subject pasted over the background scene rendered without it.", "",
           "| renderer | PSNR dB | PSNR in 8 px around the subject dB | mean abs error there | subject max change | time s |",
           "|---|---|---|---|---|---|"]
    for b in brows:
        md.append(f"| {b[0]} | {b[1]:.2f} | {b[2]:.2f} | {b[3]:.4f} | {b[4]:.4f} | {b[5]:.2f} |")
    md += ["", "Occlusion-aware layers (equal steps in diopters): around the subject against the truth "
           "rendered with the same layers (occlusion handling); the subject-free background against the plain "
           "patch-wise blur (no occlusion there to handle: what differs are the seams between layers):", "",
           "| layers | PSNR around the subject dB | background vs plain dB | time s |", "|---|---|---|---|"]
    for lr in layer_rows:
        md.append(f"| {lr[0]} | {lr[1]:.2f} | {lr[2]:.2f} | {lr[3]:.2f} |")
    md += ["", "## Multi-resolution bokeh against the exact path", "",
           f"`BokehOptions(multires=c, max_level=s_max)`: a patch whose kernel's half-energy "
           f"radius is >= c 2^s px is blurred at 1/2^s of the resolution (render/multires.py). {mr_where}. PSNR and "
           "max abs difference against the exact path over the whole frame (peak 1); around the subject: 8 px "
           "around the kept subject against the truth (subject over the subject-free background, exact path).", "",
           "| renderer | c px | max level | PSNR vs exact dB | max abs diff | PSNR around the subject dB | time s | "
           "CPU s | CPU s of the exact run after it | levels |",
           "|---|---|---|---|---|---|---|---|---|---|"]
    for q in mr_rows:
        f = lambda v: "inf" if math.isinf(v) else ("-" if math.isnan(v) else f"{v:.2f}")
        md.append(f"| {'layered' if q[0] else 'plain'} | {q[1]} | {q[2]} | {f(q[3])} | {q[4]:.4f} | {f(q[5])} | "
                  f"{q[6]:.2f} | {q[7]:.2f} | {q[8]:.2f} | {q[9]} |")
    path = out / f"simulation-accuracy-{lens.id}.md"
    write_text(path, "\n".join(md) + "\n")
    print(f"wrote {path}")
    return 0
