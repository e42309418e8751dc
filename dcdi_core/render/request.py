"""A simulation or bokeh job described in plain values, checked before any work.

The `dcdi` command and the Blender add-on ask for a render the same way: a
lens, PSF settings, the image's pixel pitch, an over-scan frame around the
sensor, the optical axis, the patch size, the warp's interpolation, sensor
noise, a perturbation, a fixed depth. :class:`RenderRequest` refuses a bad
value when it is made (before an image is read), and
:meth:`RenderRequest.plan` adds what needs the image's size (the sensor's and
the source image's geometry, the memory the PSFs will take) before a PSF is
traced.

Units: lengths on the sensor in mm, depths in metres, wavelengths in nm,
positions and sizes in image pixels (row, col; pixel centres at integers).

Names in messages: each error names a setting by its field
(``errors.field``), shown in each front end's words (the `dcdi` command's
options, the add-on's panel labels); ``labels`` ({field: label}) may still
override a name.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

from ..errors import InputRangeError
from ..errors import field as field_ref
from ..psf.compute import PSFSettings, check_pixel_pitch, check_psf_memory
from ..psf.library import LibraryGrid
from .distortion import check_interpolation
from .geometry import ImageGeometry
from .noise import check_noise
from .base import DEFAULT_INTERPOLATION, check_patch, check_within_sensor
from ..psf.library import MAX_FITTED_KERNEL

def check_library_memory(settings: PSFSettings, grid: LibraryGrid | None = None, *, map_kernels: int = 0) -> None:
    """Refuse, before any work, a PSF library of ``grid`` (default: the
    default grid) with ``settings`` that would not fit in memory, with a PSF
    map of ``map_kernels`` patch kernels besides."""
    g = grid or LibraryGrid()
    n = g.n_fields * (g.n_depths + 1)
    check_psf_memory(settings, n, 1 if settings.wavelength_nm is not None else None, library_psfs=n,
                     map_kernels=map_kernels)


@dataclass(frozen=True)
class RenderPlan:
    """What a checked request resolves to for an image of a given size."""

    settings: PSFSettings                  # the PSFs' settings (their pitch is the geometry's)
    geometry: ImageGeometry                # the sensor's frame: the output's pixels
    source_geometry: ImageGeometry | None  # the input image when it is larger (over-scan), else None


@dataclass(frozen=True)
class RenderRequest:
    """A simulation or bokeh job, checked when made (InputRangeError naming
    the setting by its label).

    ``psf``: the PSF settings; a ``pixel_pitch_mm`` set there is taken as
    ``image_pixel_pitch_mm`` (the PSFs of an image are sampled at its own
    pitch: the request holds it in that one field, its ``psf`` without
    one), ``focus_distance_m`` moves the sensor (a simulation; a bokeh's
    focus is its own argument), ``wavelength_nm`` asks for one wavelength in
    all three channels. ``fit_kernel``: the kernel grows to hold the depth
    map's blur, up to ``psf.library.MAX_FITTED_KERNEL`` px (else
    ``psf.kernel_size`` is kept).

    ``image_pixel_pitch_mm``: one image pixel on the sensor (mm; default: the
    image, or the ``sensor_size`` frame, spans the sensor's diagonal); given
    or resolved, it must let the largest kernel of the run span the lens's
    diffraction-limited spot and be at most the sensor's diagonal
    (:meth:`check_pitch`).
    ``sensor_size``: (rows, cols) of the sensor's frame, centred on the axis,
    inside a larger (over-scan) image; the output has this size.
    ``axis_px``: (row, col) of the optical axis in the image (default its
    centre). ``noise``: add shot and read noise (needs ``seed``).
    ``perturb_fraction``: checked when ``perturb_seed`` is set.
    ``fixed_depth_m``: one depth for the whole image (depth-unaware).
    ``pinhole_focal_length_mm``: the focal length of the pinhole camera that
    rendered the image, on the scale of the image's frame on the sensor (mm;
    None: the lens's own, ``camera.ideal_scale_mm``: the image is the lens's
    ideal image). A camera framed as the lens is at a close focus
    (``camera.PinholeCamera.for_lens(..., focus_m=...)``) has a longer one;
    the image is then read as the ideal image at that scale.
    """

    lens: object
    psf: PSFSettings = field(default_factory=PSFSettings)
    fit_kernel: bool = True
    image_pixel_pitch_mm: float | None = None
    sensor_size: tuple[int, int] | None = None
    axis_px: tuple[float, float] | None = None
    patch: int = 16
    interpolation: str | None = None       # None: render.simulate.DEFAULT_INTERPOLATION
    noise: bool = False
    full_well_electrons: float = 10000.0
    read_noise_electrons: float = 3.0
    seed: int | None = None
    perturb_seed: int | None = None
    perturb_fraction: float = 0.10
    fixed_depth_m: float | None = None
    pinhole_focal_length_mm: float | None = None
    labels: dict = field(default_factory=dict)

    def __post_init__(self):
        self._one_pitch()
        try:
            check_patch(self.patch)
        except InputRangeError as e:
            raise InputRangeError(self._label("patch"), e.value, e.allowed) from None
        if self.interpolation is None:
            object.__setattr__(self, "interpolation", DEFAULT_INTERPOLATION)
        try:
            check_interpolation(self.interpolation)
        except InputRangeError as e:
            raise InputRangeError(self._label("interpolation"), e.value, e.allowed) from None
        if self.noise:
            if self.seed is None:
                raise InputRangeError(self._label("seed"), None,
                                      f"an integer: {self._label('noise')} needs an explicit seed")
            check_noise(self.full_well_electrons, self.read_noise_electrons)
        if self.perturb_seed is not None and not 0.0 <= self.perturb_fraction <= 0.5:
            raise InputRangeError(self._label("perturb_fraction"), self.perturb_fraction,
                                  "a number in [0, 0.5] (0.1 = +-10 %)")
        if self.fixed_depth_m is not None:
            near = LibraryGrid().near_m
            if not self.fixed_depth_m >= near:
                raise InputRangeError(self._label("fixed_depth_m"), self.fixed_depth_m,
                                      f">= {near:g} m, the PSF library's nearest depth bin (or inf)")
        f = self.pinhole_focal_length_mm
        if f is not None and (isinstance(f, bool) or not isinstance(f, (int, float)) or not math.isfinite(f)
                              or not 0.0 < f <= 1e6):
            raise InputRangeError(self._label("pinhole_focal_length_mm"), f,
                                  "a focal length in (0, 1e6] mm on the sensor's scale, or none (the lens's own)")
        if self.psf.wavelength_nm is not None:
            self.lens.check_wavelengths(self.psf.wavelength_nm, self._label("wavelength_nm"))
        if self.image_pitch_mm is not None:      # the pitch options checked now, before an image is read
            self.check_pitch(self.image_pitch_mm)

    def _label(self, name: str) -> str:
        return self.labels.get(name) or field_ref(name)

    def _one_pitch(self) -> None:
        """The pitch in one field: a PSF settings' pitch moves to
        ``image_pixel_pitch_mm`` (refused where both are given and differ)."""
        a, b = self.image_pixel_pitch_mm, self.psf.pixel_pitch_mm
        if b is None:
            return
        if a is not None and a != b:
            raise InputRangeError(self._label("pixel_pitch_mm"), b,
                                  f"{self._label('image_pixel_pitch_mm')}'s {a} mm, or leave one out (the PSFs "
                                  "of an image are sampled at its own pitch)")
        object.__setattr__(self, "image_pixel_pitch_mm", b)
        object.__setattr__(self, "psf", replace(self.psf, pixel_pitch_mm=None))
        if a is None:                # errors name what was given
            object.__setattr__(self, "labels", {"image_pixel_pitch_mm": self._label("pixel_pitch_mm"),
                                                **self.labels})

    # ------------------------------------------------------------ resolved
    @property
    def image_pitch_mm(self) -> float | None:
        """One image pixel on the sensor (mm), or None (the default: the
        image spans the sensor's diagonal)."""
        pitch = self.image_pixel_pitch_mm
        if pitch is not None and not (pitch > 0 and math.isfinite(pitch)):
            raise InputRangeError(self._pitch_label(), pitch, "a pixel pitch > 0 mm")
        return pitch

    def _pitch_label(self) -> str:
        return self._label("image_pixel_pitch_mm")

    @property
    def largest_kernel(self) -> int:
        """The largest kernel (px) the run may use: the fitted kernel's limit
        (``psf.library.MAX_FITTED_KERNEL``) or, without fitting, the
        settings' own."""
        k = self.psf.kernel_size
        return max(k, MAX_FITTED_KERNEL) if self.fit_kernel else k

    def check_pitch(self, pitch_mm: float, label: str | None = None) -> None:
        """Refuse, before any tracing, an image pitch (mm) at which no kernel
        of the run can hold the light, or larger than the sensor
        (``psf.compute.check_pixel_pitch`` with :attr:`largest_kernel`):
        below it every PSF would clip nearly all of its energy, and the
        ray positions in pixels would overflow."""
        check_pixel_pitch(self.lens, self.psf, pitch_mm, kernel_size=self.largest_kernel,
                          name=label or self._pitch_label())

    @property
    def settings(self) -> PSFSettings:
        """The PSF settings the render uses (no pitch: the geometry's)."""
        return self.psf

    @property
    def noise_settings(self) -> dict | None:
        """The noise keywords of the simulation (full well, read noise), or None."""
        if not self.noise:
            return None
        return {"full_well_electrons": self.full_well_electrons, "read_noise_electrons": self.read_noise_electrons}

    # ------------------------------------------------------------ with the image's size
    def geometries(self, height: int, width: int, image: str = "the image"):
        """(sensor geometry, source geometry or None) of an image of
        ``height`` x ``width`` pixels; ``image`` names it in messages. A
        pinhole focal length other than the lens's own scales the source's
        pitch (its pixels seen at the lens's ideal scale)."""
        sensor, source = self._frames(height, width, image)
        f = self.pinhole_focal_length_mm
        if f is not None:
            from .camera import ideal_scale_mm
            scale = ideal_scale_mm(self.lens) / float(f)
            if abs(scale - 1.0) > 1e-12:
                src = source or sensor
                source = replace(src, pixel_pitch_mm=src.pixel_pitch_mm * scale)
        return sensor, source

    def _frames(self, height: int, width: int, image: str):
        lens, h, w = self.lens, height, width
        pitch = self.image_pitch_mm
        axis = tuple(self.axis_px) if self.axis_px is not None else None
        if axis is not None and not (-0.5 <= axis[0] <= h - 0.5 and -0.5 <= axis[1] <= w - 0.5):
            raise InputRangeError(self._label("axis_px"), axis,
                                  f"a pixel position (row, col) inside the {h} x {w} image")
        if self.sensor_size is None:
            if pitch is None:
                if axis is not None:
                    raise InputRangeError(self._label("axis_px"), axis,
                                          f"only with {self._label('image_pixel_pitch_mm')} or "
                                          f"{self._label('sensor_size')} (without them the image spans the "
                                          "sensor's diagonal about its centre)")
                return ImageGeometry.full_sensor(lens, h, w), None
            geom = ImageGeometry.from_pixel_pitch(lens, h, w, pitch, center_px=axis)
            check_within_sensor(geom, image)
            return geom, None
        rows, cols = self.sensor_size
        if not (rows >= 1 and cols >= 1) or rows > h or cols > w:
            raise InputRangeError(self._label("sensor_size"), (rows, cols),
                                  f"at least 1 and at most the image's {h} x {w} pixels (the sensor's frame "
                                  f"inside an over-scan render of {image})")
        if pitch is None:        # the sensor's frame spans the lens's sensor diagonal
            pitch = ImageGeometry.full_sensor(lens, rows, cols).pixel_pitch_mm
        sensor = ImageGeometry.from_pixel_pitch(lens, rows, cols, pitch)
        check_within_sensor(sensor, self._label("sensor_size"))
        source = ImageGeometry.from_pixel_pitch(lens, h, w, pitch, center_px=axis)
        return sensor, source

    def check_memory(self, geometry: ImageGeometry) -> None:
        """Refuse PSFs (the library and the PSF map of ``geometry``) that
        would not fit in memory, with the largest kernel the run may use."""
        biggest = replace(self.settings, kernel_size=MAX_FITTED_KERNEL) if self.fit_kernel else self.settings
        patches = -(-geometry.height // self.patch) * -(-geometry.width // self.patch)
        check_library_memory(biggest, map_kernels=patches)

    def plan(self, height: int, width: int, image: str = "the image") -> RenderPlan:
        """Settings and geometries for an image of ``height`` x ``width``
        pixels, the memory checked: all that can be refused before a PSF is
        traced."""
        geometry, source = self.geometries(height, width, image)
        if self.image_pitch_mm is None:          # the pitch the image's size gives: checked as a given one
            self.check_pitch(geometry.pixel_pitch_mm, f"pixel pitch of {image} (from its size)")
        self.check_memory(geometry)
        return RenderPlan(self.settings, geometry, source)
