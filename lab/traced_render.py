"""A reference renderer traced through the lens, and the fast bokeh scored against it.

The engine's bokeh (``dcdi bokeh --distort --focus D``) blurs an all-in-focus
pinhole RGB-D image patch by patch with PSFs. This module makes an
independent ground truth of the same scene, slow by design, and scores the
fast path against it, lens by lens:

* **Analytic scenes** (:class:`Scene`): fronto-parallel textured planes
  (:class:`Plane`, optionally cut by half-planes, so one of them is an
  occluding edge), and small emissive spheres (:class:`Sphere`, radiance
  several times the background's). Metres, in the camera's frame: the origin
  at the lens's first vertex (where the engine measures depths from), z along
  the optical axis towards the object, x to the image's right, y up.
  :func:`default_scene` lays one out over a frame's field of view: a
  background plane at 9 m, a plane at 5 m over the lower left, an occluder
  at 1.5 m over the right 30 % of the frame, and four lights (three at 7 m,
  one at 2.5 m). Every depth lies inside the engine's PSF library's range
  (0.7 to 10 m), so no far or near clamping is measured.

* **The traced render** (:func:`traced_render`): for every sensor pixel,
  rays from points inside the pixel (pixel-area integration) in directions
  over the whole exit pupil, traced backward through the lens (the
  prescription mirrored: :func:`reversed_lens`), from the sensor into object
  space, then intersected with the scene; the nearest hit wins (occlusion
  within the aperture is right by construction). The lens is refocused and
  stopped down exactly as the engine's PSFs are (``optics.paraxial.refocused``,
  as ``psf.compute.focused_lens``; ``optics.aperture.stopped_down``). Rays
  blocked by any semi-diameter or the stop are dropped.

  Sampling: directions uniform in the image-side direction cosines (kx, ky)
  inside a disc that holds every ray the lens passes from that point (found
  by a pilot trace per field height, :func:`pupil_cones`): uniform in
  projected solid angle, so each ray carries the same irradiance (radiance
  is invariant along a ray from air to air). Pupil point, point in the
  pixel and wavelength are each stratified (scrambled Halton points shifted
  at random per pixel, jittered strata), paired at random per pixel
  (randomised quasi-Monte Carlo; deterministic for a seed). Where a light's
  blur falls (a disc found from the geometry before any ray: no bias), a
  pixel gets ``--boost`` times the rays.

  Colour: the engine's wavelengths and weights (``psf.compute.spectral_samples``
  with the default ``PSFSettings``: 31 wavelengths over 400-700 nm, the
  shipped sensor response); a ray carries one wavelength, drawn with a
  probability proportional to its summed channel weights, and adds to R, G, B
  with weight / probability. The scene's RGB radiance is read per channel.

  Normalisation: the engine's PSFs sum to 1 per channel over the rays that
  arrive (``psf.compute.rays_to_kernels``: the kernel divided by the energy
  inside it; the vignetted fraction and the relative illumination are
  reported beside it, never applied). The traced render does the same per
  pixel: each channel is divided by the summed weights of the rays that pass
  the lens (those that reach the scene, whether they hit a shape or not). A
  uniformly lit plane of radiance 1 therefore renders 1 everywhere, in the
  corners too; a pixel no ray reaches is 0, never NaN.

* **The pinhole RGB-D** (:func:`pinhole_render`): the engine's ideal image,
  what Blender's pinhole camera renders: the pinhole at the paraxial entrance
  pupil, an object direction p = tan(field angle) (as ``optics.aiming.launch``)
  imaged at the paraxial height ``optics.paraxial.paraxial_image_height_mm``
  (the distortion table's ideal column, ``render.distortion.radial_distortion``),
  and the depth as the engine reads it: the hit's axial distance from the
  first vertex, metres. Supersampled (stratified, jittered, 6 x 6 a pixel),
  the depth of the pixel's centre ray; rendered over-scan (the frame grown by
  the distortion's pull and the widest blur) and given to the engine as
  ``RenderRequest(sensor_size=...)``.

* **The score** (:func:`score_case`): the engine's bokeh through its public
  job, ``app.bokeh(BokehRequest(..., focus_m=D, distortion=True))`` (what
  ``dcdi bokeh --distort --focus D`` calls), against the traced render:
  PSNR (peak 1.0, the white of the textures; mean over pixels and channels)
  over the frame, on a band of +-6 px around the occluder's edge, and in a
  21 x 21 px crop around each light (centred where its real chief ray lands).

* **The noise floor**: the traced render is the mean of two halves with
  independent seeds (each half its own random shifts and scrambling). The
  PSNR between the halves plus 6.02 dB is the PSNR of the full render
  against its noise-free limit (each half has twice the full render's noise
  variance, and their difference twice that again): the highest score a
  perfect fast path could get, per region.

The command ``python -m lab traced-render [--lenses ID ...] [--out DIR]
[--rays N] [--size H W] [--focus D ...] [--f-number N ...]`` runs every
catalogue lens wide open and at f/5.6 (skipped where the lens is slower),
focused at 1.5 m and at 5 m, and writes ``traced-render.md`` and
``traced-render.json`` to --out (with ``--save-images`` also each case's
images, .npz). Defaults: the full sensor at 96 x 144 px, 256 rays a pixel
(docs/image-formation.md states the measured table and its time).
"""
from __future__ import annotations

import json
import math
import sys
import time
from dataclasses import dataclass, replace

import numpy as np

# the scale the engine reads a pinhole render at (mm of ideal height per unit tan of the field angle)
from dcdi_core.render.camera import ideal_scale_mm

FOCI_M = (1.5, 5.0)
STOPPED_F_NUMBER = 5.6
DEFAULT_SIZE = (96, 144)
DEFAULT_RAYS = 256
EDGE_BAND_PX = 6
LIGHT_CROP_PX = 21
PEAK = 1.0
PINHOLE_SUPERSAMPLE = 6
LIGHT_RADIUS_PX = 1.5
BOOST = 8                 # rays a pixel, times, where a light's blur falls
# rays traced at once (memory: about 1 kB a ray with the scene's arrays)
CHUNK_RAYS = 1 << 17


# ------------------------------------------------------------------ scenes
@dataclass(frozen=True)
class Texture:
    """A band-limited procedural texture on a plane (X, Y metres):
    ``base`` RGB times v(X, Y) in [0.1, 1]: a sinusoid of period
    ``period_m`` along ``angle_deg`` and a smoothed checker of period
    ``checker_m`` (tanh of a product of sines: its edges a fifth of a
    period wide). ``gradient``: a ramp across X (per metre) that breaks the
    texture's symmetry."""

    base: tuple[float, float, float] = (0.8, 0.8, 0.8)
    period_m: float = 0.1
    checker_m: float = 0.3
    angle_deg: float = 30.0
    phase: float = 0.0
    gradient: float = 0.0

    def radiance(self, x, y) -> np.ndarray:
        a = math.radians(self.angle_deg)
        s = np.sin(2 * np.pi * (x * math.cos(a) + y * math.sin(a)) / self.period_m + self.phase)
        c = np.tanh(2.0 * np.sin(np.pi * x / self.checker_m + self.phase) * np.sin(np.pi * y / self.checker_m))
        v = 0.55 + 0.2 * s + 0.2 * c + self.gradient * x
        v = np.clip(v, 0.1, 1.0)
        return v[..., None] * np.asarray(self.base, np.float64)


@dataclass(frozen=True)
class Plane:
    """A fronto-parallel plane at ``depth_m`` (from the first vertex), its
    radiance ``texture`` (a :class:`Texture`, or an RGB triple: uniform);
    ``region``: half-planes (nx, ny, offset_m), all of which must hold,
    nx X + ny Y >= offset (X, Y metres on the plane); empty: the whole plane."""

    depth_m: float
    texture: object = Texture()
    region: tuple = ()

    def radiance(self, x, y) -> np.ndarray:
        if isinstance(self.texture, Texture):
            return self.texture.radiance(x, y)
        return np.broadcast_to(np.asarray(self.texture, np.float64), np.shape(x) + (3,))

    def hit(self, o, d):
        """Ray parameters t (n,) where the rays (o, d) (n, 3) meet the plane inside its region (inf: no hit)."""
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (self.depth_m - o[:, 2]) / d[:, 2]
        ok = (d[:, 2] > 0) & (t > 0)
        x = o[:, 0] + t * d[:, 0]
        y = o[:, 1] + t * d[:, 1]
        for nx, ny, off in self.region:
            ok &= nx * x + ny * y >= off
        return np.where(ok, t, np.inf)

    def shade(self, o, d, t):
        x = o[:, 0] + t * d[:, 0]
        y = o[:, 1] + t * d[:, 1]
        return self.radiance(x, y)


@dataclass(frozen=True)
class Sphere:
    """An emissive sphere: centre (x, y, z) metres, radius metres, uniform RGB radiance."""

    center_m: tuple[float, float, float]
    radius_m: float
    radiance: tuple[float, float, float] = (6.0, 5.0, 3.5)

    def hit(self, o, d):
        c = np.asarray(self.center_m, np.float64)
        oc = o - c
        b = np.einsum("ij,ij->i", oc, d)
        cc = np.einsum("ij,ij->i", oc, oc) - self.radius_m ** 2
        disc = b * b - cc
        root = np.sqrt(np.maximum(disc, 0.0))
        t0, t1 = -b - root, -b + root
        t = np.where(t0 > 0, t0, t1)
        return np.where((disc >= 0) & (t > 0), t, np.inf)

    def shade(self, o, d, t):
        return np.broadcast_to(np.asarray(self.radiance, np.float64), (len(t), 3))


@dataclass(frozen=True)
class Scene:
    """Shapes (planes, spheres) and the radiance of a ray that meets none."""

    shapes: tuple
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    lights: tuple = ()            # indices of the spheres scored as lights
    occluder: int | None = None   # index of the plane whose edge is scored

    def shade(self, o, d):
        """(radiance (n, 3), axial depth of the hit (n,) metres, inf where none,
        index of the shape hit (n,), -1 where none) of rays (o, d) (n, 3) in
        the scene's frame; d unit vectors. The nearest hit wins."""
        n = len(o)
        best = np.full(n, np.inf)
        which = np.full(n, -1, np.int64)
        for i, s in enumerate(self.shapes):
            t = s.hit(o, d)
            nearer = t < best
            best = np.where(nearer, t, best)
            which[nearer] = i
        rad = np.broadcast_to(np.asarray(self.background, np.float64), (n, 3)).copy()
        for i, s in enumerate(self.shapes):
            m = which == i
            if m.any():
                rad[m] = s.shade(o[m], d[m], best[m])
        depth = np.where(which >= 0, o[:, 2] + np.where(np.isfinite(best), best, 0.0) * d[:, 2], np.inf)
        return rad, depth, which


def default_scene(tan_w: float, tan_h: float, tan_px: float) -> Scene:
    """The scene of the table over a frame whose half-width and half-height
    subtend tan_w and tan_h (tangents, seen from the entrance pupil) and
    whose pixel subtends tan_px. Positions are fractions of the frame (fx,
    fy in [-1, 1], right and up) at each shape's depth; texture periods
    are at least 9 px, the lights' radius 1.5 px."""
    def m(fx, fy, z):
        return fx * tan_w * z, fy * tan_h * z

    def tex(z, base, phase, angle):
        return Texture(base=base, period_m=9.0 * tan_px * z, checker_m=24.0 * tan_px * z, angle_deg=angle,
                       phase=phase, gradient=0.15 / (tan_w * z))

    bg, mid, occ = 9.0, 5.0, 1.5
    shapes = [
        Plane(bg, tex(bg, (0.85, 0.8, 0.7), 0.3, 30.0)),
        Plane(mid, tex(mid, (0.55, 0.85, 0.6), 1.1, -50.0),
              region=((0.0, -1.0, -m(0, -0.2, mid)[1]), (-1.0, 0.0, -m(0.3, 0, mid)[0]))),
        Plane(occ, tex(occ, (0.6, 0.65, 0.95), 2.0, 75.0), region=((1.0, 0.0, m(0.4, 0, occ)[0]),)),
    ]
    lights = []
    # within 0.6 of the frame's half-width: in view when the lens, focused near, magnifies (a 180 mm at
    # 1.5 m by 1.33)
    for fx, fy, z, rgb in ((-0.45, 0.5, 7.0, (6.0, 5.0, 3.5)), (0.0, 0.3, 7.0, (5.0, 5.0, 5.0)),
                           (-0.6, 0.0, 7.0, (3.5, 5.0, 6.0)), (0.12, -0.55, 2.5, (6.0, 4.0, 4.0))):
        x, y = m(fx, fy, z)
        lights.append(len(shapes))
        shapes.append(Sphere((x, y, z), LIGHT_RADIUS_PX * tan_px * z, rgb))
    return Scene(tuple(shapes), (0.0, 0.0, 0.0), tuple(lights), occluder=2)


# ------------------------------------------------------------------ the lens traced backward
def reversed_lens(lens, exit_z_mm: float | None = None):
    """The lens mirrored along its axis, for tracing from the sensor into
    object space with the forward tracer: the surfaces in reverse order,
    curvatures and aspheric terms (even and odd) negated, conics, semi-
    diameters and the stop (and its blades) kept; the medium after each
    surface the one before it in the lens (object space, air, after the
    first). Its frame is z' = z_last_vertex - z (x, y unchanged): its first
    vertex is the lens's last, its object space the lens's image space
    (which must be air). Its 'sensor' is the plane z = ``exit_z_mm`` of the
    lens's frame (default ``optics.aiming.start_plane_z``: in front of every
    point of the first surface). Returns (reversed lens, z_last_vertex)."""
    from dcdi_core.errors import InputRangeError
    from dcdi_core.optics.aiming import start_plane_z
    from dcdi_core.optics.materials import AIR
    surfaces = lens.surfaces
    if surfaces[-1].material.name.lower() != "air":
        raise InputRangeError(f"image space of {lens.id}", surfaces[-1].material.name, "air (the lens traced backward)")
    z = lens.vertex_z_mm
    z_last = float(z[-1])
    front = start_plane_z(lens)
    exit_z = front if exit_z_mm is None else float(exit_z_mm)
    if not exit_z <= front:
        raise InputRangeError("exit_z_mm", exit_z, f"<= {front:.6g} mm (in front of every point of the first surface)")
    out = []
    n = len(surfaces)
    for j in range(n):
        i = n - 1 - j
        s = surfaces[i]
        thickness = float(z[i] - z[i - 1]) if i > 0 else float(z[0] - exit_z)
        material = surfaces[i - 1].material if i > 0 else AIR
        out.append(replace(s, radius_mm=-s.radius_mm, thickness_mm=thickness, material=material,
                           aspheric_coefficients=tuple(-a for a in s.aspheric_coefficients),
                           odd_aspheric_coefficients=tuple(-b for b in s.odd_aspheric_coefficients)))
    rev = replace(lens.with_surfaces(out), id=f"{lens.id}-reversed", name=f"{lens.name} (reversed)")
    return rev, z_last


def trace_backward(rev, z_last: float, origins, directions, wavelength_nm, status=None):
    """Trace rays travelling towards the object (lens frame: origins (n, 3)
    behind the last surface, directions (n, 3) with dz < 0) through the
    reversed lens to its exit plane. Returns (origins, directions, valid)
    in the scene's frame (metres; z towards the object; the origin at the
    first vertex)."""
    from dcdi_core.optics.trace import trace
    o = np.array(origins, np.float64)
    d = np.array(directions, np.float64)
    o[:, 2] = z_last - o[:, 2]
    d[:, 2] = -d[:, 2]
    b = trace(rev, o, d, wavelength_nm, status=status)
    # the reversed frame is the scene's frame shifted by z_last (x, y unchanged, z towards the object)
    pos = b.position_mm.copy()
    pos[:, 2] -= z_last
    return pos / 1000.0, b.direction, b.valid


# ------------------------------------------------------------------ where the rays of a sensor point pass
@dataclass(frozen=True)
class PupilCones:
    """For sensor points at radius ``heights_mm`` on +y: the disc in
    image-side direction cosines (kx, ky) of the rays travelling towards the
    lens that holds every ray the lens passes: centre (0, ``center``),
    radius ``radius``. Elsewhere rotated about the axis."""

    heights_mm: np.ndarray
    center: np.ndarray
    radius: np.ndarray
    pixel_margin: float

    def at(self, r_mm):
        """(centre offset along the radial direction, radius) at radii r_mm:
        the larger radius of the two bracketing heights grown by the centre's
        change across them and by a pixel's reach."""
        h = self.heights_mm
        j = np.clip(np.searchsorted(h, r_mm, side="right") - 1, 0, len(h) - 2)
        f = np.clip((r_mm - h[j]) / (h[j + 1] - h[j]), 0.0, 1.0)
        c = self.center[j] + f * (self.center[j + 1] - self.center[j])
        rad = np.maximum(self.radius[j], self.radius[j + 1])
        rad = np.where(rad > 0, rad + np.abs(self.center[j + 1] - self.center[j]) + self.pixel_margin, 0.0)
        return c, rad


def _pass(rev, z_last, lens, h, kx, ky, wl):
    """Which backward rays from sensor points (0, h) in directions (kx, ky) reach object space."""
    k2 = kx * kx + ky * ky
    ok = k2 < 0.999
    kz = -np.sqrt(np.maximum(1.0 - k2, 1e-6))
    n = kx.size
    o = np.stack([np.zeros(n), h.ravel(), np.full(n, lens.sensor_z_mm)], -1)
    d = np.stack([kx.ravel(), ky.ravel(), kz.ravel()], -1)
    from dcdi_core.optics import surfaces as S
    _, _, valid = trace_backward(rev, z_last, o, d, wl, status=np.where(ok.ravel(), S.OK, S.MISSED).astype(np.uint8))
    return valid.reshape(kx.shape)


def pupil_cones(lens, max_height_mm: float, pitch_mm: float, n_heights: int = 41, grid: int = 56,
                wavelengths_nm=(400.0, 700.0)) -> PupilCones:
    """The :class:`PupilCones` of ``lens`` (its blades ignored: the round stop
    holds the polygon) for heights 0 to ``max_height_mm``: per height a
    grid x grid trace over a box in direction cosines, started on the
    paraxial exit pupil and grown until no passing ray touches its border,
    at the band's two ends; the disc holds every passing sample with 1.5
    grid steps to spare."""
    from dcdi_core.optics.paraxial import first_order
    plain = lens.with_surfaces([replace(s, blades=0) for s in lens.surfaces])
    rev, z_last = reversed_lens(plain)
    fo = first_order(plain)
    h = np.linspace(0.0, max_height_mm, n_heights)
    zs = plain.sensor_z_mm
    z_xp = z_last + fo.exit_pupil_position_mm
    dist = zs - z_xp
    if math.isfinite(dist) and dist > 1e-6:
        v = np.stack([np.zeros_like(h), -h, -np.full_like(h, dist)], -1)
        v /= np.linalg.norm(v, axis=-1, keepdims=True)
        cy = v[:, 1]
        half = np.full_like(h, min(0.9, 1.5 * 0.5 * fo.exit_pupil_diameter_mm / dist + 0.02))
    else:
        cy, half = np.zeros_like(h), np.full_like(h, 0.5)
    cx = np.zeros_like(h)
    u = (np.arange(grid) + 0.5) / grid * 2.0 - 1.0
    center, radius = np.zeros_like(h), np.zeros_like(h)
    todo = np.ones(len(h), bool)
    for _ in range(8):
        idx = np.flatnonzero(todo)
        if idx.size == 0:
            break
        kx = cx[idx, None, None] + half[idx, None, None] * u[None, None, :]
        ky = cy[idx, None, None] + half[idx, None, None] * u[None, :, None]
        kx, ky = np.broadcast_arrays(kx, ky)
        hh = np.broadcast_to(h[idx, None, None], kx.shape)
        ok = np.zeros(kx.shape, bool)
        for wl in wavelengths_nm:
            ok |= _pass(rev, z_last, plain, hh, kx, ky, wl)
        for a, i in enumerate(idx):
            m = ok[a]
            if not m.any():
                if half[i] >= 0.95:
                    todo[i] = False           # nothing passes from this point
                else:
                    cx[i], cy[i], half[i] = 0.0, 0.0 if h[i] == 0 else cy[i], 0.95
                continue
            border = m[0].any() or m[-1].any() or m[:, 0].any() or m[:, -1].any()
            px, py = kx[a][m], ky[a][m]
            if border and half[i] < 0.95:
                cx[i] = 0.5 * (px.min() + px.max())
                cy[i] = 0.5 * (py.min() + py.max())
                half[i] = min(0.95, 1.6 * half[i])
                continue
            step = 2.0 * half[i] / grid
            c0 = 0.5 * (py.min() + py.max())
            center[i] = c0
            radius[i] = float(np.sqrt(px ** 2 + (py - c0) ** 2).max()) + 1.5 * step + abs(float(px.mean()))
            todo[i] = False
    # a beam still touching its box's border after the growth: the box's own circle (never none)
    center[todo] = cy[todo]
    radius[todo] = np.sqrt(2.0) * half[todo] + np.abs(cx[todo])
    margin = 0.75 * pitch_mm / dist if math.isfinite(dist) and dist > 1e-6 else 0.02
    return PupilCones(h, center, radius, float(margin))


# ------------------------------------------------------------------ the traced render
def _concentric(u1, u2):
    """Shirley and Chiu's map of the unit square onto the unit disc (area-preserving)."""
    a, b = 2.0 * u1 - 1.0, 2.0 * u2 - 1.0
    first = np.abs(a) > np.abs(b)
    sa = np.where(a == 0, 1e-300, a)
    sb = np.where(b == 0, 1e-300, b)
    r = np.where(first, a, b)
    phi = np.where(first, (np.pi / 4) * (b / sa), np.pi / 2 - (np.pi / 4) * (a / sb))
    zero = (a == 0) & (b == 0)
    return np.where(zero, 0.0, r * np.cos(phi)), np.where(zero, 0.0, r * np.sin(phi))


def _pixel_samples(rng, pupil, spot, p: int) -> np.ndarray:
    """(p, n, 5) samples in [0, 1): the pupil point (2), the point in the
    pixel (2) and the wavelength (1) of n rays for each of p pixels. Each
    group is stratified on its own (two scrambled Halton point sets, and n
    jittered strata of the wavelength), shifted at random per pixel
    (Cranley-Patterson), and the groups are paired at random per pixel, so
    no two of them correlate (a Halton sequence's own dimensions 3 to 5
    run in step for the first points: colour would follow the position)."""
    n = len(pupil)
    out = np.empty((p, n, 5))
    out[..., 0:2] = (pupil[None] + rng.random((p, 1, 2))) % 1.0
    out[..., 2:4] = (spot[np.argsort(rng.random((p, n)), axis=1)] + rng.random((p, 1, 2))) % 1.0
    out[..., 4] = (np.argsort(rng.random((p, n)), axis=1) + rng.random((p, n))) / n
    return out


@dataclass
class TracedImage:
    """A traced render: ``image`` (H, W, 3) float64, the mean of two halves
    ``halves`` (2, H, W, 3) of independent seeds; ``passed`` (H, W) the
    fraction of the launched rays that reached the scene; ``rays`` launched
    a pixel (both halves; ``boost_factor`` times as many on
    ``boosted_pixels`` pixels); ``seconds``."""

    image: np.ndarray
    halves: np.ndarray
    passed: np.ndarray
    rays: int
    seconds: float
    boosted_pixels: int = 0
    boost_factor: int = 1


def spectral_table():
    """(wavelengths (W,) nm, channel weights (W, 3)): the engine's default
    (``psf.compute.spectral_samples`` with ``PSFSettings()``)."""
    from dcdi_core.psf.compute import PSFSettings, spectral_samples
    return spectral_samples(PSFSettings(), None)


def traced_render(lens, scene: Scene, geometry, rays: int = DEFAULT_RAYS, seed: int = 0, *,
                  boost=None, boost_factor: int = 1, log=None, chunk_rays: int = CHUNK_RAYS) -> TracedImage:
    """The scene through ``lens`` (already refocused and stopped down) on
    ``geometry``'s pixels (``render.geometry.ImageGeometry``), ``rays`` rays a
    pixel in two halves of independent seeds (see the module docstring);
    the pixels of ``boost`` ((H, W) bool, chosen before any ray: no bias)
    get ``boost_factor`` times as many (where a small bright light's blur
    falls: few of a pixel's rays meet it). ``log(text)``: progress lines,
    about every 10 s."""
    from scipy.stats import qmc

    from dcdi_core.errors import InputRangeError
    from dcdi_core.optics import surfaces as S
    if isinstance(rays, bool) or not isinstance(rays, (int, np.integer)) or rays < 2 or rays % 2:
        raise InputRangeError("rays", rays, "an even number >= 2 (two halves)")
    if isinstance(boost_factor, bool) or not isinstance(boost_factor, (int, np.integer)) or boost_factor < 1:
        raise InputRangeError("boost_factor", boost_factor, "an integer >= 1")
    t_start = time.perf_counter()
    H, W = geometry.height, geometry.width
    pitch = geometry.pixel_pitch_mm
    cr, cc = geometry.center_px
    corner = math.hypot(max(cr, H - 1 - cr) + 0.75, max(cc, W - 1 - cc) + 0.75) * pitch
    cones = pupil_cones(lens, corner, pitch)
    rev, z_last = reversed_lens(lens)
    wl, weights = spectral_table()
    prob = weights.sum(1) / weights.sum()
    cdf = np.cumsum(prob)
    cdf[-1] = 1.0
    omega = weights / prob[:, None]                     # (W, 3) a ray's channel weight / its probability
    zs = lens.sensor_z_mm
    P = H * W
    boosted = np.zeros(P, bool) if boost is None else np.asarray(boost, bool).reshape(P)
    groups = [(np.flatnonzero(~boosted), rays // 2), (np.flatnonzero(boosted), rays // 2 * int(boost_factor))]
    total_rays = sum(len(g) * m for g, m in groups) * 2
    sums = np.zeros((2, 2, P, 3))                       # (half, numerator / denominator, pixel, channel)
    launched = np.zeros(P)
    passed = np.zeros(P)
    done_rays, last = 0, time.perf_counter()
    ss = np.random.SeedSequence(seed).spawn(2)
    for half in range(2):
        rng = np.random.default_rng(ss[half])
        for pixels, n in groups:
            if pixels.size == 0:
                continue
            pupil = qmc.Halton(d=2, scramble=True, seed=rng).random(n)      # (n, 2) each
            spot = qmc.Halton(d=2, scramble=True, seed=rng).random(n)
            per = max(1, chunk_rays // n)
            for start in range(0, pixels.size, per):
                idx = pixels[start:start + per]
                u = _pixel_samples(rng, pupil, spot, idx.size)                 # (p, n, 5)
                rows = (idx // W)[:, None] + u[..., 2] - 0.5
                cols = (idx % W)[:, None] + u[..., 3] - 0.5
                xs = -(cols - cc) * pitch                                    # the image is inverted on the sensor
                ys = (rows - cr) * pitch
                r = np.hypot(xs, ys)
                safe = np.where(r > 0, r, 1.0)
                ex, ey = np.where(r > 0, xs / safe, 0.0), np.where(r > 0, ys / safe, 1.0)
                c, rad = cones.at(r)
                dx, dy = _concentric(u[..., 0], u[..., 1])
                kx = c * ex + rad * dx
                ky = c * ey + rad * dy
                k2 = kx * kx + ky * ky
                alive = (k2 < 0.999) & (rad > 0)
                kz = -np.sqrt(np.maximum(1.0 - k2, 1e-6))
                w_idx = np.minimum(np.searchsorted(cdf, u[..., 4], side="right"), len(wl) - 1)
                o = np.stack([xs, ys, np.full(xs.shape, zs)], -1).reshape(-1, 3)
                d = np.stack([kx, ky, kz], -1).reshape(-1, 3)
                so, sd, valid = trace_backward(rev, z_last, o, d, wl[w_idx].ravel(),
                                               status=np.where(alive.ravel(), S.OK, S.MISSED).astype(np.uint8))
                rad_rgb = np.zeros((valid.size, 3))
                if valid.any():
                    rad_rgb[valid] = scene.shade(so[valid], sd[valid])[0]
                w = omega[w_idx].reshape(-1, 3) * valid[:, None]
                sums[half, 0, idx] = (rad_rgb * w).reshape(idx.size, n, 3).sum(1)
                sums[half, 1, idx] = w.reshape(idx.size, n, 3).sum(1)
                passed[idx] += valid.reshape(idx.size, n).sum(1)
                launched[idx] += n
                done_rays += idx.size * n
                if log is not None and time.perf_counter() - last > 10.0:
                    last = time.perf_counter()
                    log(f"  traced {done_rays / total_rays:.0%} ({last - t_start:.0f} s)")

    def ratio(num, den):
        return np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0)

    halves = ratio(sums[:, 0], sums[:, 1])
    image = ratio(sums[:, 0].sum(0), sums[:, 1].sum(0))
    return TracedImage(image.reshape(H, W, 3), halves.reshape(2, H, W, 3), (passed / launched).reshape(H, W), rays,
                       time.perf_counter() - t_start, int(boosted.sum()), int(boost_factor))


# ------------------------------------------------------------------ the pinhole RGB-D
def pinhole_render(lens, scene: Scene, geometry, supersample: int = PINHOLE_SUPERSAMPLE, seed: int = 0):
    """(image (H, W, 3) float32, depth (H, W) metres) of ``scene`` as the
    engine's ideal camera sees it on ``geometry``'s pixels: the pinhole at
    ``lens``'s paraxial entrance pupil, pixel (row, col) the object direction
    p = ((col - cc), -(row - cr)) pitch / k (see the module docstring).
    The image averages supersample^2 stratified jittered rays a pixel; the
    depth is the axial distance (from the first vertex) of the pixel
    centre's hit, inf where it meets nothing."""
    from dcdi_core.optics.paraxial import first_order
    H, W = geometry.height, geometry.width
    pitch = geometry.pixel_pitch_mm
    cr, cc = geometry.center_px
    k = ideal_scale_mm(lens)
    z_ep = first_order(lens).entrance_pupil_position_mm
    origin = np.array([0.0, 0.0, -z_ep / 1000.0])
    rng = np.random.default_rng(seed)
    s = int(supersample)

    def shoot(rows, cols):
        px = (cols - cc) * pitch / k
        py = -(rows - cr) * pitch / k
        d = np.stack([px, py, np.ones_like(px)], -1).reshape(-1, 3)
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        return scene.shade(np.broadcast_to(origin, d.shape), d)

    img = np.zeros((H, W, 3))
    rr, cc_ = np.mgrid[0:H, 0:W].astype(np.float64)
    for a in range(s):
        for b in range(s):
            jr = (a + rng.random((H, W))) / s - 0.5
            jc = (b + rng.random((H, W))) / s - 0.5
            img += shoot(rr + jr, cc_ + jc)[0].reshape(H, W, 3)
    img /= s * s
    depth = shoot(rr, cc_)[1].reshape(H, W)
    return img.astype(np.float32), depth


# ------------------------------------------------------------------ a case: one lens, f-number, focus
@dataclass(frozen=True)
class Case:
    lens_id: str
    f_number: float | None        # None: wide open (the lens as designed)
    focus_m: float


def case_lenses(case: Case):
    """(the lens as the engine is given it: stopped down as `dcdi bokeh
    --f-number` does; the same refocused as its PSFs are)."""
    from dcdi_core.optics.aperture import Aperture, stopped_down
    from dcdi_core.optics.lens import load_lens
    from dcdi_core.psf.compute import PSFSettings, focused_lens
    lens = stopped_down(load_lens(case.lens_id), Aperture(case.f_number))
    return lens, focused_lens(lens, PSFSettings(focus_distance_m=case.focus_m))


def frame_geometry(lens, size):
    from dcdi_core.render.geometry import ImageGeometry
    return ImageGeometry.full_sensor(lens, int(size[0]), int(size[1]))


def overscan_px(lens, focused, geometry, scene: Scene) -> int:
    """Pixels the pinhole render needs beyond the frame on each side: the
    distortion's pull at the corner (ideal minus real height) and the widest
    blur radius of the scene's depths (paraxial), plus 4."""
    from dcdi_core.optics.paraxial import first_order
    from dcdi_core.render.distortion import radial_distortion
    pitch = geometry.pixel_pitch_mm
    corner = math.hypot(geometry.height / 2.0, geometry.width / 2.0) * pitch
    table = radial_distortion(lens)
    ideal = float(table.ideal_from_real(min(corner, table.reach_real_mm)))
    pull = max(0.0, ideal - corner) / pitch
    fo = first_order(focused)
    f, D = fo.effective_focal_length_mm, fo.entrance_pupil_diameter_mm
    s = 1000.0 * focus_of(focused)
    depths = [sh.depth_m for sh in scene.shapes if isinstance(sh, Plane)]
    blur = max(D * f * abs(1.0 / (1000.0 * z) - 1.0 / s) / max(1e-9, 1.0 - f / s) for z in depths) / 2.0 / pitch
    return int(math.ceil(pull * 1.05 + blur + 4))


def focus_of(focused) -> float:
    """The paraxial in-focus distance (m) of a refocused lens."""
    from dcdi_core.optics.paraxial import first_order
    return float(first_order(focused).in_focus_object_distance_m)


def scene_for(lens, geometry) -> Scene:
    """The default scene over ``geometry``'s frame (ideal, seen from the entrance pupil)."""
    k = ideal_scale_mm(lens)
    pitch = geometry.pixel_pitch_mm
    return default_scene(geometry.width / 2.0 * pitch / k, geometry.height / 2.0 * pitch / k, pitch / k)


def fast_bokeh(lens, image, depth, geometry, focus_m: float):
    """The engine's bokeh of the over-scan pinhole RGB-D, as `dcdi bokeh
    --distort --focus D --pixel-pitch P --sensor-size H W` runs it:
    (BokehResult, seconds)."""
    from dcdi_core.app import BokehRequest, bokeh
    from dcdi_core.render.request import RenderRequest
    render = RenderRequest(lens, image_pixel_pitch_mm=geometry.pixel_pitch_mm,
                           sensor_size=(geometry.height, geometry.width))
    t = time.perf_counter()
    r = bokeh(BokehRequest(np.asarray(image, np.float32), depth, lens, focus_m=focus_m, render=render,
                           distortion=True))
    return r, time.perf_counter() - t


def psnr(a, b, mask=None) -> float:
    d = (np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2
    if mask is not None:
        d = d[mask]
    mse = float(d.mean()) if d.size else math.nan
    return math.inf if mse == 0 else 10.0 * math.log10(PEAK * PEAK / mse) if math.isfinite(mse) else math.nan


def edge_band(depth, occluder_depth_m: float, band: int = EDGE_BAND_PX) -> np.ndarray:
    """(H, W) bool: pixels within ``band`` px (Chebyshev) of where the
    occluder (depth within 1 % of ``occluder_depth_m``) meets anything else."""
    from scipy.ndimage import binary_dilation
    occ = np.abs(np.nan_to_num(depth, nan=-1.0, posinf=1e9) - occluder_depth_m) < 0.01 * occluder_depth_m
    edge = np.zeros_like(occ)
    edge[:, 1:] |= occ[:, 1:] != occ[:, :-1]
    edge[1:, :] |= occ[1:, :] != occ[:-1, :]
    return binary_dilation(edge, np.ones((3, 3), bool), iterations=band)


def light_pixels(focused, scene: Scene, geometry) -> list:
    """(row, col) where each light's real chief ray (design wavelength,
    the focused lens) lands on the frame."""
    from dcdi_core.optics.aiming import aim_chief, chief_ray_sensor_y
    from dcdi_core.optics.paraxial import first_order
    z_ep = first_order(focused).entrance_pupil_position_mm
    out = []
    for i in scene.lights:
        x, y, z = scene.shapes[i].center_m
        rho = math.hypot(x, y)
        p = 1000.0 * rho / (1000.0 * z + z_ep)
        a = aim_chief(focused, np.array([1000.0 * z]), np.array([p]))
        h = float(chief_ray_sensor_y(focused, a)[0][0])
        ux, uy = (x / rho, y / rho) if rho > 0 else (0.0, 0.0)
        xs, ys = -h * ux, -h * uy                   # the image is inverted
        cr, cc = geometry.center_px
        out.append((cr + ys / geometry.pixel_pitch_mm, cc - xs / geometry.pixel_pitch_mm))
    return out


def light_boost(focused, scene: Scene, geometry, centers) -> np.ndarray:
    """(H, W) bool: the pixels within reach of a light's blur: its radius,
    1.3 x its paraxial blur radius and 3 px about where its chief ray lands
    (geometry only: chosen before any ray is traced)."""
    from dcdi_core.optics.paraxial import first_order
    fo = first_order(focused)
    f, D = fo.effective_focal_length_mm, fo.entrance_pupil_diameter_mm
    s = 1000.0 * focus_of(focused)
    rows, cols = np.mgrid[0:geometry.height, 0:geometry.width]
    out = np.zeros((geometry.height, geometry.width), bool)
    for i, (r0, c0) in zip(scene.lights, centers):
        z = 1000.0 * scene.shapes[i].center_m[2]
        blur = D * f * abs(1.0 / z - 1.0 / s) / max(1e-9, 1.0 - f / s) / 2.0 / geometry.pixel_pitch_mm
        reach = 1.3 * blur + LIGHT_RADIUS_PX + 3.0
        out |= (rows - r0) ** 2 + (cols - c0) ** 2 <= reach * reach
    return out


def crop_mask(shape, center, size: int = LIGHT_CROP_PX):
    """(H, W) bool of the size x size crop centred at ``center`` (row, col), clipped to the frame; None if outside."""
    r, c = int(round(center[0])), int(round(center[1]))
    h = size // 2
    if not (0 <= r < shape[0] and 0 <= c < shape[1]):
        return None
    m = np.zeros(shape, bool)
    m[max(0, r - h):r + h + 1, max(0, c - h):c + h + 1] = True
    return m


def score_case(case: Case, size=DEFAULT_SIZE, rays: int = DEFAULT_RAYS, seed: int = 0, log=None,
               images: dict | None = None, boost: int = BOOST) -> dict:
    """One row of the table: the traced render, the pinhole RGB-D, the
    engine's bokeh, their PSNRs, the noise floor and the times.
    ``images``: filled with the arrays, if given."""
    lens, focused = case_lenses(case)
    geometry = frame_geometry(lens, size)
    scene = scene_for(lens, geometry)
    margin = min(overscan_px(lens, focused, geometry, scene), 2 * max(size))
    from dcdi_core.render.geometry import ImageGeometry
    source = ImageGeometry.from_pixel_pitch(lens, geometry.height + 2 * margin, geometry.width + 2 * margin,
                                            geometry.pixel_pitch_mm)
    t0 = time.perf_counter()
    pin, depth = pinhole_render(lens, scene, source, seed=seed)
    t_pin = time.perf_counter() - t0
    fast, t_fast = fast_bokeh(lens, pin, depth, geometry, case.focus_m)
    centers = light_pixels(focused, scene, geometry)
    traced = traced_render(focused, scene, geometry, rays, seed, log=log, boost_factor=boost,
                           boost=light_boost(focused, scene, geometry, centers))
    truth, (a, b) = traced.image, traced.halves
    sensor_depth = fast.depth_m if fast.depth_m is not None else depth[margin:-margin, margin:-margin]
    band = edge_band(sensor_depth, scene.shapes[scene.occluder].depth_m)
    crops = [crop_mask(truth.shape[:2], c) for c in centers]
    rest = ~np.logical_or.reduce([m for m in crops if m is not None] + [np.zeros(truth.shape[:2], bool)])
    est = fast.image.astype(np.float64)
    noise = 10.0 * math.log10(4.0)
    row = {
        "lens": case.lens_id, "f_number": case.f_number, "f_number_used": _f_number(lens),
        "focus_m": case.focus_m, "size": list(size), "pitch_mm": geometry.pixel_pitch_mm, "overscan_px": margin,
        "rays": rays,
        "psnr_frame": psnr(est, truth), "psnr_rest": psnr(est, truth, rest), "psnr_edge": psnr(est, truth, band),
        "psnr_lights": [psnr(est, truth, m) if m is not None else None for m in crops],
        "floor_frame": psnr(a, b) + noise, "floor_rest": psnr(a, b, rest) + noise,
        "floor_edge": psnr(a, b, band) + noise,
        "floor_lights": [psnr(a, b, m) + noise if m is not None else None for m in crops],
        "passed_fraction": float(traced.passed.mean()), "boosted_pixels": traced.boosted_pixels,
        "boost": traced.boost_factor,
        "seconds_traced": traced.seconds, "seconds_fast": t_fast, "seconds_pinhole": t_pin,
        "edge_pixels": int(band.sum()),
    }
    if images is not None:
        images.update(traced=truth.astype(np.float32), halves=traced.halves.astype(np.float32),
                      fast=fast.image, pinhole=pin, pinhole_depth=depth, sensor_depth=sensor_depth, edge_band=band)
    return row


def _f_number(lens) -> float:
    from dcdi_core.optics.aperture import wide_open_f_number
    return wide_open_f_number(lens)


# ------------------------------------------------------------------ the table
def cases_for(lens_ids, foci=FOCI_M, f_numbers=None) -> list[Case]:
    """Every lens wide open and at f/5.6 (skipped where the lens is slower)
    at each focus; ``f_numbers``: these instead of f/5.6 (None in it: wide
    open), refused where faster than the lens."""
    from dcdi_core.optics.aperture import OPEN_TOLERANCE, wide_open_f_number
    from dcdi_core.optics.lens import load_lens
    out = []
    for lid in lens_ids:
        n0 = wide_open_f_number(load_lens(lid))
        stops = [None] + ([STOPPED_F_NUMBER] if STOPPED_F_NUMBER >= n0 * (1 - OPEN_TOLERANCE) else []) \
            if f_numbers is None else list(f_numbers)
        for n in stops:
            for f in foci:
                out.append(Case(lid, n, float(f)))
    return out


def _num(v, digits=1) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "-"
    return "inf" if v == math.inf else f"{v:.{digits}f}"


def format_table(rows: list[dict]) -> str:
    """The markdown table: PSNR (dB) of the engine's bokeh against the traced
    render over the frame, the frame without the lights' crops, the band at
    the occluder's edge and each light's crop; the traced render's noise
    floor in the same regions (the lights: the lowest); the seconds of each."""
    out = ["| lens | f/ | focus m | frame | frame w/o lights | edge | lights | floor: frame / w/o lights / edge / "
           "lights (min) | traced s | engine s |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lights = " / ".join(_num(v) for v in r["psnr_lights"])
        fl = [v for v in r["floor_lights"] if v is not None]
        floor = (f"{_num(r['floor_frame'])} / {_num(r['floor_rest'])} / {_num(r['floor_edge'])} / "
                 f"{_num(min(fl) if fl else None)}")
        stop = f"{r['f_number_used']:.3g}" + (" (open)" if r["f_number"] is None else "")
        out.append(f"| {r['lens']} | {stop} | {r['focus_m']:g} | {_num(r['psnr_frame'])} | {_num(r['psnr_rest'])} "
                   f"| {_num(r['psnr_edge'])} | {lights} | {floor} | {r['seconds_traced']:.1f} "
                   f"| {r['seconds_fast']:.1f} |")
    return "\n".join(out) + "\n"


def _check(args):
    """Every error a user can cause, before any work: the lenses, f-numbers,
    focus distances, size, rays and the output folder."""
    from dcdi_core.errors import InputRangeError, check_writable_folder
    from dcdi_core.optics.aperture import Aperture, stopped_down
    from dcdi_core.optics.lens import available_lenses, load_lens
    from dcdi_core.optics.paraxial import refocused
    from dcdi_core.psf.library import LibraryGrid
    from dcdi_core.render.geometry import ImageGeometry
    if args.rays < 2 or args.rays % 2:
        raise InputRangeError("--rays", args.rays, "an even number >= 2 (rays a pixel, in two halves)")
    if args.boost < 1:
        raise InputRangeError("--boost", args.boost, "an integer >= 1")
    if min(args.size) < 8 or max(args.size) > 2048:
        raise InputRangeError("--size", tuple(args.size), "two integers in [8, 2048] (rows, columns)")
    near = LibraryGrid().near_m
    for f in args.focus:
        if not (math.isfinite(f) and f >= near):
            raise InputRangeError("--focus", f, f"a distance >= {near:g} m (the nearest depth of the engine's PSFs), "
                                                "finite")
    ids = args.lenses or available_lenses()
    for lid in ids:
        lens = load_lens(lid)
        for n in (args.f_number or []):
            if n is not None:
                stopped_down(lens, Aperture(n))
        for f in args.focus:
            refocused(lens, f)
        ImageGeometry.full_sensor(lens, *args.size)
    if args.out:
        check_writable_folder(args.out, f"--out {args.out}")
    return ids


def engine_state() -> dict:
    """The engine the scores are of: the checkout's commit and its files
    under dcdi_core/ changed since (the table is of the working tree)."""
    import subprocess
    from pathlib import Path
    root = Path(__file__).resolve().parents[1]
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=root, capture_output=True, text=True,
                              timeout=30).stdout.strip()
        changed = subprocess.run(["git", "status", "--porcelain", "--", "dcdi_core"], cwd=root, capture_output=True,
                                 text=True, timeout=30).stdout.splitlines()
    except (OSError, subprocess.SubprocessError):
        return {}
    return {"commit": head, "changed": sorted(line[3:] for line in changed if line.strip())}


def _stop(text: str):
    """An f-number option's value: a number, or 'open' (None: wide open)."""
    if text.strip().lower() == "open":
        return None
    try:
        return float(text)
    except ValueError:
        import argparse
        raise argparse.ArgumentTypeError(f"{text!r}: a number or 'open'") from None


def main(argv=None) -> int:
    import argparse
    from pathlib import Path
    p = argparse.ArgumentParser(prog="python -m lab traced-render",
                                description="the fast bokeh (--distort --focus) against a render traced through "
                                            "the lens, lens by lens (module docstring of lab/traced_render.py)")
    p.add_argument("--lenses", nargs="+", default=None, metavar="ID", help="lens ids (default: every catalogue lens)")
    p.add_argument("--out", default=None, metavar="DIR", help="folder for traced-render.md and traced-render.json")
    p.add_argument("--rays", type=int, default=DEFAULT_RAYS, help=f"rays a pixel, both halves (default {DEFAULT_RAYS})")
    p.add_argument("--size", type=int, nargs=2, default=list(DEFAULT_SIZE), metavar=("H", "W"),
                   help=f"the frame: the full sensor at H x W px (default {DEFAULT_SIZE[0]} {DEFAULT_SIZE[1]})")
    p.add_argument("--focus", type=float, nargs="+", default=list(FOCI_M), metavar="D",
                   help="focus distances, metres (default 1.5 5)")
    p.add_argument("--f-number", type=_stop, nargs="+", default=None, metavar="N",
                   help="f-numbers instead of wide open and f/5.6, 'open' for wide open (one faster than a lens "
                        "is refused)")
    p.add_argument("--boost", type=int, default=BOOST,
                   help=f"rays a pixel times this where a light's blur falls (default {BOOST})")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--save-images", action="store_true", help="also write each case's images to --out (.npz)")
    args = p.parse_args(argv)
    from dcdi_core.cli.common import one_line
    from dcdi_core.errors import DcdiError
    try:
        ids = _check(args)
    except DcdiError as e:
        print(f"lab: error: {one_line(str(e))}", file=sys.stderr)
        return 2

    def log(text):
        print(text, file=sys.stderr, flush=True)

    cases = cases_for(ids, args.focus, args.f_number)
    state = engine_state()
    rows = []
    t0 = time.perf_counter()
    out = Path(args.out) if args.out else None
    for i, case in enumerate(cases):
        stop = "open" if case.f_number is None else f"f/{case.f_number:g}"
        log(f"[{i + 1}/{len(cases)}] {case.lens_id} {stop} focus {case.focus_m:g} m")
        images = {} if (args.save_images and out) else None
        row = score_case(case, tuple(args.size), args.rays, args.seed, log=log, images=images, boost=args.boost)
        rows.append(row)
        log(f"  frame {_num(row['psnr_frame'])} dB (w/o lights {_num(row['psnr_rest'])}), edge {_num(row['psnr_edge'])} dB, lights "
            f"{' / '.join(_num(v) for v in row['psnr_lights'])} dB; floor {_num(row['floor_frame'])} dB; "
            f"traced {row['seconds_traced']:.1f} s, engine {row['seconds_fast']:.1f} s "
            f"({time.perf_counter() - t0:.0f} s in all)")
        if images is not None:
            out.mkdir(parents=True, exist_ok=True)
            np.savez_compressed(out / f"{case.lens_id}-{stop.replace('/', '')}-{case.focus_m:g}m.npz", **images)
    total = time.perf_counter() - t0
    text = format_table(rows)
    pitches = sorted({(r["lens"], round(1000 * r["pitch_mm"], 1)) for r in rows}, key=lambda t: t[1])
    by_pitch = {}
    for lid, um in pitches:
        by_pitch.setdefault(um, []).append(lid)
    head = (f"Frame: the full sensor at {args.size[0]} x {args.size[1]} px (pitch "
            + "; ".join(f"{um:g} um: {len(ids)} lens{'es' if len(ids) > 1 else ''}" for um, ids in by_pitch.items())
            + f"); {args.rays} rays a pixel ({args.boost} x where a light's blur falls); PSNR in dB (peak 1.0); "
              f"{total:.0f} s in all; the engine of commit {state.get('commit', '?')}"
            + (f" with {len(state['changed'])} files of dcdi_core/ changed" if state.get("changed") else "")
            + ".\n\n") if rows else ""
    print(head + text, end="")
    if out:
        from dcdi_core.atomic import write_text
        out.mkdir(parents=True, exist_ok=True)
        write_text(out / "traced-render.md", head + text)
        write_text(out / "traced-render.json", json.dumps({"size": list(args.size), "rays": args.rays,
                                                           "boost": args.boost, "seed": args.seed, "seconds": total,
                                                           "engine": state, "rows": rows}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
