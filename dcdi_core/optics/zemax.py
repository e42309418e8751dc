"""Import a Zemax OpticStudio sequential lens file (.zmx) as a prescription dict.

:func:`read_zmx` returns a dict in the ``lenses/SCHEMA.md`` layout and
:func:`write_toml` writes it atomically. Only rotationally symmetric,
refracting, sequential designs are imported: STANDARD and EVENASPH surfaces
(sphere, plane, conic, even asphere) with catalogue or model (nd, vd) glass.
Everything else that would change the optics (other surface types,
coordinate breaks, tilts and decentres, mirrors, obscurations, non-circular
apertures, non-sequential mode, ...) raises :class:`ZemaxImportError` naming
the file, the line number and the line. Lines that do not change the
geometric optics (fields, pupil, tolerances, drawing, POP, ...) are ignored.

Format facts used here (the .zmx text format is not formally published; they
agree with the readers in rayoptics ``zemax/zmxread.py`` and Optiland
``fileio/zemax``, and with files in rayoptics' test set):

* The file is UTF-16 (usually little-endian with a BOM) or 8-bit text
  (ASCII / UTF-8 / Latin-1). One record per line: a keyword, then fields.
* ``UNIT MM ...``: the lens unit (first field; MM, CM, IN/INCH, METR/METER).
* ``SURF n`` opens surface n; surface 0 is the object, the last is the image.
  Inside: ``TYPE STANDARD|EVENASPH|...``, ``CURV c ...`` (curvature, 1/unit),
  ``DISZ t`` (thickness to the next surface, ``INFINITY`` allowed on the
  object), ``GLAS name f1 f2 nd vd ...`` (medium after the surface; model
  glass is ``GLAS ___BLANK f1 f2 nd vd ...``; ``GLAS MIRROR`` a mirror; no GLAS
  line means air), ``DIAM sd ...`` (semi-diameter), ``CONI k``, ``PARM i v``
  (EVENASPH: PARM i is the coefficient of r^(2i), i = 1..8), ``STOP``,
  ``COMM text``, ``CLAP rmin rmax ...`` / ``FLAP f r ...`` (circular hard /
  floating aperture), ``OBDC dx dy`` (aperture decentre), ``OBSC`` ... (other
  apertures and obscurations), ``SCBD`` (surface tilt / decentre data).
* ``WAVM i wl weight`` (wavelength i in micrometres; older files: ``WAVL
  wl1 wl2 ...``) and ``PWAV i`` (1-based primary wavelength).
* ``MODE SEQ`` sequential; ``MODE NSC`` non-sequential.
"""
from __future__ import annotations

import codecs
import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

from ..names import MAX_NAME_CHARS
from .errors import ZemaxImportError
from .lens import MAX_SURFACES, read_lens_file
from ..atomic import write_text
from .prescription_toml import dumps_prescription

__all__ = ["read_zmx", "write_toml", "decode_zmx"]

DEFAULT_WAVELENGTH_NM = 587.56

# millimetres per lens unit
_UNIT_SCALE = {"MM": 1.0, "CM": 10.0, "IN": 25.4, "INCH": 25.4, "METR": 1000.0,
               "METER": 1000.0, "M": 1000.0}
_SUPPORTED_TYPES = ("STANDARD", "EVENASPH")
_EVENASPH_TERMS = 8

# Surface apertures other than a centred circle: they clip or obscure the beam
# in ways the prescription cannot express (refused when any field is non-zero).
_REFUSED_APERTURES = {
    "OBSC": "a circular obscuration",
    "CLOB": "a circular obscuration",
    "SQAP": "a rectangular aperture",
    "SQOB": "a rectangular obscuration",
    "ELAP": "an elliptical aperture",
    "ELOB": "an elliptical obscuration",
    "SPID": "a spider obscuration",
    "UDAP": "a user-defined aperture",
}
# Surface tilts / decentres (refused when any value is non-zero).
_REFUSED_TILTS = {"DECX": "a decentre", "DECY": "a decentre", "TILT": "a tilt"}


@dataclass(frozen=True)
class _Line:
    number: int  # 1-based
    text: str


@dataclass
class _Surf:
    """What the file says about one Zemax surface."""

    number: int
    line: _Line                 # the SURF line
    type: str = "STANDARD"
    curvature: float = 0.0      # 1/lens unit
    curv_line: _Line | None = None
    thickness: float = 0.0      # lens units
    disz_line: _Line | None = None
    material: object = "air"    # "air", a glass name or {"nd":..., "vd":...}
    glas_line: _Line | None = None
    diam: float | None = None   # semi-diameter, lens units
    clap: float | None = None   # circular hard aperture radius
    flap: float | None = None   # floating aperture radius
    conic: float = 0.0
    parms: dict = field(default_factory=dict)   # PARM index -> (value, line)
    stop_line: _Line | None = None
    comment: str = ""


def decode_zmx(data: bytes) -> str:
    """Text of a .zmx file: UTF-16 (by BOM, or by NUL bytes without one),
    else UTF-8, else Latin-1 (which decodes any byte string)."""
    if data.startswith(codecs.BOM_UTF16_LE):
        return data[2:].decode("utf-16-le")
    if data.startswith(codecs.BOM_UTF16_BE):
        return data[2:].decode("utf-16-be")
    if data.startswith(codecs.BOM_UTF8):
        return data[3:].decode("utf-8")
    if b"\x00" in data[:4096]:
        head = data[:4096]
        # ASCII text in UTF-16-LE has its NULs at odd offsets
        le = head[1::2].count(0) >= head[0::2].count(0)
        return data.decode("utf-16-le" if le else "utf-16-be", errors="replace")
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        return data.decode("latin-1")


def _any_nonzero(tokens) -> bool:
    """True if any field is not the number 0 (text fields count as non-zero)."""
    for tok in tokens:
        try:
            if float(tok.replace(",", ".")) != 0.0:
                return True
        except ValueError:
            return True
    return False


def _lens_id(stem: str) -> str:
    """A lens id (``lens.Lens``'s rule: a name of lower-case letters, digits and '-') from a file's stem."""
    s = re.sub(r"[^a-z0-9-]", "-", stem.lower())
    s = re.sub(r"-{2,}", "-", s).strip("-")
    return s[:MAX_NAME_CHARS].rstrip("-") or "imported-lens"


class _ZmxParser:
    """Line-by-line reader: one handler per keyword, unknown keywords ignored."""

    def __init__(self, path: Path):
        self.path = path
        self.name = ""
        self.unit = 1.0
        self.unit_line: _Line | None = None
        self.wavm: dict[int, float] = {}   # index -> micrometres
        self.wavl: list[float] = []
        self.pwav = 1
        self.surfaces: list[_Surf] = []
        self.handlers = {
            # system data
            "UNIT": self._unit, "NAME": self._name, "MODE": self._mode,
            "WAVM": self._wavm, "WAVL": self._wavl, "PWAV": self._pwav,
            # surface data
            "SURF": self._surf, "TYPE": self._type, "CURV": self._curv,
            "DISZ": self._disz, "GLAS": self._glas, "DIAM": self._diam,
            "CONI": self._coni, "PARM": self._parm, "STOP": self._stop,
            "COMM": self._comm, "CLAP": self._clap, "FLAP": self._flap,
            "OBDC": self._refuse_nonzero("an aperture decentre"),
            "SCBD": self._scbd,
        }
        for key, what in {**_REFUSED_APERTURES, **_REFUSED_TILTS}.items():
            self.handlers[key] = self._refuse_nonzero(what)

    # ------------------------------------------------------------ helpers
    def fail(self, line: _Line, message: str):
        raise ZemaxImportError(self.path, line.number, line.text, message)

    def number(self, tokens, i, line, what):
        if len(tokens) <= i:
            self.fail(line, f"{tokens[0]} has no {what}")
        tok = tokens[i]
        if tok.upper() in ("INFINITY", "INF"):
            return math.inf
        try:
            return float(tok.replace(",", "."))
        except ValueError:
            self.fail(line, f"{what} is not a number ({tok!r})")

    def integer(self, tokens, i, line, what):
        v = self.number(tokens, i, line, what)
        if not math.isfinite(v) or v != int(v):
            self.fail(line, f"{what} is not an integer")
        return int(v)

    def current(self, line) -> _Surf:
        if not self.surfaces:
            self.fail(line, "surface data before the first SURF line")
        return self.surfaces[-1]

    @staticmethod
    def rest(line: _Line) -> str:
        parts = line.text.strip().split(None, 1)
        text = parts[1].strip() if len(parts) == 2 else ""
        if len(text) >= 2 and text[0] == text[-1] == '"':
            text = text[1:-1].strip()
        return text

    def parse(self, text: str):
        lines = text.replace("\r\n", "\n").replace("\r", "\n").split("\n")
        for n, raw in enumerate(lines, 1):
            tokens = raw.split()
            if tokens and tokens[0] in self.handlers:
                self.handlers[tokens[0]](tokens, _Line(n, raw))

    # ------------------------------------------------------- system data
    def _unit(self, tokens, line):
        unit = tokens[1].upper() if len(tokens) > 1 else ""
        if unit not in _UNIT_SCALE:
            self.fail(line, f"unsupported lens unit {unit!r} (supported: MM, CM, IN, METR)")
        self.unit, self.unit_line = _UNIT_SCALE[unit], line

    def _name(self, tokens, line):
        self.name = self.rest(line)

    def _mode(self, tokens, line):
        if len(tokens) < 2 or tokens[1].upper() != "SEQ":
            self.fail(line, "only sequential mode (MODE SEQ) can be imported")

    def _wavm(self, tokens, line):
        self.wavm[self.integer(tokens, 1, line, "wavelength number")] = \
            self.number(tokens, 2, line, "wavelength")

    def _wavl(self, tokens, line):
        self.wavl = [self.number(tokens, i, line, "wavelength") for i in range(1, len(tokens))]

    def _pwav(self, tokens, line):
        self.pwav = self.integer(tokens, 1, line, "primary wavelength number")

    # ------------------------------------------------------ surface data
    def _surf(self, tokens, line):
        # object and image surfaces besides the lens's: refused as soon as one too many appears, before
        # the rest of a hostile file is parsed
        if len(self.surfaces) >= MAX_SURFACES + 2:
            self.fail(line, f"more than {MAX_SURFACES + 2} SURF lines: over the limit of {MAX_SURFACES} lens "
                            "surfaces (besides the object and the image)")
        self.surfaces.append(_Surf(self.integer(tokens, 1, line, "surface number"), line))

    def _type(self, tokens, line):
        s = self.current(line)
        kind = tokens[1].upper() if len(tokens) > 1 else ""
        if kind not in _SUPPORTED_TYPES:
            self.fail(line, f"surface {s.number}: surface type {kind or '(none)'} cannot be "
                            f"imported (supported: {', '.join(_SUPPORTED_TYPES)})")
        s.type = kind

    def _curv(self, tokens, line):
        s = self.current(line)
        s.curvature, s.curv_line = self.number(tokens, 1, line, "curvature"), line

    def _disz(self, tokens, line):
        s = self.current(line)
        s.thickness, s.disz_line = self.number(tokens, 1, line, "thickness"), line

    def _glas(self, tokens, line):
        s = self.current(line)
        if len(tokens) < 2:
            self.fail(line, f"surface {s.number}: glass line without a glass name")
        name = tokens[1]
        if name.upper() == "MIRROR":
            self.fail(line, f"surface {s.number}: mirrors cannot be imported (refracting lenses only)")
        if name.upper() == "___BLANK":   # model glass: GLAS ___BLANK f1 f2 nd vd ...
            nd = self.number(tokens, 4, line, "model glass nd")
            vd = self.number(tokens, 5, line, "model glass vd")
            if not (math.isfinite(nd) and nd >= 1.0 and math.isfinite(vd) and vd > 0.0):
                self.fail(line, f"surface {s.number}: model glass needs nd >= 1 and vd > 0 "
                                f"(got nd = {nd}, vd = {vd}; vd = 0 is a constant index)")
            s.material = {"nd": nd, "vd": vd}
        elif re.fullmatch(r"\d{6}", name):   # glass code: 517642 -> nd 1.517, vd 64.2
            s.material = {"nd": 1.0 + int(name[:3]) / 1000.0, "vd": int(name[3:]) / 10.0}
        elif name.upper() == "AIR":
            s.material = "air"
        else:
            s.material = name
        s.glas_line = line

    def _diam(self, tokens, line):
        self.current(line).diam = self.number(tokens, 1, line, "semi-diameter")

    def _coni(self, tokens, line):
        self.current(line).conic = self.number(tokens, 1, line, "conic constant")

    def _parm(self, tokens, line):
        s = self.current(line)
        s.parms[self.integer(tokens, 1, line, "parameter number")] = \
            (self.number(tokens, 2, line, "parameter value"), line)

    def _stop(self, tokens, line):
        s = self.current(line)
        s.stop_line = line

    def _comm(self, tokens, line):
        self.current(line).comment = self.rest(line)

    def _clap(self, tokens, line):   # CLAP rmin rmax ...
        s = self.current(line)
        rmin = self.number(tokens, 1, line, "minimum radius")
        if rmin != 0.0:
            self.fail(line, f"surface {s.number}: annular apertures cannot be imported")
        s.clap = self.number(tokens, 2, line, "maximum radius")

    def _flap(self, tokens, line):   # FLAP flag radius ...
        s = self.current(line)
        if len(tokens) > 2:
            s.flap = self.number(tokens, 2, line, "radius")

    def _scbd(self, tokens, line):
        # SCBD flag flag flag dx dy tx ty tz: tilt/decentre before or after the surface
        s = self.current(line)
        if _any_nonzero(tokens[4:]):
            self.fail(line, f"surface {s.number}: surface tilts and decentres cannot be imported")

    def _refuse_nonzero(self, what):
        def handler(tokens, line):
            s = self.current(line)
            if _any_nonzero(tokens[1:]):
                self.fail(line, f"surface {s.number}: {what} cannot be imported")
        return handler

    # ------------------------------------------------------------ result
    def wavelength_nm(self) -> float:
        if self.wavm:
            um = self.wavm.get(self.pwav)
        elif self.wavl and 1 <= self.pwav <= len(self.wavl):
            um = self.wavl[self.pwav - 1]
        else:
            um = None
        if um is None or not (math.isfinite(um) and um > 0):
            return DEFAULT_WAVELENGTH_NM
        return round(um * 1000.0, 9)

    def prescription(self) -> dict:
        k = self.unit
        if len(self.surfaces) < 3:
            self.fail(_Line(0, ""), f"needs an object surface, at least one lens surface and an "
                                    f"image surface (found {len(self.surfaces)} SURF lines)")
        obj, real, image = self.surfaces[0], self.surfaces[1:-1], self.surfaces[-1]

        if obj.glas_line is not None and obj.material != "air":
            self.fail(obj.glas_line, "the object space must be air")
        for s, where in ((obj, "object"), (image, "image")):
            if s.stop_line is not None:
                self.fail(s.stop_line, f"the stop cannot be on the {where} surface")
        if image.curvature != 0.0:
            self.fail(image.curv_line, "curved image surfaces cannot be imported (flat sensor only)")
        self._check_plane_image(image)

        stops = [s for s in real if s.stop_line is not None]
        if not stops:
            self.fail(_Line(0, ""), "no surface is marked STOP (the aperture stop is needed)")
        if len(stops) > 1:
            self.fail(stops[1].stop_line, "more than one STOP surface")

        sensor_sd = (image.diam or 0.0) * k
        if not sensor_sd > 0.0:
            self.fail(image.line, "the image surface has no semi-diameter (DIAM), "
                                  "which gives the sensor semi-diagonal")
        return {
            "schema_version": 1,
            "id": _lens_id(self.path.stem),
            "name": self.name or self.path.stem,
            "source": f"imported from {self.path.name} by dcdi lens import",
            "wavelength_nm": self.wavelength_nm(),
            "sensor": {"semi_diagonal_mm": sensor_sd},
            "surface": [self._surface(s) for s in real],
        }

    def _check_plane_image(self, image: _Surf):
        if image.type == "EVENASPH":
            for _, (v, line) in sorted(image.parms.items()):
                if v != 0.0:
                    self.fail(line, "aspheric image surfaces cannot be imported (flat sensor only)")

    def _surface(self, s: _Surf) -> dict:
        k = self.unit
        if not math.isfinite(s.thickness):
            self.fail(s.disz_line, f"surface {s.number}: infinite thickness after a lens surface")
        if s.thickness < 0.0:
            self.fail(s.disz_line, f"surface {s.number}: negative thicknesses cannot be imported")
        sd = s.clap if s.clap else (s.diam or s.flap)
        if not sd or not (math.isfinite(sd) and sd > 0.0):
            self.fail(s.line, f"surface {s.number} has no semi-diameter (DIAM is 0 or missing)")

        out: dict = {}
        if s.comment:
            out["label"] = s.comment
        out["radius_mm"] = math.inf if s.curvature == 0.0 else k / s.curvature
        out["thickness_mm"] = s.thickness * k
        out["material"] = s.material
        out["semi_diameter_mm"] = sd * k
        if s.conic != 0.0:
            out["conic"] = s.conic
        coeffs = self._aspheric(s)
        if coeffs:
            out["aspheric_coefficients"] = coeffs
        out["stop"] = s.stop_line is not None
        return out

    def _aspheric(self, s: _Surf) -> list[float]:
        """EVENASPH PARM i -> a_i (r^(2i) term), in mm^(1-2i), trailing zeros trimmed."""
        if s.type != "EVENASPH":
            return []
        coeffs = [0.0] * _EVENASPH_TERMS
        for i, (v, line) in s.parms.items():
            if 1 <= i <= _EVENASPH_TERMS:
                coeffs[i - 1] = v * self.unit ** (1 - 2 * i)   # sag a r^2i scales as unit^(1-2i)
            elif v != 0.0:
                self.fail(line, f"surface {s.number}: EVENASPH has parameters 1 to "
                                f"{_EVENASPH_TERMS} only")
        while coeffs and coeffs[-1] == 0.0:
            coeffs.pop()
        return coeffs


def read_zmx(path: str | os.PathLike) -> dict:
    """Read a Zemax .zmx file and return the prescription dict (SCHEMA.md layout).

    Raises :class:`ZemaxImportError` (file, line number, line) for anything
    that cannot be imported faithfully.
    """
    path = Path(path)
    data = read_lens_file(path, lambda p, message: ZemaxImportError(p, 0, "", message))
    parser = _ZmxParser(path)
    parser.parse(decode_zmx(data))
    return parser.prescription()


def write_toml(d: dict, out_path: str | os.PathLike) -> Path:
    """Write ``d`` as TOML to ``out_path`` atomically (temporary file in the
    same folder, then rename; the folder is created); returns the path."""
    out_path = Path(out_path)
    write_text(out_path, dumps_prescription(d))
    return out_path
