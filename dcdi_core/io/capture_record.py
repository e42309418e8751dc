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
file named, not silently read as having none. A record read from a file is
bounded before it is parsed: at most :data:`RECORD_MAX_BYTES` (a record
this project writes is about 600 bytes; extra facts included, far below),
nested at most :data:`RECORD_MAX_DEPTH` deep (ours nest 2), and a sidecar
must be a regular file; anything else is one :class:`CaptureRecordError`.
"""
from __future__ import annotations

import json
import math
import os
import stat
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

from ..atomic import atomic_path, remove_file
from ..errors import DcdiError
from ..names import printable

EXR_ATTRIBUTE = "dcdiCapture"       # no ':' in the name: OpenImageIO reads 'x:' as another format's namespace
FORMAT = 1
SIDECAR_SUFFIX = ".dcdi.json"
KINDS = ("simulated", "rendered", "corrected", "refocused")
#: the longest record text read (bytes of a sidecar, characters of an EXR
#: attribute): 64 KiB, a hundred times a record this project writes
RECORD_MAX_BYTES = 64 << 10
#: the deepest nesting of JSON arrays and objects read (a record nests 2:
#: the record, its noise or extra; extra's values may nest a little)
RECORD_MAX_DEPTH = 16
_SHOWN_CHARS = 60                   # a bad value is shown up to this many characters


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
    (``optics.lens.lens_fingerprint``: everything optical, so a perturbed
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
        """The record in JSON ``text`` read from ``path`` (named in every
        refusal): bounded (:data:`RECORD_MAX_BYTES`, :data:`RECORD_MAX_DEPTH`)
        before it is parsed, then each field checked."""
        _check_bounds(text, path)             # json recurses once a level: bounded first
        try:
            d = json.loads(text)
        except (ValueError, TypeError) as e:
            raise CaptureRecordError(path, f"not JSON ({_shown(str(e))})") from None
        if not isinstance(d, dict):
            raise CaptureRecordError(path, "not a JSON object")
        if type(d.get("format")) is not int or d["format"] != FORMAT:
            raise CaptureRecordError(path, f"format {_shown(repr(d.get('format')))}; this version reads format "
                                           f"{FORMAT}")
        names = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - names - {"format"})
        if unknown:
            raise CaptureRecordError(path, f"unknown field(s) {_shown(', '.join(unknown))}")
        if "kind" not in d:
            raise CaptureRecordError(path, f"field kind is missing; allowed: {', '.join(KINDS)}")
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
            out.append(f"{f.name}: {printable(v)}")        # a file's text: no line or escape of its own
        return out


def _software() -> str:
    try:
        from importlib.metadata import version
        return f"dcdi {version('dcdi')}"
    except Exception:               # a checkout that was never installed
        return "dcdi"


def _positive(v) -> bool:
    return _finite(v) and v > 0


def _shown(text: str) -> str:
    """``text`` (a file's) cut to :data:`_SHOWN_CHARS` for a one-line message, its controls escaped."""
    return printable(text, _SHOWN_CHARS + 3)


def _bad(name: str, value, allowed: str) -> str:
    """A field's refusal: 'field <name> = <value>; allowed: <allowed>'."""
    return f"field {name} = {_shown(repr(value))}; allowed: {allowed}"


def _finite(v) -> bool:
    """A real number a float holds (JSON's 400-digit integers do not)."""
    if not isinstance(v, (int, float)) or isinstance(v, bool):
        return False
    try:
        return math.isfinite(v)
    except OverflowError:
        return False


def _problem(r: CaptureRecord) -> str:
    """What is wrong with a record's values ('' if nothing), naming the field."""
    if not isinstance(r.kind, str) or r.kind not in KINDS:
        return _bad("kind", r.kind, ", ".join(KINDS))
    for name in ("lens_id", "prescription_sha256", "psf_source"):
        v = getattr(r, name)
        if v is not None and not isinstance(v, str):
            return _bad(name, v, "a string, or null")
    if r.pixel_pitch_mm is not None and not _positive(r.pixel_pitch_mm):
        return _bad("pixel_pitch_mm", r.pixel_pitch_mm, "> 0 mm, finite")
    if r.focus_distance_m is not None and not _positive(r.focus_distance_m):
        return _bad("focus_distance_m", r.focus_distance_m, "> 0 m, finite")
    if r.axis_px is not None and not (isinstance(r.axis_px, tuple) and len(r.axis_px) == 2
                                      and all(_finite(a) for a in r.axis_px)):
        return _bad("axis_px", r.axis_px, "(row, col), finite pixels")
    if r.image_size is not None and not (isinstance(r.image_size, tuple) and len(r.image_size) == 2 and all(
            isinstance(a, int) and not isinstance(a, bool) and a >= 1 for a in r.image_size)):
        return _bad("image_size", r.image_size, "(height, width), whole pixels >= 1")
    if r.noise is not None and _noise_problem(r.noise):
        return _noise_problem(r.noise)
    if r.distortion_applied is not None and not isinstance(r.distortion_applied, bool):
        return _bad("distortion_applied", r.distortion_applied, "true, false or null")
    if not isinstance(r.software, str):
        return _bad("software", r.software, "a string")
    if not isinstance(r.extra, dict) or not all(isinstance(k, str) for k in r.extra):
        return _bad("extra", r.extra, "an object with string keys")
    try:
        json.dumps(r.extra)
    except (TypeError, ValueError, RecursionError):
        return "field extra: JSON values only"
    return ""


def _noise_problem(noise) -> str:
    """What is wrong with a record's noise ('' if nothing)."""
    if not isinstance(noise, dict) or set(noise) != {"full_well_electrons", "read_noise_electrons", "seed"}:
        return _bad("noise", noise, "null, or {full_well_electrons, read_noise_electrons, seed}")
    if not _positive(noise["full_well_electrons"]):
        return _bad("noise.full_well_electrons", noise["full_well_electrons"], "> 0 electrons, finite")
    rn = noise["read_noise_electrons"]
    if not (_finite(rn) and rn >= 0):
        return _bad("noise.read_noise_electrons", rn, ">= 0 electrons, finite")
    return ""


def _check_bounds(text: str, path) -> None:
    """Refuse, before it is parsed, record text longer than
    :data:`RECORD_MAX_BYTES` characters or nested deeper than
    :data:`RECORD_MAX_DEPTH` (json would recurse once a level: 100000
    levels end in RecursionError). One linear pass over the text."""
    if len(text) > RECORD_MAX_BYTES:
        raise CaptureRecordError(path, f"{len(text)} characters; a record is at most {RECORD_MAX_BYTES} "
                                       f"({RECORD_MAX_BYTES >> 10} KiB)")
    from .jsontext import nesting
    if nesting(text, RECORD_MAX_DEPTH) > RECORD_MAX_DEPTH:
        raise CaptureRecordError(path, f"JSON nested more than {RECORD_MAX_DEPTH} levels deep; a record "
                                       f"nests at most {RECORD_MAX_DEPTH}")


def prescription_sha256(lens) -> str:
    """The lens's optical fingerprint (``optics.lens.lens_fingerprint``)."""
    from ..optics.lens import lens_fingerprint
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
        remove_file(side)
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
    text = _sidecar_text(side)
    return None if text is None else CaptureRecord.from_json(text, side)


def _sidecar_text(side: Path) -> str | None:
    """The text of the sidecar ``side`` (None where there is none), refused
    before it is read when it is not a regular file (a folder, a FIFO that
    would block) or longer than :data:`RECORD_MAX_BYTES`."""
    try:
        st = os.stat(side)
    except FileNotFoundError:
        return None
    except OSError as e:
        raise CaptureRecordError(side, f"cannot be read ({e.strerror})") from None
    if stat.S_ISDIR(st.st_mode):
        raise CaptureRecordError(side, "is a folder; a record sidecar must be a JSON file (move the folder away)")
    if not stat.S_ISREG(st.st_mode):
        raise CaptureRecordError(side, "is not a regular file; a record sidecar must be a JSON file")
    too_long = f"bytes; a record is at most {RECORD_MAX_BYTES} bytes ({RECORD_MAX_BYTES >> 10} KiB)"
    if st.st_size > RECORD_MAX_BYTES:
        raise CaptureRecordError(side, f"{st.st_size} {too_long}")
    try:
        with open(side, "rb") as f:
            raw = f.read(RECORD_MAX_BYTES + 1)         # one more: a file that grew since its stat shows
        if len(raw) > RECORD_MAX_BYTES:
            raise CaptureRecordError(side, f"more than {RECORD_MAX_BYTES} {too_long}")
        return raw.decode("utf-8")
    except OSError as e:
        raise CaptureRecordError(side, f"cannot be read ({e.strerror})") from None
    except UnicodeDecodeError as e:
        raise CaptureRecordError(side, f"not UTF-8 text ({e.reason} at byte {e.start})") from None


def _exr_record_text(path: Path) -> str | None:
    """The record attribute of an EXR's first part (None: it has none), from
    its headers only: tiled and deep files included."""
    from . import rawexr
    try:
        f = rawexr.ExrFile(path, header_only=True)
    except rawexr.RawExrError as e:
        raise CaptureRecordError(path, e.why) from None
    return f.parts[0].strings.get(EXR_ATTRIBUTE) if f.parts else None
