"""Shipped network files: a module's state as .npz arrays (no pickle) plus
one JSON string ``meta`` with format, version and a sha256 checksum of all
of it (``io.npzfile.checksum``, as the PSF bases). numpy only: writing them from a torch
module and loading them into one is ``models.common.weights_file``.

Reading one (:func:`read_model_npz`) is the shared checked reader
(``io.npzfile.read_npz``: size limits, array headers before their data,
finite arrays), then format, version and checksum, then the format's own
check of its metadata (:data:`FORMAT_CHECKS`, or the caller's): every key
it needs present, every size in its documented range, before the network
it describes is built. Each problem is one :class:`ModelFileError` line
naming the file, the field and what is allowed.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..atomic import atomic_path
from .npzfile import Record, checksum, read_npz
from ..errors import ModelFileError

DTYPES = ("float16", "float32")


def model_fail(path):
    """``fail(message, field=None, allowed=None)`` of ``io.npzfile`` for a model file: a ModelFileError."""
    return lambda message, field=None, allowed=None: ModelFileError(path, message, field=field, allowed=allowed)


def write_model_npz(path, meta: dict, arrays: dict) -> dict:
    """Write ``arrays`` and ``meta`` (its checksum added) atomically; returns meta."""
    meta = dict(meta)
    meta["checksum"] = checksum(meta, arrays)
    path = Path(path)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            from .npzfile import save_npz
            save_npz(f, {"meta": np.array(json.dumps(meta)), **arrays}, compressed=False)
    return meta


def read_npz_with_meta(path, what: str) -> tuple[dict, dict]:
    """(meta, arrays) of an .npz with a JSON ``meta`` record, read by the
    checked reader; any damage is a ModelFileError naming the file (``what``:
    the kind of file expected)."""
    path = Path(path)
    fail = model_fail(path)
    meta, arrays = read_npz(path, lambda message, field=None, allowed=None: fail(
        message + (f": not an exported {what}" if field == "meta" else ""), field, allowed))
    return meta, arrays


def check_header(path, meta: dict, arrays: dict, fmt: str, version: int) -> None:
    """Format, version and checksum of a model file's record."""
    if meta.get("format") != fmt:
        raise ModelFileError(path, f"format {str(meta.get('format'))[:80]!r}", field="format", allowed=repr(fmt))
    if meta.get("version") != version:
        raise ModelFileError(path, f"version {str(meta.get('version'))[:80]!r} (newer or older software wrote it)",
                             field="version", allowed=str(version))
    if meta.get("checksum") != checksum(meta, arrays):
        raise ModelFileError(path, "checksum mismatch (the file is corrupt or was edited)", field="checksum")


def read_model_npz(path, fmt: str, version: int, what: str, check=None) -> tuple[dict, dict]:
    """(meta, arrays) of a file written by :func:`write_model_npz`, its
    format, version and checksum checked, then its metadata by ``check(meta,
    arrays, fail)`` (default: :data:`FORMAT_CHECKS`'s for ``fmt``, if any);
    ``what`` names the kind of file."""
    path = Path(path)
    meta, arrays = read_npz_with_meta(path, what)
    check_header(path, meta, arrays, fmt, version)
    check = check or FORMAT_CHECKS.get(fmt)
    if check is not None:
        check(meta, arrays, model_fail(path))
    return meta, arrays


def float_parameters(arrays: dict) -> int:
    """The number of floating-point values a file holds: the most parameters its network may have."""
    return sum(int(a.size) for a in arrays.values() if a.dtype.kind == "f")


def check_parameters(least: int, arrays: dict, fail, what: str) -> None:
    """Refuse a network whose spec needs at least ``least`` parameters when
    the file holds fewer (it could not be loaded; building it first could
    take far more memory than the file)."""
    held = float_parameters(arrays)
    if least > held:
        raise fail(f"{what} needs at least {least} parameters; the file holds {held}", field="spec",
                   allowed=f"a spec whose network the file's {held} values fill")


# -------------------------------------------------------------- DACN
# ``models.dacn.spec.DACNSpec``'s fields (the runtime does not import the
# training code): integers and their ranges (the shipped: 64 channels, 3 x 2
# blocks; the paper's 180 channels, 6 x 6, window 8, 6 heads), the ratios'
# ranges, the choices and the flags. tests/test_hostile_models.py checks
# these are its fields.
DACN_INTEGERS = {"channels": (1, 1024), "groups": (1, 32), "blocks": (1, 32), "window": (1, 64),
                 "heads": (1, 64), "rdicab_heads": (1, 64)}
DACN_RATIOS = {"mlp_ratio": 16.0, "rdicab_mlp_ratio": 16.0, "res_scale": 16.0}
DACN_CHOICES = {"racm": ("rb", "rstb"), "tail": ("direct", "paper"), "depth_encoding": ("minmax", "diopter")}
DACN_FLAGS = ("rdicab", "d2cb", "condition", "refine")


def check_dacn(meta: dict, arrays: dict, fail) -> None:
    """A DACN file's metadata: its spec's fields in range, its step, weights
    kind and lens; the spec's network no larger than the weights held."""
    rec = Record(meta, fail)
    spec = rec.sub("spec")
    spec.allowed_keys(list(DACN_INTEGERS) + list(DACN_RATIOS) + list(DACN_CHOICES) + list(DACN_FLAGS))
    ints = {k: spec.integer(k, lo, hi, optional=True) for k, (lo, hi) in DACN_INTEGERS.items()}
    for k, hi in DACN_RATIOS.items():
        spec.number(k, 0.0, hi, optional=True, lo_open=True)
    for k, choices in DACN_CHOICES.items():
        spec.choice(k, choices, optional=True)
    for k in DACN_FLAGS:
        spec.flag(k, optional=True)
    rec.integer("step", 0, 10 ** 12)
    rec.text("weights", max_chars=64)
    rec.sub("config")
    rec.sub("da2t", optional=True)
    rec.name("lens", optional=True)
    rec.number("pixel_pitch_mm", 0.0, 10.0, optional=True, lo_open=True)
    # the convolutions every group has, C x C x 3 x 3 each (a residual block
    # two, a Swin block's attention at least 4 C^2), and the one after the body
    c = ints["channels"] or 48
    per_block = 18 if (spec.table.get("racm") or "rstb") == "rb" else 4
    least = ((ints["groups"] or 2) * (9 + (ints["blocks"] or 2) * per_block) + 9) * c * c
    check_parameters(least, arrays, fail, "this DACN spec")


def check_depthnet(meta: dict, arrays: dict, fail) -> None:
    """A depth network file's metadata: its spec's widths in range, its step
    and lens; the spec's network no larger than the weights held."""
    rec = Record(meta, fail)
    spec = rec.sub("spec")
    spec.allowed_keys(["widths"])
    widths = spec.integers("widths", 1, 1024, (2, 8))
    rec.integer("step", 0, 10 ** 12)
    rec.name("lens", optional=True)
    rec.number("pixel_pitch_mm", 0.0, 10.0, optional=True, lo_open=True)
    # each level's second 3 x 3 convolution, w x w x 3 x 3
    check_parameters(sum(9 * w * w for w in widths), arrays, fail, "this depth network spec")


FORMAT_CHECKS = {"dcdi-dacn": check_dacn, "dcdi-depthnet": check_depthnet}
