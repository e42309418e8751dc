"""What an image file remembers of how it was made: a :class:`CaptureRecord`.

``dcdi simulate``, the factory and the add-on's Simulate write one beside
the pixels; ``correct``, ``dof`` and ``bokeh`` read it back as their
defaults (the capture's pixel pitch, optical axis and focus), so a capture
made with this tool need not be described again.

Where it lives: in an EXR, one string attribute of the header
(:data:`EXR_ATTRIBUTE`, JSON), which survives a copy of the file; for
formats without such a header (PNG, JPEG), a JSON sidecar ``<file>.dcdi.json``
beside it (:func:`sidecar_path`), written after the image and removed when
the image is written again without one (a stale record is worse than none).

The JSON holds ``format`` (:data:`FORMAT`) and the record's fields; a file
whose record is damaged or of another format version is refused with the
file named, not silently read as having none.
"""
from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

from ..errors import DcdiError
from ..atomic import atomic_path

EXR_ATTRIBUTE = "dcdiCapture"       # no ':' in the name: OpenImageIO reads 'x:' as another format's namespace
FORMAT = 1
SIDECAR_SUFFIX = ".dcdi.json"
KINDS = ("simulated", "rendered", "corrected", "refocused")


class CaptureRecordError(DcdiError, ValueError):
    """A record that cannot be read back (damaged, another format version)."""

    def __init__(self, path, message: str):
        self.path = Path(path)
        super().__init__(f"{self.path}: capture record: {message}")


@dataclass(frozen=True)
class CaptureRecord:
    """How an image was made. Units: ``pixel_pitch_mm`` mm per pixel on the
    sensor; ``axis_px`` (row, col) the optical axis in the image's pixels
    (0.5 is a pixel's centre... as ``ImageGeometry.center_px``);
    ``image_size`` (height, width) px; ``focus_distance_m`` metres from the
    first vertex where the sensor was focused (None: as prescribed).

    kind: one of :data:`KINDS`. lens_id and prescription_sha256: the lens
    (``psf.library.lens_fingerprint``: everything optical, so a perturbed
    copy of a shipped lens differs). psf_source: 'basis', 'cache' or
    'trace'. noise: None (noiseless) or {full_well_electrons,
    read_noise_electrons, seed}. distortion_applied: the image was moved to
    where the real chief rays put it. software: what wrote it. extra: other
    facts ({str: JSON value}), shown by ``dcdi info`` and otherwise unused.
    """

    kind: str
    lens_id: str | None = None
    prescription_sha256: str | None = None
    pixel_pitch_mm: float | None = None
    axis_px: tuple | None = None
    image_size: tuple | None = None
    focus_distance_m: float | None = None
    psf_source: str | None = None
    noise: dict | None = None
    distortion_applied: bool | None = None
    software: str = field(default_factory=lambda: _software())
    extra: dict = field(default_factory=dict)

    def __post_init__(self):
        problem = _problem(self)
        if problem:
            raise ValueError(f"capture record: {problem}")

    def as_json(self) -> str:
        d = {"format": FORMAT, **asdict(self)}
        return json.dumps(d, sort_keys=True, separators=(",", ":"))

    @classmethod
    def from_json(cls, text: str, path) -> "CaptureRecord":
        try:
            d = json.loads(text)
        except (ValueError, TypeError) as e:
            raise CaptureRecordError(path, f"not JSON ({e})") from None
        if not isinstance(d, dict):
            raise CaptureRecordError(path, "not a JSON object")
        if d.get("format") != FORMAT:
            raise CaptureRecordError(path, f"format {d.get('format')!r}; this version reads format {FORMAT}")
        names = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - names - {"format"})
        if unknown:
            raise CaptureRecordError(path, f"unknown field(s) {', '.join(unknown)}")
        kw = {k: v for k, v in d.items() if k in names}
        for k in ("axis_px", "image_size"):
            if isinstance(kw.get(k), list):
                kw[k] = tuple(kw[k])
        try:
            return cls(**kw)
        except (TypeError, ValueError) as e:
            raise CaptureRecordError(path, str(e).removeprefix("capture record: ")) from None

    def lines(self) -> list[str]:
        """The record as 'name: value' lines for a person (``dcdi info``)."""
        out = []
        for f in fields(self):
            v = getattr(self, f.name)
            if v is None or v == {}:
                continue
            if f.name == "pixel_pitch_mm":
                v = f"{v:g} mm ({v * 1000:g} um)"
            elif f.name == "focus_distance_m":
                v = f"{v:g} m"
            elif f.name == "axis_px":
                v = f"row {v[0]:g}, col {v[1]:g} px"
            elif f.name == "image_size":
                v = f"{v[0]} x {v[1]} px (height x width)"
            elif isinstance(v, dict):
                v = ", ".join(f"{k}={x}" for k, x in sorted(v.items()))
            out.append(f"{f.name}: {v}")
        return out


def _software() -> str:
    try:
        from importlib.metadata import version
        return f"dcdi {version('dcdi')}"
    except Exception:               # a checkout that was never installed
        return "dcdi"


def _positive(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v > 0


def _problem(r: CaptureRecord) -> str:
    """What is wrong with a record's values ('' if nothing)."""
    if r.kind not in KINDS:
        return f"kind {r.kind!r}; allowed: {', '.join(KINDS)}"
    for name in ("lens_id", "prescription_sha256", "psf_source"):
        v = getattr(r, name)
        if v is not None and not isinstance(v, str):
            return f"{name} {v!r}: a string, or null"
    if r.pixel_pitch_mm is not None and not _positive(r.pixel_pitch_mm):
        return f"pixel_pitch_mm {r.pixel_pitch_mm!r}: > 0 mm, finite"
    if r.focus_distance_m is not None and not _positive(r.focus_distance_m):
        return f"focus_distance_m {r.focus_distance_m!r}: > 0 m, finite"
    if r.axis_px is not None and not (isinstance(r.axis_px, tuple) and len(r.axis_px) == 2 and all(
            isinstance(a, (int, float)) and not isinstance(a, bool) and math.isfinite(a) for a in r.axis_px)):
        return f"axis_px {r.axis_px!r}: (row, col), finite pixels"
    if r.image_size is not None and not (isinstance(r.image_size, tuple) and len(r.image_size) == 2 and all(
            isinstance(a, int) and not isinstance(a, bool) and a >= 1 for a in r.image_size)):
        return f"image_size {r.image_size!r}: (height, width), whole pixels >= 1"
    if r.noise is not None:
        if not isinstance(r.noise, dict) or set(r.noise) != {"full_well_electrons", "read_noise_electrons", "seed"}:
            return f"noise {r.noise!r}: null, or {{full_well_electrons, read_noise_electrons, seed}}"
        if not _positive(r.noise["full_well_electrons"]):
            return f"noise.full_well_electrons {r.noise['full_well_electrons']!r}: > 0 electrons"
        rn = r.noise["read_noise_electrons"]
        if not (isinstance(rn, (int, float)) and not isinstance(rn, bool) and math.isfinite(rn) and rn >= 0):
            return f"noise.read_noise_electrons {rn!r}: >= 0 electrons"
    if r.distortion_applied is not None and not isinstance(r.distortion_applied, bool):
        return f"distortion_applied {r.distortion_applied!r}: true, false or null"
    if not isinstance(r.software, str):
        return f"software {r.software!r}: a string"
    if not isinstance(r.extra, dict) or not all(isinstance(k, str) for k in r.extra):
        return f"extra {r.extra!r}: an object with string keys"
    try:
        json.dumps(r.extra)
    except (TypeError, ValueError):
        return "extra: JSON values only"
    return ""


def prescription_sha256(lens) -> str:
    """The lens's optical fingerprint (``psf.library.lens_fingerprint``)."""
    from ..psf.library import lens_fingerprint
    return lens_fingerprint(lens)


def sidecar_path(path) -> Path:
    """Where the record of a PNG or JPEG ``path`` lives: ``<path>.dcdi.json``."""
    path = Path(path)
    return path.with_name(path.name + SIDECAR_SUFFIX)


def has_header(path) -> bool:
    """The format keeps the record in its own header (EXR)."""
    return Path(path).suffix.lower() == ".exr"


def write_sidecar(path, record: CaptureRecord | None) -> None:
    """Write (atomically) the sidecar of ``path``, or remove a stale one when
    ``record`` is None."""
    side = sidecar_path(path)
    if record is None:
        side.unlink(missing_ok=True)
        return
    with atomic_path(side) as tmp:
        Path(tmp).write_text(record.as_json() + "\n", encoding="utf-8")


def read_record(path) -> CaptureRecord | None:
    """The record an image file carries (EXR header attribute, else the
    sidecar), or None when it carries none. A damaged record raises
    :class:`CaptureRecordError` naming the file."""
    path = Path(path)
    if has_header(path):
        text = _exr_record_text(path)
        return None if text is None else CaptureRecord.from_json(text, path)
    side = sidecar_path(path)
    if not side.is_file():
        return None
    try:
        text = side.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise CaptureRecordError(side, f"cannot be read ({e})") from None
    return CaptureRecord.from_json(text, side)


def _exr_record_text(path: Path) -> str | None:
    from . import rawexr
    try:
        f = rawexr.ExrFile(path, header_only=True)
    except rawexr.RawExrError as e:
        raise CaptureRecordError(path, str(e)) from None
    return f.parts[0].strings.get(EXR_ATTRIBUTE) if f.parts else None
