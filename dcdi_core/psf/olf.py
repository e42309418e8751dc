"""Serve an exported Omni-Lens-Field (.npz) with numpy alone.

The file holds the network's arrays and a JSON metadata record (see
``models.export``); it is read with ``allow_pickle=False`` and checked
against its sha256 checksum. A lens is served only if its optical
fingerprint (``optics.lens.lens_fingerprint``: surfaces, glass indices,
sensor) equals the one the OLF learned, and only within the trained ranges
of field, depth and focus; otherwise a :class:`LensMismatchError` or
:class:`OutsideTrainedRangeError` says so (the caller traces instead).

The input encodings below are the only ones: the trainer encodes its
samples with the same functions.
"""
from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

from ..io.npzfile import READ_ERRORS, Record, checksum  # noqa: F401  (READ_ERRORS, checksum: re-exported)
from ..io.model_npz import check_header, model_fail, read_npz_with_meta
from ..errors import LensMismatchError, ModelFileError, OutsideTrainedRangeError
from ..errors import InputRangeError

FORMAT = "dcdi-olf"
FORMAT_VERSION = 1


# ------------------------------------------------------------------ encodings
def inverse_depth(depth_m, far_m: float) -> np.ndarray:
    """1/depth (1/m); depths at or beyond ``far_m`` (inf, 1e10 included) are
    infinity, 0 (docs/design.md). NaN, 0 and negative depths are errors."""
    d = np.asarray(depth_m, dtype=np.float64)
    bad = ~(d > 0)
    if bad.any():
        raise InputRangeError("depth_m", float(d[bad].ravel()[0]),
                              "> 0 metres or inf (mask invalid depths before asking for PSFs)")
    far = d >= far_m
    return np.where(far, 0.0, 1.0 / np.where(far, 1.0, d))


def encode_radial(spec: dict, lens_index, field, diopters, focus_diopters=None) -> np.ndarray:
    """Inputs (n, n_inputs) of the radial variant: field radius, inverse depth
    / diopter_scale, [focus inverse distance / diopter_scale], lens one-hot.
    Arrays broadcast together and are flattened."""
    n_l = len(spec["lenses"])
    focus = bool(spec.get("focus", False))
    arrs = [field, diopters, lens_index] + ([0.0 if focus_diopters is None else focus_diopters] if focus else [])
    b = np.broadcast_arrays(*(np.asarray(a, dtype=np.float64) for a in arrs))
    f, dio, li = (a.ravel() for a in b[:3])
    cols = [f, dio / spec["diopter_scale"]]
    if focus:
        cols.append(b[3].ravel() / spec["diopter_scale"])
    onehot = (li.astype(np.int64)[:, None] == np.arange(n_l)[None, :]).astype(np.float64)
    return np.concatenate([np.stack(cols, -1), onehot], axis=-1)


def encode_paper(spec: dict, lens_index, row, col, depth_m) -> np.ndarray:
    """Inputs (n, 4) of the paper variant: patch row / (rows - 1), patch
    column / (cols - 1), depth (m) / max depth, lens index / (lenses - 1)."""
    g = spec["paper_grid"]
    rows, cols = g["height"] // g["patch"], g["width"] // g["patch"]
    n_l = len(spec["lenses"])
    r, c, d, li = (a.ravel() for a in np.broadcast_arrays(*(np.asarray(a, dtype=np.float64)
                                                            for a in (row, col, depth_m, lens_index))))
    return np.stack([r / (rows - 1), c / (cols - 1), d / g["max_depth_m"], li / max(n_l - 1, 1)], -1)


def patch_centres_px(spec: dict, row, col):
    """Pixel (row, col) of the centres of patches (row, col) of the paper grid
    (the convention of ``render.psfmap``: m i + (m - 1) / 2)."""
    m = spec["paper_grid"]["patch"]
    return np.asarray(row, float) * m + (m - 1) / 2.0, np.asarray(col, float) * m + (m - 1) / 2.0


# ----------------------------------------------------------------- file I/O
# the limits of an OLF's metadata, each checked on load (the shipped one: 4
# lenses, k 41-129, 1 hidden layer of 64; the paper's: 5 of 2048, k 41)
MAX_LENSES = 64
MAX_KERNEL = 255               # px, odd
MAX_HIDDEN_LAYERS = 32
MAX_WIDTH = 8192


def read_olf_file(path) -> tuple[dict, dict]:
    """(metadata, arrays) of an exported OLF, checked: the file by the shared
    reader (``io.model_npz``: size, arrays, finite), format, version,
    checksum, then every field the runtime reads (:func:`check_olf`)."""
    path = Path(path)
    meta, arrays = read_npz_with_meta(path, "Omni-Lens-Field")
    check_header(path, meta, arrays, FORMAT, FORMAT_VERSION)
    check_olf(meta, arrays, model_fail(path))
    return meta, arrays


def load_olf_file(path):
    """An OLF file of either kind, read once and checked: the network
    (:class:`OmniLensField`) or the store in ray space
    (``psf.rayfield.RayFieldOLF``), by the format its record names."""
    from . import rayfield
    path = Path(path)
    meta, arrays = read_npz_with_meta(path, "Omni-Lens-Field")
    if meta.get("format") == rayfield.FORMAT:
        return rayfield.RayFieldOLF.from_record(path, meta, arrays)
    if meta.get("format") != FORMAT:
        raise ModelFileError(path, f"format {str(meta.get('format'))[:80]!r}", field="format",
                             allowed=f"{FORMAT!r} or {rayfield.FORMAT!r}")
    check_header(path, meta, arrays, FORMAT, FORMAT_VERSION)
    check_olf(meta, arrays, model_fail(path))
    return OmniLensField(meta, arrays, path)


def check_olf(meta: dict, arrays: dict, fail) -> None:
    """Every field of an OLF's metadata that the runtime reads, in its range,
    and every array the network names with the shape its spec gives (``fail``:
    ``io.npzfile``'s)."""
    rec = Record(meta, fail)
    spec = rec.sub("spec")
    variant = spec.choice("variant", ("paper", "radial"))
    lens_ids = spec.strings("lenses", (1, MAX_LENSES), max_chars=128)
    ks = spec.integers("kernel_sizes", 1, MAX_KERNEL, (len(lens_ids), len(lens_ids)), odd=True)
    width = spec.integer("width", 1, MAX_WIDTH)
    first = spec.integer("first_width", 1, MAX_WIDTH, optional=True) or width // 4
    if first < 1:
        raise fail(f"width {width} leaves a first layer of {first}", field="spec.width", allowed=">= 4")
    hidden = spec.integer("hidden_layers", 0, MAX_HIDDEN_LAYERS)
    focus = spec.flag("focus", optional=True)
    spec.number("diopter_scale", 0.0, 1e3, lo_open=True, optional=variant == "paper")
    if variant == "paper":
        grid = spec.sub("paper_grid")
        for key in ("height", "width", "patch"):
            grid.integer(key, 1, 65536)
        grid.number("max_depth_m", 0.0, 1e6, lo_open=True)
        n_in = 4
    else:
        n_in = 2 + int(bool(focus)) + len(lens_ids)
    trunk = [(n_in, first), (first, width)] + [(width, width)] * hidden
    heads = [(width, ks[0] * ks[0])] * 3 if variant == "paper" else [(width, 3 * k * k) for k in ks]
    net = rec.sub("network")
    _check_layers(net, "trunk", trunk, arrays, fail)
    _check_layers(net, "heads", heads, arrays, fail)
    _check_lenses(rec, lens_ids, ks, fail)


def _check_layers(net, key: str, shapes, arrays: dict, fail) -> None:
    """The network's ``key`` layers: one [weight, bias] pair of array names
    each, shaped (out, in) and (out,) as the spec says."""
    from ..io.npzfile import check_array
    for names, (n_in, n_out) in zip(_pairs(net, key, len(shapes)), shapes):
        check_array(arrays, names[0], (n_out, n_in), fail)
        check_array(arrays, names[1], (n_out,), fail)


def _pairs(net, key: str, count: int) -> list:
    """The [weight, bias] array names of ``count`` layers at ``net[key]``."""
    items = net.value(key, allowed=f"{count} [weight, bias] pairs of array names")
    ok = isinstance(items, list) and len(items) == count and all(
        isinstance(p, list) and len(p) == 2 and all(isinstance(n, str) for n in p) for p in items)
    if not ok:
        raise net.refuse(key, items, f"{count} [weight, bias] pairs of array names (the spec's layers)")
    return items


def _check_lenses(rec, lens_ids, ks, fail) -> None:
    """One entry per lens of the spec, each with the fields the runtime reads."""
    from .basis import check_grid, check_psf_settings
    entries = rec.subs("lenses", (len(lens_ids), len(lens_ids)))
    for i, (e, lens_id, k) in enumerate(zip(entries, lens_ids, ks)):
        if e.name("id") != lens_id:
            raise fail(f"{e.table['id']!r} where the spec has {lens_id!r}", field=e.where("id"),
                       allowed=f"the spec's lenses[{i}]")
        e.text("fingerprint", max_chars=128)
        e.integer("kernel_size", k, k)
        e.number("pixel_pitch_mm", 0.0, 10.0, lo_open=True)
        lo, hi = e.numbers("field_range", 0.0, 10.0, (2, 2))
        near, far = e.numbers("depth_range_m", 0.0, 1e6, (2, 2), lo_open=True)
        if not (lo <= hi and near < far):
            raise fail(f"field {lo}-{hi}, depths {near}-{far} m", field=e.where("field_range"),
                       allowed="ranges whose low end is below their high end")
        e.numbers("focus_range_m", 0.0, 1e6, (2, 2), lo_open=True, inf=True, optional=True)
        e.numbers("focus_diopters_range", 0.0, 1e6, (2, 2), optional=True)
        e.number("prescribed_focus_diopters", -1e6, 1e6, optional=True)
        if e.table.get("library_grid") is not None:
            check_grid(e.sub("library_grid"), k, fail)
        check_psf_settings(e.sub("psf_settings"), fail)


# ------------------------------------------------------------------- network
def _sigmoid(z):
    return 0.5 * (1.0 + np.tanh(0.5 * z))


def _softmax(z, axis=-1, *, overwrite: bool = False):
    """Softmax along ``axis``; ``overwrite``: ``z`` (a temporary) becomes the result (no copies)."""
    z = z if overwrite else z.copy()
    z -= z.max(axis=axis, keepdims=True)
    np.exp(z, out=z)
    z /= z.sum(axis=axis, keepdims=True)
    return z


class OmniLensField:
    """An exported OLF, ready to serve PSFs (numpy)."""

    def __init__(self, meta: dict, arrays: dict, path: str | os.PathLike = "<memory>"):
        self.meta = meta
        self.path = str(path)
        self.spec = meta["spec"]
        self.variant = self.spec["variant"]
        net = meta["network"]
        try:
            self._trunk = [(arrays[w], arrays[b]) for w, b in net["trunk"]]
            self._heads = [(arrays[w], arrays[b]) for w, b in net["heads"]]
        except KeyError as e:
            raise ModelFileError(self.path, f"array {e} is missing", field="network") from None
        self._lenses = {entry["id"]: entry for entry in meta["lenses"]}
        self._cast = {}

    @classmethod
    def load(cls, path) -> "OmniLensField":
        meta, arrays = read_olf_file(path)
        return cls(meta, arrays, path)

    # ------------------------------------------------------------- queries
    @property
    def lens_ids(self) -> list[str]:
        return list(self.spec["lenses"])

    def lens_entry(self, lens_id: str) -> dict:
        if lens_id not in self._lenses:
            raise LensMismatchError(f"{self.path}: lens {lens_id!r} is not one this OLF learned "
                                    f"({', '.join(self.lens_ids)}); trace its PSFs instead")
        return self._lenses[lens_id]

    def kernel_size(self, lens_id: str) -> int:
        return int(self.lens_entry(lens_id)["kernel_size"])

    def check_lens(self, lens) -> int:
        """The lens's index in the OLF; refuses a lens whose prescription (optical
        fingerprint) differs from the one learned."""
        from ..optics.lens import lens_fingerprint

        entry = self.lens_entry(lens.id)
        fp = lens_fingerprint(lens)
        if fp != entry["fingerprint"]:
            raise LensMismatchError(
                f"{self.path}: lens {lens.id!r} ({lens.path}) differs optically from the prescription this OLF "
                f"learned ({entry.get('file')}; fingerprint {entry['fingerprint'][:12]}..., this lens "
                f"{fp[:12]}...): not served; trace its PSFs instead")
        return self.spec["lenses"].index(lens.id)

    def covers(self, lens) -> bool:
        """True if this OLF serves ``lens`` (same prescription)."""
        try:
            self.check_lens(lens)
            return True
        except LensMismatchError:
            return False

    # ------------------------------------------------------------- network
    def _weights(self, dtype):
        """The layers' (W^T, b) in ``dtype``, W^T contiguous: a BLAS given a
        transposed view may copy it or take a slower path (Debian's numpy 2.4
        in Blender 5.2: 0.32 s against 0.08 s for one head of 512 PSFs)."""
        dtype = np.dtype(dtype)
        if dtype not in self._cast:
            def cast(layers):
                return [(np.ascontiguousarray(w.T, dtype), b.astype(dtype)) for w, b in layers]
            self._cast[dtype] = (cast(self._trunk), cast(self._heads))
        return self._cast[dtype]

    def features(self, x, dtype=np.float32) -> np.ndarray:
        trunk, _ = self._weights(dtype)
        h = np.asarray(x, dtype=dtype)
        for wt, b in trunk:
            h = h @ wt
            h += b
            np.maximum(h, 0, out=h)
        return h

    @staticmethod
    def _affine(h, wt, b):
        out = h @ wt
        out += b
        return out

    def forward(self, x, lens_index: int | None = None, dtype=np.float32) -> np.ndarray:
        """The network on encoded inputs x (n, n_inputs): paper: (n, 3, k, k)
        in (0, 1) (peak scale); radial: the PSFs (n, 3, k, k) of lens index
        ``lens_index``, each channel summing to 1."""
        _, heads = self._weights(dtype)
        h = self.features(x, dtype)
        if self.variant == "paper":
            k = self.spec["kernel_sizes"][0]
            out = np.concatenate([_sigmoid(self._affine(h, wt, b)) for wt, b in heads], axis=1)
            return out.reshape(-1, 3, k, k)
        if lens_index is None:
            raise InputRangeError("lens_index", None, "a lens index (radial OLF: one head per lens)")
        k = self.spec["kernel_sizes"][lens_index]
        wt, b = heads[lens_index]
        return _softmax(self._affine(h, wt, b).reshape(-1, 3, k * k), overwrite=True).reshape(-1, 3, k, k)

    # ----------------------------------------------------------- checks
    def _check_range(self, name, values, lo, hi, unit=""):
        v = np.asarray(values, dtype=np.float64)
        if v.size == 0:
            return
        if not np.isfinite(v).all():
            raise OutsideTrainedRangeError(self.path, name, float(v[~np.isfinite(v)].ravel()[0]),
                                           f"[{lo}, {hi}]{unit}")
        if v.min() < lo - 1e-9 or v.max() > hi + 1e-9:
            bad = float(v.min()) if v.min() < lo - 1e-9 else float(v.max())
            raise OutsideTrainedRangeError(self.path, name, bad, f"[{lo}, {hi}]{unit}")

    def _diopters(self, entry, depth_m):
        near, far = entry["depth_range_m"]
        d = np.asarray(depth_m, dtype=np.float64)
        if (d > 0).all() and (d < near - 1e-9).any():
            raise OutsideTrainedRangeError(self.path, "depth_m", float(d.min()),
                                           f">= {near} m (the near limit; beyond {far} m counts as infinity)")
        return inverse_depth(d, far)

    def focus_diopters(self, lens_id: str, focus_m=None) -> np.ndarray | None:
        """The focus input (diopters) of a lens learned across focus: None
        gives its prescribed focus (the paraxial focus its sensor position is
        equivalent to); a distance (m, inf allowed) must lie in the learned
        range. None for a lens learned at its prescribed focus only (a
        distance is refused then)."""
        entry = self.lens_entry(lens_id)
        f = np.asarray(np.nan if focus_m is None else focus_m, float)
        return self._focus_diopters(lens_id, entry, focus_m, f)

    def _focus_diopters(self, lens_id, entry, focus_m, f):
        fr = entry.get("focus_range_m")
        if fr is None:
            if focus_m is not None:
                raise OutsideTrainedRangeError(self.path, "focus_m", focus_m,
                                               f"none: this OLF learned {lens_id} at its prescribed focus only")
            return None
        if focus_m is None:
            dp = entry.get("prescribed_focus_diopters")
            if dp is None:         # written before the prescribed focus was learned
                raise InputRangeError("focus_m", None, f"a focus distance in {fr} m "
                                                       f"(this OLF learned {lens_id} across focus)")
            return np.full(f.shape, float(dp))
        if not (f > 0).all():
            raise InputRangeError("focus_m", float(f[~(f > 0)].ravel()[0]), "> 0 metres, or inf")
        d = 1.0 / f
        d_lo, d_hi = entry.get("focus_diopters_range") or (1.0 / fr[1], 1.0 / fr[0])
        if d.min() < d_lo - 1e-9 or d.max() > d_hi + 1e-9:
            bad = float(f.ravel()[np.argmax((d < d_lo - 1e-9) | (d > d_hi + 1e-9))])
            raise OutsideTrainedRangeError(self.path, "focus_m", bad,
                                           f"[{fr[0]}, {fr[1]}] m (or None: the prescribed focus)")
        return d

    # ---------------------------------------------------------- PSFs
    def psf(self, lens, field, depth_m, focus_m=None, *, dtype=np.float32) -> np.ndarray:
        """Radial OLF: PSFs (..., 3, k, k) at field radii x depths [x focus
        distances] (broadcast together), kernel rows along the radial direction, as the library's;
        each channel sums to 1. ``focus_m``: the focus distance (m, inf
        allowed) for a lens trained across focus (None: its prescribed focus;
        refused for a lens learned at its prescribed focus only)."""
        if self.variant != "radial":
            raise InputRangeError("variant", self.variant, "'radial' for psf(); use patch_psf() for 'paper'")
        li = self.check_lens(lens)
        entry = self._lenses[lens.id]
        field, depth_m, f = np.broadcast_arrays(np.asarray(field, float), np.asarray(depth_m, float),
                                                np.asarray(np.nan if focus_m is None else focus_m, float))
        shape = field.shape
        self._check_range("field", field, *entry["field_range"])
        dio = self._diopters(entry, depth_m)
        fdio = self._focus_diopters(lens.id, entry, focus_m, f)
        x = encode_radial(self.spec, li, field, dio, fdio)
        k = self.spec["kernel_sizes"][li]
        # equal inputs (depths at and beyond the far limit, repeated fields) give bit-equal PSFs: a BLAS
        # product may round a row differently by its place in the batch; and each is computed once
        x = np.asarray(x).reshape(-1, np.shape(x)[-1])
        unique, back = np.unique(x, axis=0, return_inverse=True)
        return self.forward(unique, li, dtype)[back.reshape(-1)].reshape(shape + (3, k, k))

    def patch_psf(self, lens, row, col, depth_m, *, peak_scale: bool = False, dtype=np.float32) -> np.ndarray:
        """Paper OLF: PSFs (..., 3, k, k) of patches (row, col) of the paper's
        grid (fractional positions allowed) at depths; kernels in image
        orientation. Each channel renormalised to sum 1 (the network's
        peak-normalised output with ``peak_scale``). Depths beyond the grid's
        max depth use it (the paper's rule: >= 10 m is infinity)."""
        if self.variant != "paper":
            raise InputRangeError("variant", self.variant, "'paper' for patch_psf(); use psf() for 'radial'")
        li = self.check_lens(lens)
        entry = self._lenses[lens.id]
        g = self.spec["paper_grid"]
        row, col, depth_m = np.broadcast_arrays(*(np.asarray(a, float) for a in (row, col, depth_m)))
        shape = row.shape
        self._check_range("row", row, 0, g["height"] // g["patch"] - 1)
        self._check_range("col", col, 0, g["width"] // g["patch"] - 1)
        d = np.asarray(depth_m, dtype=np.float64)
        inverse_depth(d, math.inf)          # NaN, 0, negative
        near, far = entry["depth_range_m"]
        if (d < near - 1e-9).any():
            raise OutsideTrainedRangeError(self.path, "depth_m", float(d.min()), f">= {near} m (the near limit)")
        d = np.minimum(d, far)
        out = self.forward(encode_paper(self.spec, li, row, col, d), None, dtype)
        if not peak_scale:
            s = out.sum(axis=(-1, -2), keepdims=True)
            out = out / np.where(s > 0, s, 1.0)
        k = self.spec["kernel_sizes"][0]
        return out.reshape(shape + (3, k, k))

    # ------------------------------------------------------------ summary
    def info(self) -> dict:
        size = os.path.getsize(self.path) if os.path.exists(self.path) else None
        n_params = sum(w.size + b.size for w, b in self._trunk + self._heads)
        return {"file": self.path, "bytes": size, "variant": self.variant,
                "hidden_layers": self.spec["hidden_layers"], "width": self.spec["width"],
                "parameters": int(n_params), "dtype": self.meta.get("dtype"),
                "weights": self.meta.get("weights"),
                "lenses": [{k: e.get(k) for k in ("id", "fingerprint", "kernel_size", "pixel_pitch_mm",
                                                  "field_range", "depth_range_m", "focus_range_m",
                                                  "prescribed_focus_diopters")}
                           for e in self.meta["lenses"]],
                "held_out": self.meta.get("held_out"), "training": self.meta.get("training"),
                "version": self.meta.get("version"), "dcdi_version": self.meta.get("dcdi_version"),
                "checksum": self.meta.get("checksum")}
