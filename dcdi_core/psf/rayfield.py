"""The Omni-Lens-Field in ray space: a lens's ray map as smooth functions
of the source (numpy only).

A ray map (``psf.raymap``) holds, at a grid of fields x depths, the
polynomials of the stop that say where a source's rays land on two sensor
planes (at the design wavelength, and each stored wavelength's difference),
where they meet each surface that clips the beam, its chief ray and its
illumination; between grid points they are interpolated. This store holds
each of those values as one tensor Legendre polynomial of (field, 1/depth):
a source's values come from its own (field, depth), no grid between.

Every landing polynomial is held in an orthonormal basis of the stop
(:class:`StopBasis`: the monomials' QR on the map's fit grid), in which a
coefficient's error is the RMS of the landing points' error over the pupil,
in mm. ``python -m lab olf-rays`` fits it to a map (least squares weighed on
the rays that pass each source), scores it against traces and writes the
file (docs/olf.md).

It serves as a ray map does (:class:`RayFieldMap` is a ``RayMap``): any
focus, f-number, blades, pixel pitch, rays and wavelengths within its band,
the PSFs deposited alike (``RayMapLibrary``). The reachable disc, the usable
sources and the axial illumination stay the map's small tables. One file
(:class:`RayFieldOLF`) holds any number of lenses.
"""
from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

from ..io.model_npz import check_header, model_fail, read_npz_with_meta
from ..io.npzfile import FileCache, Record, check_array, write_format
from .raymap import MAX_COEFFICIENT_MM, RayMap, check_bounded, check_map_meta, check_tables, grid_weights, \
    monomial_set, n_terms

FORMAT = "dcdi-ray-field"
FORMAT_VERSION = 1
# fields a depth's values are evaluated at (the map's 4-point Lagrange between them)
SERVE_FIELDS = 65
MAX_DEGREE = 32
MAX_LENSES = 64
# a whitening matrix's entries (the monomials' inverse triangle): bounded, the served values stay finite
MAX_WHITENING = 1e8
# the map's small tables the store keeps as they are
TABLES = ("aim", "ok", "reference_geometry")
# what a file's meta says of a lens beside its map's record
ENTRY_KEYS = ("lens_id", "map", "degrees", "max_diopters", "serve_fields", "geometry_scale", "held_out")


def legendre_terms(fields, diopters, max_diopters: float, degrees) -> np.ndarray:
    """(S, (df + 1)(dd + 1)) tensor Legendre polynomials of field (0-1) and
    1/depth (0 to ``max_diopters``, 1/m), each taken to [-1, 1]."""
    from numpy.polynomial import legendre
    a = legendre.legvander(2.0 * np.asarray(fields, np.float64) - 1.0, int(degrees[0]))
    b = legendre.legvander(2.0 * np.asarray(diopters, np.float64) / max_diopters - 1.0, int(degrees[1]))
    return (a[:, :, None] * b[:, None, :]).reshape(len(a), -1)


class StopBasis:
    """A map's values at S sources as one vector each (S, D), in mm: every
    polynomial of the stop in an orthonormal basis of the stop, the chief
    ray's height and its slope times the far plane's distance, the
    illumination's geometry relative to its largest axial value.
    ``rinv[(degree, parity)]``: the monomials' coefficients of the basis
    (n, n); :meth:`of_map` makes them from a map and its lens."""

    def __init__(self, recipe, n_clip: int, rinv: dict, far_mm: float, geometry_scale: float, r: dict | None = None):
        self.recipe, self.n_clip, self.rinv = recipe, int(n_clip), rinv
        self.far, self.geometry_scale = float(far_mm), float(geometry_scale)
        self._r = r
        self.parts = [("xy", recipe.degree), ("chroma", recipe.chroma_degree), ("clip", recipe.clip_degree)]
        self.terms = {deg: n_terms(deg) for _, deg in self.parts}
        self.shapes = {"xy": (2,), "chroma": (recipe.n_wavelengths, 2), "clip": (self.n_clip,)}
        self.size = sum(int(np.prod(self.shapes[n])) * sum(self.terms[d]) for n, d in self.parts) + 3

    @classmethod
    def of_map(cls, rm: RayMap, lens) -> "StopBasis":
        """The basis of ``rm``'s polynomials on its fit grid of ``lens``'s stop (wide open)."""
        from ..optics.aiming import stop_grid
        r = rm.recipe
        opened, _ = rm.wide_open(lens)
        uv = stop_grid(opened, r.fit_samples) / rm.stop_radius_mm
        rr, rinv = {}, {}
        for key, m in monomial_set(uv, r).items():
            _, tri = np.linalg.qr(m)
            rr[key] = tri / math.sqrt(len(m))
            rinv[key] = np.linalg.inv(rr[key])
        scale = float(np.abs(rm.arrays["reference_geometry"]).max()) or 1.0
        return cls(r, len(rm.clear_mm), rinv, abs(float(rm.meta["far_plane_mm"])), scale, rr)

    @property
    def r(self) -> dict:
        if self._r is None:
            self._r = {k: np.linalg.inv(v) for k, v in self.rinv.items()}
        return self._r

    def _each(self, a, deg, mats: dict):
        no, _ = self.terms[deg]
        return np.concatenate([a[..., :no] @ mats[deg, 1].T, a[..., no:] @ mats[deg, 0].T], axis=-1)

    def white(self, at: dict) -> np.ndarray:
        """(S, D) from the map's arrays at S sources."""
        s = len(at["chief"])
        cols = [self._each(np.asarray(at[n], np.float64), d, self.r).reshape(s, -1) for n, d in self.parts]
        cols += [at["chief"][:, :1], at["chief"][:, 1:] * self.far, at["geometry"][:, None] / self.geometry_scale]
        return np.concatenate(cols, axis=1)

    def unwhite(self, vec: np.ndarray) -> dict:
        """The map's arrays at S sources from (S, D)."""
        s, out, i = len(vec), {}, 0
        for n, d in self.parts:
            width = sum(self.terms[d])
            count = int(np.prod(self.shapes[n])) * width
            out[n] = self._each(vec[:, i:i + count].reshape((s,) + self.shapes[n] + (width,)), d, self.rinv)
            i += count
        out["chief"] = np.stack([vec[:, i], vec[:, i + 1] / self.far], axis=1)
        out["geometry"] = vec[:, i + 2] * self.geometry_scale
        return out


class RayFieldMap(RayMap):
    """One lens of a ray-space OLF, served as its ray map: the values at a
    depth are the Legendre polynomials' at :data:`SERVE_FIELDS` fields (the
    map's Lagrange between them); the tables come from the map's grid."""

    def __init__(self, entry: dict, arrays: dict, path: str | None = None):
        super().__init__(entry["map"], {k: arrays[k] for k in TABLES}, path)
        self.map_fields = self.fields
        self.fields = np.linspace(0.0, 1.0, int(entry["serve_fields"]))
        rinv = {key: np.asarray(arrays[_rinv_name(*key)], np.float64) for key in _keys(self.recipe)}
        self.basis = StopBasis(self.recipe, len(self.clear_mm), rinv, abs(float(entry["map"]["far_plane_mm"])),
                               float(entry["geometry_scale"]))
        self.coefficients = np.asarray(arrays["legendre"], np.float64)
        self.degrees, self.max_diopters = tuple(entry["degrees"]), float(entry["max_diopters"])

    @classmethod
    def of_fit(cls, rm: RayMap, basis: StopBasis, coeffs, degrees, max_diopters: float) -> "RayFieldMap":
        """The store of a fit (Legendre coefficients (T, D) of ``basis``'s values of ``rm``), in memory."""
        entry, arrays = _record(rm, basis, coeffs, degrees, max_diopters, None)
        return cls(entry, arrays, rm.path)

    def values(self, fields, diopters) -> dict:
        """The map's arrays at sources (fields (S,), diopters (S,) 1/m)."""
        return self.basis.unwhite(legendre_terms(fields, diopters, self.max_diopters, self.degrees)
                                  @ self.coefficients)

    def _interpolated(self, x: float) -> dict:
        g = self.diopters
        pos = np.array([(g[0] - x) / (g[0] - g[-1]) * (len(g) - 1)])
        (idx,), (w,) = grid_weights(pos, len(g))
        (i2,), (w2,) = grid_weights(pos, len(g), nodes=2)
        out = self.values(self.fields, np.full(len(self.fields), x))
        out["reference_geometry"] = float(w @ self.arrays["reference_geometry"][idx])
        # the reachable disc linear between the map's depths and fields (as the map serves it)
        aim = np.tensordot(w2, self.arrays["aim"][i2], axes=1)
        out["aim"] = np.stack([np.interp(self.fields, self.map_fields, aim[:, c]) for c in (0, 1)], axis=1)
        ok = self.arrays["ok"][idx].all(axis=0)
        pos_f = self.fields * (len(self.map_fields) - 1)
        out["ok"] = ok[np.floor(pos_f).astype(int)] & ok[np.ceil(pos_f).astype(int)]
        return out


def _keys(recipe) -> list[tuple[int, int]]:
    return sorted({(d, p) for d in (recipe.degree, recipe.chroma_degree, recipe.clip_degree) for p in (0, 1)})


def _rinv_name(degree: int, parity: int) -> str:
    return f"rinv_{degree}_{parity}"


class RayFieldOLF:
    """A ray-space OLF file: each lens's :class:`RayFieldMap`."""

    def __init__(self, meta: dict, arrays: dict, path: str | os.PathLike = "<memory>"):
        self.meta, self.arrays, self.path = meta, arrays, str(path)
        self._entries = {e["lens_id"]: (i, e) for i, e in enumerate(meta["lenses"])}
        self._maps: dict = {}

    @classmethod
    def load(cls, path) -> "RayFieldOLF":
        """A file read by the shared checked reader, its format, version,
        checksum and every field it serves from (``ModelFileError`` naming the field)."""
        meta, arrays = read_npz_with_meta(path, "Omni-Lens-Field")
        return cls.from_record(path, meta, arrays)

    @classmethod
    def from_record(cls, path, meta: dict, arrays: dict) -> "RayFieldOLF":
        check_header(path, meta, arrays, FORMAT, FORMAT_VERSION)
        check_ray_field(meta, arrays, model_fail(path))
        return cls(meta, arrays, path)

    @property
    def lens_ids(self) -> list[str]:
        return list(self._entries)

    def entry(self, lens_id: str) -> dict:
        return self._entries[lens_id][1]

    def map_for(self, lens_id: str) -> RayFieldMap:
        """The lens's ray map served from the store (made once)."""
        if lens_id not in self._maps:
            i, e = self._entries[lens_id]
            prefix = f"lens{i}_"
            own = {k[len(prefix):]: v for k, v in self.arrays.items() if k.startswith(prefix)}
            self._maps[lens_id] = RayFieldMap(e, own, self.path)
        return self._maps[lens_id]

    def info(self) -> dict:
        size = os.path.getsize(self.path) if os.path.exists(self.path) else None
        return {"file": self.path, "bytes": size, "variant": "rays", "lenses": [
            {"id": e["lens_id"], "fingerprint": e["map"]["lens_fingerprint"], "degrees": list(e["degrees"]),
             "n_wavelengths": e["map"]["recipe"]["n_wavelengths"], "near_m": e["map"]["recipe"]["near_m"],
             "held_out": e.get("held_out")} for e in self.meta["lenses"]],
                "training": self.meta.get("training"), "version": self.meta.get("version"),
                "checksum": self.meta.get("checksum")}

    @staticmethod
    def write(path, lenses: list, extra: dict | None = None) -> None:
        """Write ``lenses`` [(map (``RayMap``), basis (:class:`StopBasis`),
        Legendre coefficients (T, D), degrees, max diopters, held-out scores
        or None)], atomically."""
        meta = {"lenses": [], **(extra or {})}
        arrays = {}
        for i, item in enumerate(lenses):
            entry, own = _record(*item)
            meta["lenses"].append(entry)
            arrays.update({f"lens{i}_{k}": v for k, v in own.items()})
        write_format(path, meta, arrays, FORMAT, FORMAT_VERSION)


def _record(rm: RayMap, basis: StopBasis, coeffs, degrees, d_max: float, held_out) -> tuple[dict, dict]:
    """One lens's entry and arrays (named as in its file, without the lens's prefix)."""
    record = {k: v for k, v in rm.meta.items() if k not in ("format", "version", "checksum")}
    entry = {"lens_id": rm.lens_id, "map": record, "degrees": [int(d) for d in degrees],
             "max_diopters": float(d_max), "serve_fields": SERVE_FIELDS,
             "geometry_scale": basis.geometry_scale, "held_out": held_out}
    arrays = {"legendre": np.asarray(coeffs, np.float32)}
    for key in _keys(rm.recipe):
        arrays[_rinv_name(*key)] = np.asarray(basis.rinv[key], np.float64)
    for k in TABLES:
        arrays[k] = np.asarray(rm.arrays[k])
    return entry, arrays


def check_ray_field(meta: dict, arrays: dict, fail) -> None:
    """Every field of a ray-space OLF's metadata that serving reads, in its
    range, and each lens's arrays shaped as its record says."""
    rec = Record(meta, fail)
    entries = rec.subs("lenses", (1, MAX_LENSES))
    seen = set()
    for i, e in enumerate(entries):
        lens_id = e.name("lens_id")
        if lens_id in seen:
            raise fail(f"lens {lens_id!r} twice", field=f"lenses[{i}].lens_id", allowed="each lens once")
        seen.add(lens_id)
        e.allowed_keys(ENTRY_KEYS)
        where = f"lenses[{i}]."

        def sub_fail(message, field=None, allowed=None, _w=where):
            return fail(message, field=None if field is None else _w + str(field), allowed=allowed)
        recipe, n_clip = check_map_meta(e.value("map", allowed="a ray map's record"), _prefixed(sub_fail, "map."))
        if e.table["map"].get("lens_id") != lens_id:
            raise fail(f"the map's lens {str(e.table['map'].get('lens_id'))[:80]!r}", field=where + "map.lens_id",
                       allowed=repr(lens_id))
        degrees = e.integers("degrees", 0, MAX_DEGREE, (2, 2))
        e.number("max_diopters", 0.0, 1e3, lo_open=True)
        e.integer("serve_fields", 2, 1024)
        e.number("geometry_scale", 0.0, 1e6, lo_open=True)
        e.sub("held_out", optional=True)
        p = f"lens{i}_"
        own = {k[len(p):]: v for k, v in arrays.items() if k.startswith(p)}
        size = StopBasis(recipe, n_clip, {}, 1.0, 1.0).size
        check_array(own, "legendre", ((degrees[0] + 1) * (degrees[1] + 1), size), sub_fail)
        check_bounded(own, "legendre", MAX_COEFFICIENT_MM, sub_fail)
        for deg, parity in _keys(recipe):
            n = n_terms(deg)[1 - parity]
            name = _rinv_name(deg, parity)
            check_array(own, name, (n, n), sub_fail)
            check_bounded(own, name, MAX_WHITENING, sub_fail, unit="")
        check_tables(own, recipe, sub_fail)


def _prefixed(fail, prefix: str):
    return lambda message, field=None, allowed=None: fail(message, None if field is None else prefix + str(field),
                                                          allowed)


_FILES = FileCache(RayFieldOLF.load, 2, "ray-space OLF files")


def open_ray_field(path) -> RayFieldOLF:
    """``RayFieldOLF.load``, kept for the next request of the same file."""
    return _FILES(Path(path))


__all__ = ["RayFieldMap", "RayFieldOLF", "StopBasis", "FORMAT", "legendre_terms", "open_ray_field"]
