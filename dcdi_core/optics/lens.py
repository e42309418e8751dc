"""The lens model: a validated sequential prescription plus its sensor.

Loaded from the TOML files in ``lenses/`` (schema: ``lenses/SCHEMA.md``).
Every violation of the schema raises :class:`LensFileError` naming the file,
the surface (1-based), the field and the allowed values.
"""
from __future__ import annotations

import hashlib
import math
import os
import re
import stat
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InputRangeError
from ..names import MAX_NAME_CHARS, NAME_RULE, name_problem, printable, shown

from .errors import LensFileError, OpticsError, UnknownGlassError
from .materials import AIR, get_material
from .surfaces import Surface

D_LINE_NM = 587.5618

_TOP_KEYS = {"schema_version", "id", "name", "maker", "source", "notes", "wavelength_nm",
             "sensor", "stated", "surface"}
_SENSOR_KEYS = {"semi_diagonal_mm", "resolution_px", "pixel_pitch_mm"}
_STATED_KEYS = {"effective_focal_length_mm", "f_number", "field_of_view_deg",
                "field_of_view_note", "image_semi_diameter_mm", "back_focal_length_mm",
                "sensor_semi_diagonal_mm", "sensor_note", "pixel_pitch_mm", "resolution_px"}
_SURFACE_KEYS = {"label", "radius_mm", "thickness_mm", "material", "semi_diameter_mm",
                 "conic", "aspheric_coefficients", "odd_aspheric_coefficients", "stop"}
_ID_RE = re.compile(r"^[a-z0-9][a-z0-9-]*$")

# Limits checked before a lens is built, so a hostile file cannot run for
# minutes: real prescriptions have 3-30 surfaces (the shipped ones 3-13, patent
# zoom lenses about 30), so 200 is far above any; a TOML file of 200 surfaces is
# about 40 kB, so 1 MiB holds any of them with long notes (a Zemax file, UTF-16
# with tolerance data, is 20-200 kB: the same limit serves both); 32 aspheric
# coefficients per surface (Zemax's even asphere has 8, its odd asphere 16, a
# shipped one at most 5).
MAX_SURFACES = 200
MAX_LENS_FILE_BYTES = 1 << 20
MAX_ASPHERIC_TERMS = 32
# the longest length a lens file may give (a thickness, a semi-diameter, the sensor's semi-diagonal, a surface's
# sag over its clear aperture): a kilometre, far beyond any lens; a finite 1e300 would overflow the trace's
# squares into inf and NaN, found as a traceback or a map of NaN far from the file
MAX_LENGTH_MM = 1e6
# a conic constant beyond this is no surface a lens holds (its sag is the same numbers' overflow)
MAX_CONIC = 1e6


def lens_dirs() -> list[Path]:
    """Folders searched for lens ids: $DCDI_LENS_PATH (os.pathsep-separated),
    then the repository's ``lenses/`` (also bundled beside ``dcdi_core`` in
    the Blender add-on)."""
    dirs = [Path(p) for p in os.environ.get("DCDI_LENS_PATH", "").split(os.pathsep) if p]
    here = Path(__file__).resolve().parent.parent
    dirs += [here.parent / "lenses", here / "lenses"]
    return [d for d in dirs if d.is_dir()]


def available_lenses() -> list[str]:
    """Ids of the lenses found in :func:`lens_dirs`."""
    ids = []
    for d in lens_dirs():
        ids += [p.stem for p in sorted(d.glob("*.toml")) if p.stem not in ids]
    return ids


@dataclass(frozen=True)
class Sensor:
    """Image sensor: field 1.0 is ``semi_diagonal_mm`` from the axis."""

    semi_diagonal_mm: float
    resolution_px: tuple[int, int] | None = None   # (rows, columns)
    pixel_pitch_mm: float | None = None


@dataclass(frozen=True)
class Lens:
    """A rotationally symmetric sequential lens (lengths in mm).

    ``vertex_z_mm[i]`` is the axial position of surface i's vertex (the first
    vertex at 0); ``sensor_z_mm`` the sensor plane. Depths (object distances)
    are measured from the first vertex, in metres, as docs/design.md states.
    """

    id: str
    name: str
    surfaces: tuple[Surface, ...]
    sensor: Sensor
    stated: dict = field(default_factory=dict)
    source: str = ""
    notes: str = ""
    wavelength_nm: float = D_LINE_NM
    path: str = "<dict>"
    content_hash: str = ""
    iris: str = ""          # stopped down from the prescription ('f/8, 6 blades': optics.aperture), or ""

    @property
    def vertex_z_mm(self) -> np.ndarray:
        t = np.array([0.0] + [s.thickness_mm for s in self.surfaces[:-1]])
        return np.cumsum(t)

    @property
    def sensor_z_mm(self) -> float:
        return float(sum(s.thickness_mm for s in self.surfaces))

    @property
    def stop_index(self) -> int:
        return next(i for i, s in enumerate(self.surfaces) if s.stop)

    @property
    def total_track_mm(self) -> float:
        """First vertex to sensor, mm."""
        return self.sensor_z_mm

    @property
    def wavelength_range_nm(self) -> tuple[float, float]:
        """Wavelengths (nm) where the data of every glass of the lens are
        valid: the intersection of the glasses' own validity ranges."""
        lo, hi = 0.0, math.inf
        for s in self.surfaces:
            a, b = s.material.wavelength_range_nm
            lo, hi = max(lo, float(a)), min(hi, float(b))
        return lo, hi

    def check_wavelengths(self, wavelength_nm, what: str = "wavelength_nm") -> np.ndarray:
        """Refuse wavelengths where a glass of the lens has no valid data (the
        one rule of every command: each glass's own validity range); returns
        them as a float64 array. ``what`` names the option or argument."""
        wl = np.asarray(wavelength_nm, dtype=np.float64)
        lo, hi = self.wavelength_range_nm
        bad = ~((wl >= lo) & (wl <= hi))
        if bad.any():
            v = float(wl[bad].flat[0]) if wl.ndim else float(wl)
            edge = 0 if not v > lo else 1          # the limit crossed: lower (or NaN) or upper
            limits = sorted({(s.material.name, *s.material.wavelength_range_nm) for s in self.surfaces
                             if s.material.wavelength_range_nm[edge] == (lo, hi)[edge]})
            why = ", ".join(f"{name}'s data are valid for {a:g}-{b:g} nm" for name, a, b in limits)
            raise InputRangeError(what, v if math.isfinite(v) else str(v),
                                  f"{lo:g}-{hi:g} nm for lens {self.id} ({why or 'finite wavelengths'})")
        return wl

    def refractive_indices(self, wavelength_nm) -> np.ndarray:
        """Indices (n_surfaces + 1, *wavelength shape): object space first,
        then the medium after each surface. Wavelengths outside
        :attr:`wavelength_range_nm` are refused (InputRangeError)."""
        wl = self.check_wavelengths(wavelength_nm)
        cache: dict[int, np.ndarray] = {}
        rows = [AIR.refractive_index(wl) * np.ones_like(wl)]
        for s in self.surfaces:
            key = id(s.material)
            if key not in cache:
                cache[key] = np.asarray(s.material.refractive_index(wl), dtype=np.float64) * np.ones_like(wl)
            rows.append(cache[key])
        return np.stack(rows)

    def with_surfaces(self, surfaces) -> "Lens":
        """A copy with other surfaces (used by perturbation and refocusing)."""
        return Lens(self.id, self.name, tuple(surfaces), self.sensor, self.stated, self.source,
                    self.notes, self.wavelength_nm, self.path, "", self.iris)

    # ------------------------------------------------------------------ loading
    @classmethod
    def from_dict(cls, d: dict, path: str | os.PathLike = "<dict>", content_hash: str = "") -> "Lens":
        """Validate a prescription dict (the TOML layout) and build the lens."""
        path = str(path)

        def err(msg, **kw):
            return LensFileError(path, msg, **kw)

        if not isinstance(d, dict):
            raise err("a prescription must be a table")
        unknown = set(d) - _TOP_KEYS
        if unknown:
            raise err("unknown top-level key", field=sorted(unknown)[0], allowed=sorted(_TOP_KEYS))
        if d.get("schema_version") != 1:
            raise err("unsupported schema version", field="schema_version",
                      value=d.get("schema_version"), allowed="1")
        lens_id = d.get("id")
        if not isinstance(lens_id, str) or not _ID_RE.match(lens_id) or len(lens_id) > MAX_NAME_CHARS:
            # the id names files (PSF caches, shipped bases and weights): a name, never a path
            raise err(f"id must be 1-{MAX_NAME_CHARS} lower-case letters, digits and '-', not starting with '-'",
                      field="id", value=lens_id if not isinstance(lens_id, str) else lens_id[:80])
        wl = _number(d.get("wavelength_nm", D_LINE_NM), err, "wavelength_nm", None, lo=200.0, hi=2500.0)

        sensor = _sensor(d.get("sensor"), err)
        stated = d.get("stated", {})
        if not isinstance(stated, dict):
            raise err("must be a table", field="stated")
        bad = set(stated) - _STATED_KEYS
        if bad:
            raise err("unknown key in [stated]", field=sorted(bad)[0], allowed=sorted(_STATED_KEYS))

        raw = d.get("surface")
        if not isinstance(raw, list) or not raw:
            raise err("at least one [[surface]] is needed", field="surface")
        if len(raw) > MAX_SURFACES:
            raise err(f"{len(raw)} surfaces, over the limit", field="surface", allowed=f"at most {MAX_SURFACES}")
        materials: dict = {}
        surfaces = [_surface(i + 1, s, err, materials) for i, s in enumerate(raw)]
        stops = [i for i, s in enumerate(surfaces) if s.stop]
        if len(stops) != 1:
            raise err("exactly one surface must have stop = true",
                      field="stop", value=[i + 1 for i in stops])
        # a name and a source are shown on one line wherever the lens is named: their controls escaped
        lens = cls(id=lens_id, name=printable(d.get("name", lens_id)), surfaces=tuple(surfaces),
                   sensor=sensor, stated=dict(stated), source=printable(d.get("source", "")),
                   notes=str(d.get("notes", "")), wavelength_nm=wl, path=path,
                   content_hash=content_hash)
        _check_no_crossing(lens.surfaces, err)
        lo, hi = lens.wavelength_range_nm
        if not lo <= wl <= hi:
            raise err("the design wavelength lies outside the glass data's validity", field="wavelength_nm",
                      value=wl, allowed=f"[{lo:g}, {hi:g}] nm")
        return lens

    @classmethod
    def from_toml(cls, path: str | os.PathLike) -> "Lens":
        path = Path(path)
        data = read_lens_file(path, LensFileError)
        try:
            d = tomllib.loads(data.decode("utf-8"))
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
            raise LensFileError(path, f"not valid TOML: {e}") from None
        return cls.from_dict(d, path, hashlib.sha256(data).hexdigest())


def read_lens_file(path: Path, error) -> bytes:
    """The bytes of a lens file (TOML or Zemax), refused before reading when
    over :data:`MAX_LENS_FILE_BYTES`. ``error(path, message)``: the reader's
    error class (LensFileError, or a ZemaxImportError maker)."""
    try:
        st = os.stat(path)
        if not stat.S_ISREG(st.st_mode):         # a FIFO would block the read for ever
            raise error(path, "not a regular file (a folder, a pipe or a device); give a lens file")
        size = st.st_size
        if size <= MAX_LENS_FILE_BYTES:
            with open(path, "rb") as f:
                data = f.read(MAX_LENS_FILE_BYTES + 1)      # at most: the file may grow after the stat
            size = len(data)
    except OSError as e:
        raise error(path, f"cannot read the file: {e.strerror or e}") from None
    if size > MAX_LENS_FILE_BYTES:
        raise error(path, f"{size} bytes, over the limit of {MAX_LENS_FILE_BYTES} bytes for a lens file "
                          "(a real prescription is a few kB)")
    return data


# a gap below this (mm) is two surfaces through each other, not a touch at the edge
CROSSING_TOLERANCE_MM = 1e-6


def _check_no_crossing(surfaces, err) -> None:
    """Refuse a prescription whose neighbouring surfaces (or the last one and
    the sensor) cross inside their common clear aperture: the axial gap
    t_i + sag_{i+1}(r) - sag_i(r) must stay >= 0 for r up to the smaller
    semi-diameter (a lens's edge thickness, an air gap's clearance)."""
    for i, s in enumerate(surfaces):
        nxt = surfaces[i + 1] if i + 1 < len(surfaces) else None
        r = s.semi_diameter_mm if nxt is None else min(s.semi_diameter_mm, nxt.semi_diameter_mm)
        r2 = np.linspace(0.0, r * r, 129)
        gap = s.thickness_mm + (0.0 if nxt is None else nxt.sag(r2)) - s.sag(r2)
        j = int(np.argmin(gap))
        if gap[j] < -CROSSING_TOLERANCE_MM:
            what = "the sensor" if nxt is None else f"surface {i + 2}"
            raise err(f"surface {i + 1} and {what} cross: {gap[j]:.4g} mm apart at {math.sqrt(r2[j]):.4g} mm from "
                      f"the axis ({s.thickness_mm:g} mm on it; an edge thickness must be >= 0)", surface=i + 1,
                      field="thickness_mm", value=s.thickness_mm,
                      allowed=f">= {s.thickness_mm - gap[j]:.4g} mm, or smaller semi-diameters")


def load_lens(name_or_path: str | os.PathLike) -> Lens:
    """A lens by id (searched in :func:`lens_dirs`) or by path to a TOML file."""
    p = Path(name_or_path)
    if p.suffix == ".toml" or p.exists():
        return Lens.from_toml(p)
    # an id (perhaps read from a record or a model file) becomes a file name in the lens folders: a name only
    why = name_problem(str(name_or_path))
    if why:
        raise OpticsError(f"no lens {shown(str(name_or_path))}: not a file, and not a lens id (it is {why}; "
                          f"a lens id is {NAME_RULE})")
    for d in lens_dirs():
        cand = d / f"{name_or_path}.toml"
        if cand.exists():
            return Lens.from_toml(cand)
    raise OpticsError(f"no lens {str(name_or_path)!r}: not a file, and not an id in "
                      f"{[str(d) for d in lens_dirs()]} (known ids: {', '.join(available_lenses())})")


# ---------------------------------------------------------------- validation
def _number(v, err, name, surface, lo=None, hi=None, lo_open=False, allow_inf=False):
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise err("must be a number", surface=surface, field=name, value=v)
    v = float(v)
    if math.isnan(v) or (math.isinf(v) and not allow_inf):
        raise err("must be finite", surface=surface, field=name, value=v)
    if hi is None:
        rng = None if lo is None else f"{'>' if lo_open else '>='} {lo:g}"
    elif lo is None:
        rng = f"<= {hi:g}"
    else:
        rng = f"{'(' if lo_open else '['}{lo:g}, {hi:g}]"
    if lo is not None and (v < lo or (lo_open and v == lo)):
        raise err("out of range", surface=surface, field=name, value=v, allowed=rng)
    if hi is not None and v > hi:
        raise err("out of range", surface=surface, field=name, value=v, allowed=rng)
    return v


def _sensor(s, err) -> Sensor:
    if not isinstance(s, dict):
        raise err("a [sensor] table with semi_diagonal_mm is needed", field="sensor")
    bad = set(s) - _SENSOR_KEYS
    if bad:
        raise err("unknown key in [sensor]", field=sorted(bad)[0], allowed=sorted(_SENSOR_KEYS))
    sd = _number(s.get("semi_diagonal_mm"), err, "sensor.semi_diagonal_mm", None, lo=0.0, lo_open=True,
                 hi=MAX_LENGTH_MM)
    res = s.get("resolution_px")
    if res is not None:
        if (not isinstance(res, list) or len(res) != 2
                or not all(isinstance(r, int) and not isinstance(r, bool) and r > 0 for r in res)):
            raise err("must be [rows, columns], positive integers", field="sensor.resolution_px", value=res)
        res = (int(res[0]), int(res[1]))
    pitch = s.get("pixel_pitch_mm")
    if pitch is not None:
        pitch = _number(pitch, err, "sensor.pixel_pitch_mm", None, lo=0.0, lo_open=True)
    if pitch is not None and res is not None:
        implied = 0.5 * pitch * math.hypot(*res)
        if abs(implied - sd) > 0.01 * sd:
            raise err("semi_diagonal_mm disagrees with pixel_pitch_mm x resolution_px by more than 1 %",
                      field="sensor.semi_diagonal_mm", value=sd, allowed=f"{implied:.4f} +- 1 %")
    return Sensor(sd, res, pitch)


def _coefficients(s, key, err, num) -> tuple[float, ...]:
    """A surface's list of aspheric coefficients ``key``, trailing zeros dropped."""
    values = s.get(key, [])
    if not isinstance(values, list) or len(values) > MAX_ASPHERIC_TERMS:
        raise err("must be a list of numbers", surface=num, field=key,
                  value=values if not isinstance(values, list) else f"a list of {len(values)}",
                  allowed=f"at most {MAX_ASPHERIC_TERMS} numbers")
    values = tuple(_number(a, err, key, num) for a in values)
    while values and values[-1] == 0.0:
        values = values[:-1]
    return values


def _surface(num, s, err, materials) -> Surface:
    if not isinstance(s, dict):
        raise err("a surface must be a table", surface=num)
    bad = set(s) - _SURFACE_KEYS
    if bad:
        raise err("unknown key", surface=num, field=sorted(bad)[0], allowed=sorted(_SURFACE_KEYS))
    for key in ("radius_mm", "thickness_mm", "semi_diameter_mm"):
        if key not in s:
            raise err("missing", surface=num, field=key)
    radius = _number(s["radius_mm"], err, "radius_mm", num, allow_inf=True)
    thickness = _number(s["thickness_mm"], err, "thickness_mm", num, lo=0.0, hi=MAX_LENGTH_MM)
    sd = _number(s["semi_diameter_mm"], err, "semi_diameter_mm", num, lo=0.0, lo_open=True, hi=MAX_LENGTH_MM)
    conic = _number(s.get("conic", 0.0), err, "conic", num, lo=-MAX_CONIC, hi=MAX_CONIC)
    coeffs = _coefficients(s, "aspheric_coefficients", err, num)
    odd = _coefficients(s, "odd_aspheric_coefficients", err, num)
    if coeffs and odd:
        raise err("an even or an odd asphere, not both", surface=num, field="odd_aspheric_coefficients")
    stop = s.get("stop", False)
    if not isinstance(stop, bool):
        raise err("must be true or false", surface=num, field="stop", value=stop)
    spec = s.get("material", "air")
    key = repr(sorted(spec.items())) if isinstance(spec, dict) else str(spec).lower()
    if key not in materials:
        try:
            materials[key] = get_material(spec)
        except UnknownGlassError as e:
            raise err(str(e), surface=num, field="material") from None
        except (ValueError, TypeError) as e:
            raise err(str(e), surface=num, field="material", value=spec) from None
    c = 0.0 if (radius == 0 or math.isinf(radius)) else 1.0 / radius
    if c != 0.0 and not coeffs and not odd and (1.0 + conic) * c * c * sd * sd > 1.0:
        raise err("semi-diameter exceeds the surface's sag domain (the sphere/conic closes before it)",
                  surface=num, field="semi_diameter_mm", value=sd,
                  allowed=f"<= {1.0 / math.sqrt(max((1.0 + conic) * c * c, 1e-300)):.6g}")
    surface = Surface(radius_mm=radius, thickness_mm=thickness, material=materials[key],
                      semi_diameter_mm=sd, conic=conic, aspheric_coefficients=coeffs, stop=stop,
                      label=str(s.get("label", "")), odd_aspheric_coefficients=odd)
    if coeffs or odd:           # each term's sag at the clear aperture bounded, as the lengths are
        with np.errstate(over="ignore", invalid="ignore"):
            sag = surface.max_abs_sag()
        if not math.isfinite(sag) or sag > MAX_LENGTH_MM:
            raise err("the aspheric terms' sag over the clear aperture is out of range", surface=num,
                      field="odd_aspheric_coefficients" if odd else "aspheric_coefficients",
                      value=f"{sag:.3g} mm", allowed=f"|sag| <= {MAX_LENGTH_MM:g} mm")
    return surface


def lens_fingerprint(lens: "Lens") -> str:
    """sha256 of everything optical about the lens (surfaces, glass indices at
    three wavelengths, sensor): two lenses with the same fingerprint image alike."""
    wl = np.array([450.0, 550.0, 650.0])
    n = lens.refractive_indices(wl)
    # an odd asphere's terms only where there are any: the fingerprints (and caches) of all other lenses unchanged
    parts = [repr([(s.radius_mm, s.thickness_mm, s.semi_diameter_mm, s.conic, s.aspheric_coefficients, s.stop)
                   + ((s.odd_aspheric_coefficients,) if s.odd_aspheric_coefficients else ())
                   + ((s.blades, s.blade_rotation_deg) if s.blades else ())     # likewise a bladed iris
                   for s in lens.surfaces]),
             np.round(n, 12).tobytes().hex(), repr(lens.sensor), repr(lens.wavelength_nm)]
    return hashlib.sha256("|".join(parts).encode()).hexdigest()
