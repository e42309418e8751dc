"""Lens bokeh on an all-in-focus RGB-D image.

bokeh(): the depth of field of a target lens on a sharp image, as one
:class:`BokehOptions` says. What is kept sharp is a depth range [near, far]
(the paper's mask: identity PSF inside it), a focus distance (the library
refocused there) or the lens as prescribed; optionally with the lens's
distortion first. Two renderers:
``occlusion=False`` is the plain patch-wise blur; ``occlusion=True`` (the
default) splits the scene into depth layers and composites them back to
front, each blurred with its own PSFs and carrying its blurred coverage, so
a sharp subject does not bleed into a blurred background nor get a halo.

The input checks, the library at the image's pitch, the move onto the
sensor and the result are the simulation's (``render.simulate``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from ..errors import InputRangeError
from ..psf.compute import PSFSettings
from ..parallel import thread_pool, workers
from ..psf.library import PSFLibrary
from . import layer_patch
from . import multires as mr
from .convolve import METHODS, ConvolveOptions, box_reach, patch_box, patch_convolve
from .windows import grow_square
from .geometry import ImageGeometry
from .inputs import check_rgbd
from .psfmap import PSFMap, psf_map
from ..psf.library import valid_depth_mask
from .base import DEFAULT_INTERPOLATION, Cancelled, RenderResult, check_flag, check_image, check_library_pitch, check_patch, check_within_sensor, on_sensor
from ..psf.sources import lens_library

PRESCRIBED = "prescribed"     # BokehOptions(focus_m=PRESCRIBED): the sensor where the prescription puts it
LAYER_PAIRS = ((0, 0), (1, 1), (2, 2), (3, 0), (3, 1), (3, 2))   # a layer's colour, and its coverage per colour PSF


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

    interp_eps: each depth layer is blurred with the cheapest patches
    (``patch`` with the tent, or 32 or 64 px with 8-px ramps) whose blur of
    sampled layer pixels lies at most this RMS fraction of it further from
    their blur with their own PSFs than the tent's (``render.layer_patch``),
    in (0, 1); None: every layer at ``patch`` with the tent (the exact
    path). seam_tol: adjacent layers that meet without a depth edge (99 %
    of their touching pixels within this fraction of a layer's width in
    diopters) are blurred as one (a floor is not cut into bands), in [0,
    1]; None: never. Neither applies with ``multires``.

    large_blur: where the traced library's kernel, grown to its cap
    (``psf.library.MAX_FITTED_KERNEL`` px), clips a layer's blur (more than 1 %
    of a channel's energy outside), that layer is
    blurred at 1/f of the resolution (f = 2, 4 or 8: the smallest whose
    kernel holds it) with PSFs made at f times the pitch by the library's source, and brought back
    by Keys' cubic (``multires.coarse_blur``); False: clipped, with the
    library's warning. The occlusion-aware renderer only, without ``multires``.

    coarse_blur: a depth layer whose every kernel holds half its energy
    beyond a radius of coarse_blur x f px (``multires.radius_table``) is
    blurred at 1/f of the resolution (f = 2, 4 or 8, the largest that
    holds) with PSFs made at f times the pitch, as a large blur is (a
    wide blur keeps nothing of the detail the coarse grid drops); None:
    every layer the kernel holds at full resolution. The error budget
    (``psf.budget``) sets it. Occlusion-aware, without ``multires``.

    support_eps: each patch's kernel is cropped to the disc that holds all
    but this fraction of every channel's energy, rescaled to its sum (the
    FFT windows' size: ``ConvolveOptions.support_eps``), in [0, 0.2]; the
    error budget may raise it (a fast lens's faint halo is wide).
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
    interp_eps: float | None = 0.002
    seam_tol: float | None = 0.25
    large_blur: bool = True
    coarse_blur: float | None = None
    support_eps: float = 1e-3

    def __post_init__(self):
        from .distortion import check_interpolation
        self._check_sharpness()
        for name in ("geometry", "source_geometry"):
            if getattr(self, name) is not None and not isinstance(getattr(self, name), ImageGeometry):
                raise InputRangeError(name, getattr(self, name), "an ImageGeometry, or None")
        for name in ("distortion", "occlusion", "fit_kernel", "large_blur"):
            check_flag(name, getattr(self, name))
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
        self.multires_options()                           # checks the level rule and coarse_patch
        for name, lo, hi, low_open in (("interp_eps", 0.0, 1.0, True), ("seam_tol", 0.0, 1.0, False)):
            value = getattr(self, name)
            if value is not None and not (isinstance(value, (int, float, np.floating)) and not isinstance(value, bool)
                                          and (lo < value if low_open else lo <= value) and value <= hi):
                raise InputRangeError(name, value, f"a fraction in {'(' if low_open else '['}{lo:g}, {hi:g}], or None")
        e = self.support_eps
        if isinstance(e, bool) or not isinstance(e, (int, float, np.floating)) or not 0.0 <= e <= 0.2:
            raise InputRangeError("support_eps", e, "a fraction of a kernel's energy in [0, 0.2]")
        c = self.coarse_blur
        if c is not None and (isinstance(c, bool) or not isinstance(c, (int, float, np.integer, np.floating))
                              or not math.isfinite(c) or not c >= 1.0):
            raise InputRangeError("coarse_blur", c, "a radius in pixels >= 1 (finite), or None")
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
                raise InputRangeError("keep", keep, "(near, far) with 0 < near <= far metres")
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
        return ConvolveOptions(method=self.convolution, rank_eps=self.rank_eps, fft_backend=self.fft_backend,
                               support_eps=self.support_eps)

    def multires_options(self) -> mr.MultiresOptions:
        """The multi-resolution blur's options (``multires.grouped_blur``)."""
        return mr.MultiresOptions(self.multires, patch=self.patch, max_level=self.max_level,
                                  coarse_patch=self.coarse_patch, fft_backend=self.fft_backend)


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
    return _layered_bokeh(scene, options, cancelled, layer_progress, progress)


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
    lens: object = None        # the lens (a large blur's coarse PSFs are traced for it)

    def result(self, image: np.ndarray, info: dict, pm: PSFMap | None = None) -> RenderResult:
        return RenderResult(image, info, self.img if self.moved else None, pm,
                            depth=self.depth if self.moved else None)


def _bokeh_scene(image, depth, lens, options: BokehOptions, library: PSFLibrary | None, progress) -> _BokehScene:
    """The checked input moved onto the sensor (distortion, over-scan), and
    the library (opened if none is given)."""
    img, d = check_image(image, depth, options.source_geometry)
    check_rgbd(img, d)
    source = options.source_geometry
    geometry = options.geometry or source or ImageGeometry.full_sensor(lens, img.shape[0], img.shape[1])
    check_within_sensor(geometry)
    moved = options.distortion or (source is not None and source != geometry)
    if moved:
        from ..psf.library import LibraryGrid
        from .distortion import chief_ray_map
        # the lens's chief rays at the focus, per depth (breathing, depth-dependent distortion)
        near_m = (library.grid if library is not None else LibraryGrid()).near_m
        table = chief_ray_map(lens, focus_m=options.focus_distance_m, near_m=near_m) if options.distortion else None
        img, d, _ = on_sensor(img, d, lens, geometry, source_geometry=source, distortion=table,
                              interpolation=options.interpolation)
    if library is None:
        library = lens_library(lens, geometry, options.library_settings(), response=options.response,
                               fit_depth_m=d if options.fit_kernel else None, progress=progress)
    check_library_pitch(library, geometry)
    valid = valid_depth_mask(d)
    inv = np.where(valid & (d < library.grid.far_m), 1.0 / np.where(valid, d, 1.0), 0.0)
    keep = options.keep
    kept = np.zeros(d.shape, bool) if keep is None else valid & (d >= keep[0]) & (d <= keep[1])
    info = {"convolution": options.convolution, "occlusion": options.occlusion,
            "distortion": bool(options.distortion), "kept_pixels": int(kept.sum()),
            "invalid_depth_pixels": int((~valid).sum()), "multires": options.multires}
    # each layer (plain: each patch group) is blurred on its own patch-aligned
    # bounding box, grown by the kernel's reach: outside it the blur is zero
    grow = box_reach(library.kernel_size, options.patch)
    return _BokehScene(img, d, moved, geometry, library, valid, inv, kept, grow, info, lens)


def _plain_bokeh(sc: _BokehScene, options: BokehOptions, cancelled) -> RenderResult:
    """The plain patch-wise blur (``occlusion=False``)."""
    if cancelled is not None and cancelled():
        raise Cancelled("bokeh cancelled")
    if options.multires is not None:
        out, mi = mr.plain_blur(sc.img, sc.depth, sc.library, sc.geometry, options.multires_options(),
                                keep_range_m=options.keep)
        return sc.result(out, dict(sc.info, **mi))
    pm = psf_map(sc.library, sc.geometry, sc.depth, options.patch, keep_range_m=options.keep,
                 support_eps=options.support_eps)
    out = patch_convolve(sc.img, pm.kernels, options.patch, options.convolve_options(), identity=pm.identity)
    return sc.result(out, dict(sc.info, **pm.info), pm)


# the diopter range is seen in this many bins when the layers share out the depths the frame holds
LAYER_BINS = 1024


def _layer_edges(values: np.ndarray, lo: float, hi: float, n_layers: int) -> np.ndarray:
    """(n_layers + 1,) diopter edges: equal shares of the depths the frame
    holds (the occupied ones of LAYER_BINS bins over [lo, hi]), so that an
    empty stretch of depth between two objects takes no layer: a light at 7
    m before a wall at 9 m gets a layer of its own beside a near occluder,
    where equal widths over the whole range put both in one (and the light
    took the wall's blur). A continuous range of depths keeps equal widths;
    no layer is ever wider than equal widths over [lo, hi] would make it."""
    counts, _ = np.histogram(values, bins=LAYER_BINS, range=(lo, hi))
    occupied = np.concatenate([[0], np.cumsum(counts > 0)])
    at = np.searchsorted(occupied, np.linspace(0.0, occupied[-1], n_layers + 1), side="left")
    edges = lo + (hi - lo) * np.clip(at, 0, LAYER_BINS) / LAYER_BINS
    edges[0], edges[-1] = lo, hi
    return np.maximum.accumulate(edges)


def _layer_masks(inv: np.ndarray, valid: np.ndarray, n_layers: int):
    """([(layer index, mask)] of the non-empty depth layers, far to near
    (:func:`_layer_edges`: equal shares of the occupied diopters); the (H, W)
    layer index, -1 off ``valid``."""
    lo, hi = float(inv[valid].min()), float(inv[valid].max())
    if hi - lo < 1e-12:
        return [(0, valid)], np.where(valid, 0, -1)
    edges = _layer_edges(inv[valid], lo, hi, n_layers)
    idx = np.where(valid, np.clip(np.searchsorted(edges, inv, side="right") - 1, 0, n_layers - 1), -1)
    return [(i, idx == i) for i in range(n_layers) if (idx == i).any()], idx


def _merge_continuous(sc: _BokehScene, layers: list, idx: np.ndarray, tol: float) -> list:
    """Adjacent depth layers (far to near) joined where they meet without a
    depth edge: a layer joins the group before it when it touches the last
    of them and, across 99 % of the pixel pairs where it touches any of
    them, the diopters jump by at most ``tol`` of a layer's width. A
    continuous surface cut by the layering (a floor, a wall at a slant)
    occludes nothing of itself, and its bands composited one over another
    equal their sum up to the difference of the kernels across that jump;
    a depth edge between any two members keeps them apart (a chain of
    floor bands does not join a board standing on it to a disk in front
    of it). Never across the kept range."""
    if len(layers) < 2:
        return [m_ for _, m_ in layers]
    limit = tol * _layer_width(sc, idx)
    barrier = float(sc.inv[sc.kept].mean()) if sc.kept.any() else None
    seam = _seams(idx, sc.inv)
    groups = [[layers[0]]]
    for label, mask in layers[1:]:
        group = groups[-1]
        last_label, last_mask = group[-1]
        crosses = barrier is not None and float(sc.inv[last_mask].max()) < barrier < float(sc.inv[mask].min())
        smooth = all(np.quantile(seam[(g, label)], 0.99) <= limit for g, _ in group if (g, label) in seam)
        if (last_label, label) in seam and smooth and not crosses:
            group.append((label, mask))
        else:
            groups.append([(label, mask)])
    return [np.logical_or.reduce([m_ for _, m_ in g]) for g in groups]


def _layer_width(sc: _BokehScene, idx: np.ndarray) -> float:
    """A depth layer's width in diopters."""
    inv = sc.inv[idx >= 0]
    return float(inv.max() - inv.min()) / max(1, int(idx.max()) + 1)


def _seams(idx: np.ndarray, inv: np.ndarray) -> dict:
    """{(layer a, layer b): the diopter jumps (n,) across the 4-neighbour
    pixel pairs where a layer a pixel touches a layer b pixel, a < b}."""
    pairs = []
    for sl_a, sl_b in (((slice(None), slice(None, -1)), (slice(None), slice(1, None))),
                       ((slice(None, -1), slice(None)), (slice(1, None), slice(None)))):
        a, b = idx[sl_a], idx[sl_b]
        sel = (a >= 0) & (b >= 0) & (a != b)
        pairs.append((np.minimum(a, b)[sel], np.maximum(a, b)[sel], np.abs(inv[sl_a] - inv[sl_b])[sel]))
    lo, hi, jump = (np.concatenate(x) for x in zip(*pairs))
    order = np.lexsort((hi, lo))
    lo, hi, jump = lo[order], hi[order], jump[order]
    cut = np.flatnonzero((np.diff(lo) != 0) | (np.diff(hi) != 0)) + 1
    return {(int(a[0]), int(b_[0])): j for a, b_, j in zip(np.split(lo, cut), np.split(hi, cut), np.split(jump, cut))
            if len(a)}


def _layer_order(sc: _BokehScene, n_layers: int, seam_tol: float | None = None) -> list[tuple[np.ndarray, bool]]:
    """The layers far to near, as (mask, sharp): the blurred depth layers,
    and the kept (sharp) pixels with the invalid ones as one layer at their
    depth (first when nothing is kept)."""
    sharp_mask = sc.kept | ~sc.valid
    blurred = sc.valid & ~sc.kept
    layers = []
    if blurred.any():
        labelled, idx = _layer_masks(sc.inv, blurred, n_layers)
        layers = [m_ for _, m_ in labelled] if seam_tol is None else _merge_continuous(sc, labelled, idx, seam_tol)
    order = [(float(sc.inv[m_].mean()), m_, False) for m_ in layers]
    if sharp_mask.any():
        order += [(float(sc.inv[sc.kept].mean()) if sc.kept.any() else -1.0, sharp_mask, True)]
    order.sort(key=lambda t: t[0])                        # far (small diopters) first
    return [(m_, s_) for _, m_, s_ in order]


def _layered_bokeh(sc: _BokehScene, options: BokehOptions, cancelled, layer_progress, progress=None) -> RenderResult:
    """The occlusion-aware renderer: the layers, back to front, each layer's
    colour and coverage blurred alike and composited over what lies behind."""
    # ``col`` is the colour seen so far, un-premultiplied, with ``acc`` its
    # coverage (per colour): a layer goes over what lies behind in proportion
    # to that coverage, and the sum is normalised by the coverage of both, so
    # what lies behind a layer where little farther was seen (hidden by a
    # nearer layer, or the farthest layer's own holes) takes the colour spread
    # from around it (normalised blur) instead of black: no dark seam where a
    # continuous surface crosses from one layer to the next, no dark halo; and
    # a faint far layer (a light's blur seen through a hole) stays as faint as
    # its coverage says, not raised to its full colour where nothing else was.
    col = np.zeros_like(sc.img)
    acc = np.zeros_like(sc.img)
    order = _layer_order(sc, options.n_layers, options.seam_tol if options.multires is None else None)
    table = None
    if options.multires is not None and sc.valid.any():
        sc.library.ensure(bins=sc.library.bins_needed(sc.depth[sc.valid], clamp_near=True))
        table = mr.radius_table(sc.library)
    info = dict(sc.info, layer_levels=[])            # multires: per layer, its patches at each level
    large = _large_blur(sc, options, cancelled, progress)
    if large is not None:
        info["large_blur_factor"] = large.f
    coarse = {} if large is None else {large.f: large}       # f -> the PSFs at f times the pitch
    radii = _coarse_radii(sc, options)
    for n_done, (mask, is_sharp) in enumerate(order):
        if layer_progress is not None:
            layer_progress(n_done, len(order))
        if cancelled is not None and not is_sharp and cancelled():
            raise Cancelled("bokeh cancelled")
        ys, xs = patch_box(mask, options.patch, sc.grow if not is_sharp else 0)
        choice, f, clipped = None, 1, False
        if not is_sharp:
            clipped = large is not None and _clipped(sc.library, sc.depth[mask])
            f = max(large.f if clipped else 1, _coarse_factor(sc, options, mask, radii))
        if not is_sharp and f == 1 and options.interp_eps is not None and options.multires is None:
            choice = _layer_patch(sc, options, mask)
            info.setdefault("layer_patches", []).append(choice.info())
            if choice.m != options.patch:
                ys, xs = patch_box(mask, choice.m, box_reach(sc.library.kernel_size, choice.m))
        if is_sharp:
            a = mask[ys, xs][..., None]
            col[ys, xs] = np.where(a, sc.img[ys, xs], col[ys, xs])
            acc[ys, xs] = np.where(a, np.float32(1.0), acc[ys, xs])
            continue
        if f > 1:
            if f not in coarse:
                coarse[f] = _coarse_psfs(sc, f, cancelled, progress)
            blurred, ys, xs = _blur_layer_coarse(sc, mask, coarse[f], options.support_eps)
            levels = None
            _clamp_overshoot(blurred, sc.img[mask].max(axis=0))
            key = "large_blur_layers" if clipped else "coarse_blur_layers"
            info[key] = info.get(key, 0) + 1
        else:
            blurred, levels = _blur_layer(sc, options, mask, ys, xs, table, choice)
        if levels is not None:
            info["layer_levels"].append([int((levels == s_).sum()) for s_ in range(options.max_level + 1)])
            if int(levels.max()) > 0:
                _clamp_overshoot(blurred, sc.img[ys, xs][mask[ys, xs]].max(axis=0))
        _composite(col, acc, ys, xs, blurred)
    if layer_progress is not None:
        layer_progress(len(order), len(order))
    info["layers"] = len(order)
    if large is not None:           # the coarse kernels may clip too (a blur past 8 x the kernel): said, not hidden
        text = getattr(large.library, "clip_text", lambda: None)()
        if text:
            info["large_blur_clipped"] = text
    return sc.result(col, info)


LARGE_BLUR_MAX_LEVEL = 3        # a large blur at 1/8 of the resolution at most: kernels up to 8 x the library's


@dataclass(frozen=True)
class _LargeBlur:
    """What blurs the layers the image-pitch kernel clips: ``f`` (the
    resolution's divisor), the PSFs made at f times the pitch and the
    coarse grid's geometry."""

    f: int
    library: PSFLibrary
    geometry: ImageGeometry


CLIPPED = 0.01              # a kernel that leaves more than this fraction of a channel's energy out clips a blur


def _clipped(library, depth_m: np.ndarray) -> bool:
    """Whether the library's kernel leaves more than CLIPPED of a channel's
    energy out, in any of these depths' bins (what its warning says)."""
    bins = library.bins_needed(depth_m[valid_depth_mask(depth_m)], clamp_near=True)
    if not len(bins):
        return False
    return bool(library.energy_outside[bins].max() > CLIPPED)


def _large_blur(sc: _BokehScene, options: BokehOptions, cancelled=None, progress=None) -> _LargeBlur | None:
    """The coarse PSFs of a large blur (BokehOptions.large_blur), or None
    where the library's kernel holds every layer's blur (or cannot say:
    a PSF basis or the OLF says nothing clips). A ray map's coarse PSFs come
    from the same ray map. Their bins are traced with
    ``progress(done, total)`` called, and ``cancelled()`` asked, after each."""
    lib = sc.library
    blurred = sc.valid & ~sc.kept
    from ..psf import library as psf_library
    # a kernel below the cap was chosen (a given library, an explicit size): it is the caller's, clipped or not
    if (not options.large_blur or options.multires is not None or sc.lens is None or not isinstance(lib, PSFLibrary)
            or lib.kernel_size < psf_library.MAX_FITTED_KERNEL or not blurred.any()):
        return None
    lib.ensure(bins=lib.bins_needed(sc.depth[blurred], clamp_near=True))
    need = int(lib.kernel_size_needed[lib.computed].max())
    if need <= lib.kernel_size or not _clipped(lib, sc.depth[blurred]):
        return None
    f = 2 ** min(LARGE_BLUR_MAX_LEVEL, math.ceil(math.log2(need / lib.kernel_size)))
    return _coarse_psfs(sc, f, cancelled, progress)


def _coarse_radii(sc: _BokehScene, options: BokehOptions) -> np.ndarray | None:
    """The half-energy radius (px) of each of the library's kernels of the
    blurred depths (``multires.radius_table``), where ``options.coarse_blur``
    asks for coarse layers; else None."""
    blurred = sc.valid & ~sc.kept
    if options.coarse_blur is None or options.multires is not None or sc.lens is None or not blurred.any() \
            or not isinstance(sc.library, PSFLibrary):
        return None
    sc.library.ensure(bins=sc.library.bins_needed(sc.depth[blurred], clamp_near=True))
    return mr.radius_table(sc.library)


def _coarse_factor(sc: _BokehScene, options: BokehOptions, mask: np.ndarray, radii) -> int:
    """1, or the f (2, 4, 8) at which the layer ``mask`` is blurred: the
    largest with every kernel of its depth bins (all fields) holding half its
    energy beyond ``options.coarse_blur`` x f px."""
    if radii is None:
        return 1
    bins = sc.library.bins_needed(sc.depth[mask & sc.valid], clamp_near=True)
    if not len(bins):
        return 1
    r = float(radii[bins].min())
    s = int(mr.level_for(r, options.coarse_blur, LARGE_BLUR_MAX_LEVEL))
    return 2 ** s


def _coarse_psfs(sc: _BokehScene, f: int, cancelled=None, progress=None) -> _LargeBlur:
    """The PSFs of the blurred depths at f times the pitch, from the library's
    own source (``PSFLibrary.at_geometry``: a ray map's from the same ray
    map, else traced), with its
    settings; ``progress(done, total)`` called and ``cancelled()`` asked
    after each bin."""
    lib = sc.library
    blurred = sc.valid & ~sc.kept
    h, w = sc.depth.shape
    gc = mr.coarse_geometry(sc.geometry, f, -(-h // f), -(-w // f))
    settings = replace(lib.settings, pixel_pitch_mm=None, kernel_size=PSFSettings().kernel_size)
    def bins_done(done, total):
        if cancelled is not None and cancelled():
            raise Cancelled("bokeh cancelled")
        if progress is not None:
            progress(done, total)
    # the same source's PSFs at the coarse pitch: a ray map's from it, never traced
    coarse = lib.at_geometry(gc, settings, fit_depth_m=sc.depth[blurred], progress=bins_done)
    return _LargeBlur(f, coarse, gc)


def _blur_layer_coarse(sc: _BokehScene, mask: np.ndarray, large: _LargeBlur, support_eps: float = 1e-3):
    """The layer ``mask``'s premultiplied colour and coverage blurred at 1/f
    of the resolution with the coarse PSFs, on the layer's box grown by their
    reach and aligned to the coarse patches (float32 (h, w, 6), as
    ``_blur_layer``'s, and the box's rows and columns): the blocks without
    layer pixels take the layer's mean depth, so its blur reaches as far as
    its kernels do."""
    f, lib = large.f, large.library
    grid = COARSE_PATCH * f
    ys, xs = patch_box(mask, grid, grid * math.ceil((lib.kernel_size // 2 + COARSE_PATCH) / COARSE_PATCH))
    sub = mask[ys, xs]
    af = sub[..., None].astype(np.float32)
    layer = np.concatenate([sc.img[ys, xs] * af, af], axis=-1)
    inv = sc.inv[mask]
    mean = float(inv.mean()) if inv.size else 0.0
    fill = np.where(sub, sc.depth[ys, xs], (1.0 / mean) if mean > 0 else np.inf)
    # coarse_blur area-resamples kernels from the geometry's pitch to f times it: here the library is
    # already at f times the pitch, so it is given the coarse grid's geometry and f = 1 for the kernels
    h, w = sub.shape
    gc = mr.coarse_geometry(sc.geometry.crop(ys, xs), f, -(-h // f), -(-w // f))
    img = mr.block_mean(mr.pad_to(layer, f), f)
    dc = mr.coarse_depth(mr.pad_to(fill, f), mr.pad_to(np.ones_like(sub), f), lib.grid.far_m, f)
    pm = psf_map(lib, gc, dc, COARSE_PATCH, clamp_field=True, support_eps=support_eps)
    out = patch_convolve(img, pm.kernels, COARSE_PATCH, ConvolveOptions(support_eps=support_eps),
                         identity=pm.identity, pairs=LAYER_PAIRS)
    return mr.upsample(out, f, h, w, "cubic", averages=True), ys, xs


COARSE_PATCH = 16           # px of the coarse grid: a large blur's patches (as the fine path's 16)


def _layer_patch(sc: _BokehScene, options: BokehOptions, mask) -> layer_patch.PatchChoice:
    """The layer's patch size and blend (``layer_patch.choose``)."""
    return layer_patch.choose(sc.library, sc.geometry, sc.img, mask, sc.inv, options.patch, options.interp_eps)


def _blur_layer(sc: _BokehScene, options: BokehOptions, mask, ys: slice, xs: slice, table, choice=None):
    """The layer ``mask``'s premultiplied colour and coverage, blurred on its
    box (ys, xs) with the patches of ``choice`` (None: ``options.patch``
    and the tent): (float32 (h, w, 6): three colours, then the coverage
    blurred with each colour's PSF; the multires levels of its patches, or
    None)."""
    af = mask[ys, xs][..., None].astype(np.float32)
    # each colour's coverage blurred with that colour's own PSF: the
    # normalisation of the composite is then exact for any colour fringe
    layer = np.concatenate([sc.img[ys, xs] * af, af], axis=-1)
    # every patch of the box gets a kernel of the layer, also those holding
    # none of its pixels (that of the nearest ones: layer_depth): a gather
    # takes each output pixel's kernel from its own patch, so an identity
    # there would cut the blur spilling out of the layer's patches (a
    # bright light's halo ended after the tent)
    sub = sc.geometry.crop(ys, xs)
    m = options.patch
    conv = options.convolve_options()
    if choice is not None:
        m, conv = choice.m, replace(conv, blend=choice.b)
    d_layer = layer_patch.layer_depth(sc.depth[ys, xs], sc.inv[ys, xs], mask[ys, xs], m,
                                      layer_patch.fill_rings(sc.library.kernel_size, m, conv.blend_px(m)))
    if options.multires is None:
        # a patch whose window (the patch and its blend margin) lies beyond
        # the kernel's reach of every layer pixel gathers nothing whatever its
        # kernel: it gets none (NaN depth: the identity, copying zeros)
        reach = sc.library.kernel_size // 2 + conv.blend_px(m)
        d_layer[~_within_reach(mask[ys, xs], m, reach)] = np.nan
        pm = psf_map(sc.library, sub, d_layer, m, crop=True, support_eps=options.support_eps)
        blurred = patch_convolve(layer, pm.kernels, m, conv, identity=pm.identity, pairs=LAYER_PAIRS)
        return blurred, None
    every = np.ones(d_layer.shape, bool)                # every pixel has the layer's depth now
    no_copy = np.zeros((math.ceil(every.shape[0] / m), math.ceil(every.shape[1] / m)), bool)
    return mr.grouped_blur(layer, d_layer, every, no_copy, sc.library, sub, options.multires_options(),
                           pairs=LAYER_PAIRS, table=table)


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


COVER_EPS = 1e-6     # a layer's coverage below this is FFT round-off, not light
# what lies behind a layer counts as whole from this coverage on: 0.05 keeps `python -m lab bench-defocus`'s
# distances to the reference as they were (38.10 dB, each crop within 0.01 dB) while a 30 x light seen through
# a 3-px hole of a nearer layer no longer lights up a patch-shaped square of it (the catalogue's contact sheet)
OPAQUE_COVER = 0.05


def _composite(col: np.ndarray, acc: np.ndarray, ys: slice, xs: slice, blurred: np.ndarray) -> None:
    """A blurred layer (colour premultiplied, coverage) over the colour seen
    behind it on its box; ``col`` and its coverage ``acc`` updated in place.
    Only the rows and columns its coverage reaches change (below COVER_EPS
    nothing does), in blocks of rows on the thread pool."""
    reach = (blurred[..., 3:] >= COVER_EPS).any(axis=-1)
    rows, cols = np.flatnonzero(reach.any(axis=1)), np.flatnonzero(reach.any(axis=0))
    if not len(rows):
        return
    r0, r1, c0, c1 = int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1
    step = max(8, -(-(r1 - r0) // (4 * workers())))

    def block(r):
        sl = (slice(ys.start + r, ys.start + min(r1, r + step)), slice(xs.start + c0, xs.start + c1))
        _composite_block(col[sl], acc[sl], blurred[r:min(r1, r + step), c0:c1])
    list(thread_pool().map(block, range(r0, r1, step)))


def _composite_block(col: np.ndarray, acc: np.ndarray, blurred: np.ndarray) -> None:
    """``_composite`` on views of one block (col, acc written in place)."""
    # the FFT leaves ~1e-8 of coverage (and colour) where the layer's blur is
    # zero: below COVER_EPS it is zero, so what lies behind stays bit-exact there
    tiny = blurred[..., 3:] < COVER_EPS
    cover = np.clip(blurred[..., 3:], 0.0, 1.0)
    cover[tiny] = 0.0
    front = blurred[..., :3].copy()
    front[tiny] = 0.0
    # premultiplied: the layer, and what lies behind it; behind, a coverage of
    # OPAQUE_COVER or more counts as whole (the colour spread from around a
    # hidden part fills it), a fainter one in proportion (a light's faint blur
    # seen through a hole stays faint)
    behind = np.minimum(acc * np.float32(1.0 / OPAQUE_COVER), np.float32(1.0)) * (1.0 - cover)
    front += col * behind
    total = cover + behind
    ok = total > 1e-4
    acc[...] = np.where(ok, cover + acc * (1.0 - cover), np.float32(0.0))
    np.divide(front, np.maximum(total, np.float32(1e-4)), out=front)
    front[~ok] = 0.0
    col[...] = front
