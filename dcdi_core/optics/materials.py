"""Optical materials: air, catalogue glasses and (nd, vd) model glasses.

Every refractive index here is *relative to air*, the convention of all glass
catalogues (SCHOTT, CDGM, Zemax AGF files): the catalogues measure and fit the
index of the glass against air at standard conditions, so air itself is
exactly 1 and no air-dispersion correction is ever applied.

Wavelengths are in **nanometres** at the API (the dispersion formulas
themselves use micrometres internally, as the catalogues do).

Spectral lines used for the Abbe number and partial dispersion (SCHOTT TIE-29):

* d  = 587.5618 nm (helium)     -> ``nd``
* F  = 486.1327 nm (hydrogen)
* C  = 656.2725 nm (hydrogen)   -> ``vd = (nd - 1) / (nF - nC)``
* g  = 435.8343 nm (mercury)    -> ``P_gF = (ng - nF) / (nF - nC)``

Public API: :class:`Material`, :class:`Air`, :class:`CatalogueGlass`,
:class:`ModelGlass`, :func:`get_material`, :func:`catalogue_names`, ``AIR``.

Catalogue glasses are module-level singletons, so ``get_material("N-BK7") is
get_material("nbk7")``; callers may cache per material by identity.  A name
is never silently replaced by a similar glass: unknown names raise
:class:`~dcdi_core.optics.errors.UnknownGlassError` with suggestions.
"""
from __future__ import annotations

import difflib
import math
from collections.abc import Mapping
from functools import cached_property

import numpy as np

from ..errors import InputRangeError

from .errors import UnknownGlassError

__all__ = [
    "Material",
    "Air",
    "CatalogueGlass",
    "ModelGlass",
    "AIR",
    "get_material",
    "catalogue_names",
    "LAMBDA_D_NM",
    "LAMBDA_F_NM",
    "LAMBDA_C_NM",
    "LAMBDA_G_NM",
]

# Fraunhofer / emission lines, nm (SCHOTT TIE-29 values).
LAMBDA_D_NM = 587.5618
LAMBDA_F_NM = 486.1327
LAMBDA_C_NM = 656.2725
LAMBDA_G_NM = 435.8343


def _wavelengths_nm(wavelength_nm) -> np.ndarray:
    """Convert to a float64 array and reject non-finite or non-positive values.

    Wavelengths outside a glass's catalogue range are *not* rejected: the
    tracer samples 380-780 nm and several catalogues start at 400 nm or so;
    the formulas extrapolate smoothly a few tens of nm past their fit range.
    """
    try:
        wl = np.asarray(wavelength_nm, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputRangeError("wavelength_nm", wavelength_nm, "finite numbers > 0 (nm)") from None
    ok = np.isfinite(wl) & (wl > 0.0)
    if not ok.all():
        bad = wl[~ok].flat[0] if wl.ndim else wl.item()
        raise InputRangeError("wavelength_nm", float(bad), "finite numbers > 0 (nm)")
    return wl


class Material:
    """Base class of every optical medium.

    Subclasses implement :meth:`_index` (vectorised, wavelengths in nm,
    already validated).  ``name`` identifies the medium in error messages and
    prescriptions.
    """

    name: str = "material"

    def refractive_index(self, wavelength_nm) -> np.ndarray:
        """Refractive index (relative to air) at ``wavelength_nm`` (nm).

        Accepts a scalar or any array shape; returns float64 of the same
        shape (a 0-d array for a scalar).  Raises ``InputRangeError`` for
        non-finite or non-positive wavelengths, and for wavelengths so far
        outside the formula's domain that it has no real index (n^2 <= 0,
        e.g. on a Sellmeier pole deep in the UV) rather than returning NaN.
        """
        wl = _wavelengths_nm(wavelength_nm)
        n = self._index(wl)
        if not np.all(np.isfinite(n)):
            bad = wl[~np.isfinite(n)].flat[0] if wl.ndim else wl.item()
            raise InputRangeError(
                "wavelength_nm", float(bad),
                f"wavelengths where the dispersion formula of {self.name!r} is defined "
                f"(catalogue range {self.wavelength_range_nm[0]:g}-{self.wavelength_range_nm[1]:g} nm)")
        return n

    def _index(self, wl_nm: np.ndarray) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError

    #: Wavelength range (nm) over which the data is documented to be valid.
    wavelength_range_nm: tuple = (0.0, math.inf)

    @cached_property
    def nd(self) -> float:
        """Index at the helium d line, 587.5618 nm."""
        return float(self.refractive_index(LAMBDA_D_NM))

    @cached_property
    def vd(self) -> float:
        """Abbe number (nd - 1) / (nF - nC) with F = 486.1327 nm, C = 656.2725 nm."""
        n = self.refractive_index(np.array([LAMBDA_F_NM, LAMBDA_C_NM]))
        return float((self.nd - 1.0) / (n[0] - n[1]))

    @cached_property
    def pgf(self) -> float:
        """Relative partial dispersion P_g,F = (ng - nF) / (nF - nC), g = 435.8343 nm."""
        n = self.refractive_index(np.array([LAMBDA_G_NM, LAMBDA_F_NM, LAMBDA_C_NM]))
        return float((n[0] - n[1]) / (n[1] - n[2]))

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.name}>"


class Air(Material):
    """Air, n = 1 exactly at every wavelength.

    Catalogue indices are relative to air (not vacuum), so in that convention
    the index of air is exactly 1 and air has no dispersion: ``vd`` is
    infinite and ``pgf`` undefined (NaN).
    """

    name = "air"

    def _index(self, wl_nm: np.ndarray) -> np.ndarray:
        return np.ones_like(wl_nm, dtype=np.float64)

    @cached_property
    def vd(self) -> float:
        """Infinite: air has no dispersion in the relative-to-air convention."""
        return math.inf

    @cached_property
    def pgf(self) -> float:
        """Undefined for a non-dispersive medium (NaN)."""
        return math.nan


class CatalogueGlass(Material):
    """A glass defined by a manufacturer's dispersion formula.

    Parameters
    ----------
    name : catalogue name, e.g. ``"N-BK7"``.
    formula : ``"sellmeier"`` -- n^2 - 1 = sum_i B_i L^2 / (L^2 - C_i), with
        ``coefficients = (B1, B2, B3, C1, C2, C3)``, C_i in um^2 (the SCHOTT
        data-sheet order; Zemax AGF formula 2 "Sellmeier 1" stores them
        interleaved as K1 L1 K2 L2 K3 L3);
        ``"schott"`` -- n^2 = A0 + A1 L^2 + A2 L^-2 + A3 L^-4 + A4 L^-6 + A5 L^-8,
        ``coefficients = (A0, ..., A5)`` (Zemax AGF formula 1).
        L is the wavelength in micrometres.
    catalogue_nd, catalogue_vd : nd and vd as printed by the catalogue.
    catalogue : short catalogue name and version.
    source : full citation of where the coefficients were taken from.
    wavelength_range_nm : (min, max) validity range stated by the catalogue.
        Informational only: evaluation outside it is allowed.
    note : anything a user should know (status, equivalences).
    """

    _FORMULAS = ("sellmeier", "schott")

    def __init__(self, name, formula, coefficients, catalogue_nd, catalogue_vd,
                 catalogue, source, wavelength_range_nm, note=""):
        if formula not in self._FORMULAS:
            raise ValueError(f"glass {name!r}: formula must be one of {self._FORMULAS}, got {formula!r}")
        coefficients = tuple(float(c) for c in coefficients)
        if len(coefficients) != 6:
            raise ValueError(f"glass {name!r}: {formula} formula needs 6 coefficients, got {len(coefficients)}")
        self.name = str(name)
        self.formula = formula
        self.coefficients = coefficients
        self.catalogue_nd = float(catalogue_nd)
        self.catalogue_vd = float(catalogue_vd)
        self.catalogue = str(catalogue)
        self.source = str(source)
        lo, hi = wavelength_range_nm
        self.wavelength_range_nm = (float(lo), float(hi))
        self.note = str(note)
        c = np.asarray(coefficients, dtype=np.float64)
        if formula == "sellmeier":
            self._b, self._c = c[:3], c[3:]
        else:
            self._a = c

    def _index(self, wl_nm: np.ndarray) -> np.ndarray:
        l2 = (wl_nm * 1e-3) ** 2  # um^2, the catalogues' unit
        if self.formula == "sellmeier":
            b, c = self._b, self._c
            # Three resonance terms written out: no (..., 3) temporary for large ray batches.
            n2 = 1.0 + b[0] * l2 / (l2 - c[0]) + b[1] * l2 / (l2 - c[1]) + b[2] * l2 / (l2 - c[2])
        else:
            a = self._a
            inv = 1.0 / l2
            # Horner in 1/L^2 for the four negative powers.
            n2 = a[0] + a[1] * l2 + inv * (a[2] + inv * (a[3] + inv * (a[4] + inv * a[5])))
        with np.errstate(invalid="ignore"):
            # n^2 <= 0 only happens far outside the fit range; it becomes NaN
            # here and refractive_index() turns that into an InputRangeError.
            return np.sqrt(np.where(n2 > 0.0, n2, np.nan))


class ModelGlass(Material):
    """A fictitious glass defined only by (nd, vd), on the SCHOTT normal line.

    Dispersion model: Buchdahl's chromatic coordinate (H. A. Buchdahl,
    *Optical Aberration Coefficients*, 1954; P. N. Robb and R. I. Mercado,
    "Calculation of refractive indices using Buchdahl's chromatic
    coordinate", Appl. Opt. 22, 1198 (1983))::

        dl    = (lambda - lambda_d) / 1000          (um)
        omega = dl / (1 + 2.5 dl)
        n     = nd + v1 omega + v2 omega^2

    ``v1`` and ``v2`` are fixed by two conditions:

    1. principal dispersion: nF - nC = (nd - 1) / vd  (reproduces vd);
    2. relative partial dispersion on the SCHOTT "normal line"
       (SCHOTT TIE-29, the line through K7 and F2):
       P_gF = (ng - nF) / (nF - nC) = 0.6438 - 0.001682 vd.

    n(lambda_d) = nd exactly (omega = 0 there), and vd and P_gF are reproduced
    to rounding error.  Robb & Mercado found the quadratic model good to
    about 1e-4 in the visible for real glasses; it is meant for 365-1014 nm
    and diverges at lambda = lambda_d - 400 nm (about 188 nm).
    """

    _LAMBDA_RANGE_NM = (365.0, 1014.0)

    def __init__(self, nd, vd, name=None):
        self._nd_in = _model_number("nd", nd, lo=1.0, allowed="a finite number > 1")
        self._vd_in = _model_number("vd", vd, lo=0.0, allowed="a finite number > 0")
        self.name = name if name is not None else f"model(nd={self._nd_in:.6g}, vd={self._vd_in:.6g})"
        self.wavelength_range_nm = self._LAMBDA_RANGE_NM
        self.pgf_normal_line = 0.6438 - 0.001682 * self._vd_in
        w_f, w_c, w_g = (_buchdahl_omega(np.float64(x)) for x in (LAMBDA_F_NM, LAMBDA_C_NM, LAMBDA_G_NM))
        dn_fc = (self._nd_in - 1.0) / self._vd_in  # nF - nC
        dn_gf = self.pgf_normal_line * dn_fc       # ng - nF
        # Solve [[wF-wC, wF^2-wC^2], [wg-wF, wg^2-wF^2]] @ (v1, v2) = (dn_fc, dn_gf).
        a11, a12 = w_f - w_c, w_f * w_f - w_c * w_c
        a21, a22 = w_g - w_f, w_g * w_g - w_f * w_f
        det = a11 * a22 - a12 * a21
        self.v1 = float((dn_fc * a22 - a12 * dn_gf) / det)
        self.v2 = float((a11 * dn_gf - a21 * dn_fc) / det)

    def _index(self, wl_nm: np.ndarray) -> np.ndarray:
        w = _buchdahl_omega(wl_nm)
        return self._nd_in + w * (self.v1 + self.v2 * w)

    def __eq__(self, other):
        if not isinstance(other, ModelGlass):
            return NotImplemented
        return (self._nd_in, self._vd_in) == (other._nd_in, other._vd_in)

    def __hash__(self):
        return hash((ModelGlass, self._nd_in, self._vd_in))


def _buchdahl_omega(wl_nm):
    # Subtract in nm so that omega(lambda_d) is exactly 0 (no 587.5618/1000
    # rounding), hence n(lambda_d) == nd bit for bit.
    dl = (wl_nm - LAMBDA_D_NM) * 1e-3
    with np.errstate(divide="ignore", invalid="ignore"):
        return dl / (1.0 + 2.5 * dl)


def _model_number(field, value, lo, allowed):
    # bool is an int subclass; "nd = true" in a TOML file is a typo, not 1.0.
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise InputRangeError(f"model glass {field}", value, allowed)
    v = float(value)
    if not math.isfinite(v) or v <= lo:
        raise InputRangeError(f"model glass {field}", value, allowed)
    return v


# ---------------------------------------------------------------------------
# Catalogue data.
#
# Coefficients were copied programmatically from the files named in each
# source string (and cross-checked against a second copy where one exists);
# each reproduces its catalogue nd to < 4e-6 and vd to < 0.005, which
# tests/optics/test_materials.py re-checks for every glass.

_SCHOTT_2018 = (
    "SCHOTT optical glass catalogue, status 2018-06-01: Zemax AGF 'SCHOTT. preferred. inquiry and "
    "obsolete data since 2006. status as of 1 June 2018' (schott-1.agf as shipped in the KrakenOS "
    "1.0.0.24 package, Cat/), identical to the SCHOTT data table 2018-06-01 (SCHOTT.xls in the "
    "opticalglass 1.1.1 package) and to refractiveindex.info's SCHOTT Zemax catalog 2017-01-20b")
_SCHOTT_2008_OBSOLETE = (
    "Zemax SCHOTT.AGF 'SCHOTT Preferred optical glasses. 26th February 2008 plus B270 and obsolete "
    "glasses', obsolete section (status 2); file as shipped in the KrakenOS 1.0.0.24 package, "
    "Cat/SCHOTT.AGF")
_CDGM_2022 = (
    "CDGM Zemax catalogue 2022-06 (CDGM-ZEMAX202206new.AGF), as transcribed in the "
    "refractiveindex.info database, database/data-nk/glass/cdgm/")
_ZEMAX_MISC = (
    "Zemax MISC.AGF (misc.agf as shipped in the KrakenOS 1.0.0.24 package, Cat/)")


def _sellmeier_agf(k1, l1, k2, l2, k3, l3):
    """Reorder Zemax AGF 'Sellmeier 1' CD coefficients (K1 L1 K2 L2 K3 L3) to (B1 B2 B3 C1 C2 C3)."""
    return (k1, k2, k3, l1, l2, l3)


_S18, _OBS, _CDGM, _MISC = "SCHOTT 2018-06-01", "SCHOTT (obsolete; Zemax SCHOTT.AGF 2008)", "CDGM 2022-06", "Zemax MISC.AGF"

# (name, formula, coefficients, catalogue nd, catalogue vd, catalogue, source, range nm, note)
_CATALOGUE = (
    # --- SCHOTT, current (2018-06-01) ----------------------------------------
    # Sellmeier coefficients (B1, B2, B3, C1, C2, C3), C in um^2.
    ("N-BK7", "sellmeier", (1.03961212, 0.231792344, 1.01046945, 0.00600069867, 0.0200179144, 103.560653),
     1.51680, 64.17, _S18, _SCHOTT_2018, (300, 2500), ""),
    ("N-K5", "sellmeier", (1.08511833, 0.199562005, 0.930511663, 0.00661099503, 0.024110866, 111.982777),
     1.52249, 59.48, _S18, _SCHOTT_2018, (310, 2500), ""),
    ("N-FK5", "sellmeier", (0.844309338, 0.344147824, 0.910790213, 0.00475111955, 0.0149814849, 97.8600293),
     1.48749, 70.41, _S18, _SCHOTT_2018, (260, 2500), ""),
    ("N-FK51A", "sellmeier", (0.971247817, 0.216901417, 0.904651666, 0.00472301995, 0.0153575612, 168.68133),
     1.48656, 84.47, _S18, _SCHOTT_2018, (290, 2500), ""),
    ("N-PSK3", "sellmeier", (0.88727211, 0.489592425, 1.04865296, 0.00469824067, 0.0161818463, 104.374975),
     1.55232, 63.46, _S18, _SCHOTT_2018, (300, 2500), "lead-free successor of PSK3"),
    ("N-SK2", "sellmeier", (1.28189012, 0.257738258, 0.96818604, 0.0072719164, 0.0242823527, 110.377773),
     1.60738, 56.65, _S18, _SCHOTT_2018, (310, 2500), ""),
    ("N-SK16", "sellmeier", (1.34317774, 0.241144399, 0.994317969, 0.00704687339, 0.0229005, 92.7508526),
     1.62041, 60.32, _S18, _SCHOTT_2018, (310, 2500), ""),
    ("N-BAK4", "sellmeier", (1.28834642, 0.132817724, 0.945395373, 0.00779980626, 0.0315631177, 105.965875),
     1.56883, 55.98, _S18, _SCHOTT_2018, (334, 2500), ""),
    ("N-BAF10", "sellmeier", (1.5851495, 0.143559385, 1.08521269, 0.00926681282, 0.0424489805, 105.613573),
     1.67003, 47.11, _S18, _SCHOTT_2018, (350, 2500), ""),
    ("N-LAK9", "sellmeier", (1.46231905, 0.344399589, 1.15508372, 0.00724270156, 0.0243353131, 85.4686868),
     1.69100, 54.71, _S18, _SCHOTT_2018, (300, 2500), ""),
    ("N-LAF2", "sellmeier", (1.80984227, 0.15729555, 1.0930037, 0.0101711622, 0.0442431765, 100.687748),
     1.74397, 44.85, _S18, _SCHOTT_2018, (350, 2500), "lead-free successor of LAF2 (different dispersion)"),
    ("N-LASF9", "sellmeier", (2.00029547, 0.298926886, 1.80691843, 0.0121426017, 0.0538736236, 156.530829),
     1.85025, 32.17, _S18, _SCHOTT_2018, (365, 2500), ""),
    ("N-F2", "sellmeier", (1.39757037, 0.159201403, 1.2686543, 0.00995906143, 0.0546931752, 119.248346),
     1.62005, 36.43, _S18, _SCHOTT_2018, (365, 2500), ""),
    ("N-SF1", "sellmeier", (1.60865158, 0.237725916, 1.51530653, 0.0119654879, 0.0590589722, 135.521676),
     1.71736, 29.62, _S18, _SCHOTT_2018, (370, 2500), "lead-free counterpart of SF1; not the same glass"),
    ("N-SF2", "sellmeier", (1.47343127, 0.163681849, 1.36920899, 0.0109019098, 0.0585683687, 127.404933),
     1.64769, 33.82, _S18, _SCHOTT_2018, (365, 2500), ""),
    ("N-SF5", "sellmeier", (1.52481889, 0.187085527, 1.42729015, 0.011254756, 0.0588995392, 129.141675),
     1.67271, 32.25, _S18, _SCHOTT_2018, (370, 2500), ""),
    ("N-SF6", "sellmeier", (1.77931763, 0.338149866, 2.08734474, 0.0133714182, 0.0617533621, 174.01759),
     1.80518, 25.36, _S18, _SCHOTT_2018, (370, 2500), ""),
    ("N-SF10", "sellmeier", (1.62153902, 0.256287842, 1.64447552, 0.0122241457, 0.0595736775, 147.468793),
     1.72828, 28.53, _S18, _SCHOTT_2018, (380, 2500), ""),
    ("N-SF11", "sellmeier", (1.73759695, 0.313747346, 1.89878101, 0.013188707, 0.0623068142, 155.23629),
     1.78472, 25.68, _S18, _SCHOTT_2018, (370, 2500), ""),
    # Lead-containing classics that SCHOTT still lists (status 'standard' in 2018).
    ("F2", "sellmeier", (1.34533359, 0.209073176, 0.937357162, 0.00997743871, 0.0470450767, 111.886764),
     1.62004, 36.37, _S18, _SCHOTT_2018, (320, 2500), "lead-containing"),
    ("SF1", "sellmeier", (1.55912923, 0.284246288, 0.968842926, 0.0121481001, 0.0534549042, 112.174809),
     1.71736, 29.51, _S18, _SCHOTT_2018, (350, 2500),
     "lead-containing; still in the 2018 SCHOTT catalogue (not discontinued); differs from N-SF1"),
    ("SF2", "sellmeier", (1.40301821, 0.231767504, 0.939056586, 0.0105795466, 0.0493226978, 112.405955),
     1.64769, 33.85, _S18, _SCHOTT_2018, (350, 2500), "lead-containing"),
    ("SF5", "sellmeier", (1.46141885, 0.247713019, 0.949995832, 0.0111826126, 0.0508594669, 112.041888),
     1.67270, 32.21, _S18, _SCHOTT_2018, (350, 2500), "lead-containing"),
    ("SF6", "sellmeier", (1.72448482, 0.390104889, 1.04572858, 0.0134871947, 0.0569318095, 118.557185),
     1.80518, 25.43, _S18, _SCHOTT_2018, (365, 2500), "lead-containing"),
    ("SF10", "sellmeier", (1.61625977, 0.259229334, 1.07762317, 0.0127534559, 0.0581983954, 116.60768),
     1.72825, 28.41, _S18, _SCHOTT_2018, (380, 2500), "lead-containing"),
    ("SF11", "sellmeier", (1.73848403, 0.311168974, 1.17490871, 0.0136068604, 0.0615960463, 121.922711),
     1.78472, 25.76, _S18, _SCHOTT_2018, (390, 2500), "lead-containing"),
    # --- SCHOTT, discontinued (Zemax 2008 obsolete section) --------------------
    # nd/vd are the values in the AGF NM lines (glass codes 744447 and 552635);
    # AGF status 2 = obsolete.
    ("LAF2", "sellmeier", _sellmeier_agf(1.75302282, 0.00957243296, 0.213978997, 0.0402787459, 1.09939444, 102.533259),
     1.744002, 44.719972, _OBS, _SCHOTT_2008_OBSOLETE, (334, 2325),
     "discontinued lead-containing lanthanum flint (glass code 744447); NOT N-LAF2 (744449)"),
    ("PSK3", "sellmeier", _sellmeier_agf(0.88727211, 0.00469824067, 0.489592425, 0.0161818463, 1.04865296, 104.374975),
     1.552322, 63.456253, _OBS, _SCHOTT_2008_OBSOLETE, (310, 2325),
     "discontinued; the AGF entry carries the N-PSK3 coefficients. Robb & Mercado, Appl. Opt. 22, 1198 "
     "(1983), Table V (SCHOTT 1980 catalogue, Buchdahl fit) agrees with it to 1.1e-5 over 400-700 nm"),
    # --- CDGM (2022-06) -----------------------------------------------------
    ("H-K9L", "sellmeier", (0.614555251, 0.656775017, 1.02699346, 0.0145987884, 0.00287769588, 107.653051),
     1.516800, 64.198732, _CDGM, _CDGM_2022, (302, 2325),
     "CDGM equivalent of N-BK7 (code 517642); differs from N-BK7 by < 2e-5 in 380-780 nm"),
    ("H-ZF52", "sellmeier", (0.409982615, 2.37517176, 1.83913582, 0.0621421199, 185.055134, 0.0136093459),
     1.846660, 23.784497, _CDGM, _CDGM_2022, (404.7, 2325), ""),
    ("H-ZF52A", "schott", (3.2506862, -0.0133942217, 0.0483625913, 0.00314442751, -0.000197073674, 3.47645679e-05),
     1.846670, 23.791236, _CDGM, _CDGM_2022, (404.7, 1014), "CDGM gives this glass in the Schott formula"),
    # --- Crystals and plastics ----------------------------------------------
    # Fused silica: I. H. Malitson, "Interspecimen comparison of the refractive
    # index of fused silica", J. Opt. Soc. Am. 55, 1205 (1965); 20 C.
    ("F_SILICA", "sellmeier", (0.6961663, 0.4079426, 0.8974794, 0.0684043 ** 2, 0.1162414 ** 2, 9.896161 ** 2),
     1.458464, 67.821433, _MISC,
     "I. H. Malitson, J. Opt. Soc. Am. 55, 1205-1208 (1965) (coefficients); nd/vd as listed for "
     "F_SILICA in " + _ZEMAX_MISC, (210, 3710), "fused silica, Malitson 1965"),
    # CaF2: I. H. Malitson, Appl. Opt. 2, 1103 (1963); 24 C.
    ("CAF2", "sellmeier", (0.5675888, 0.4710914, 3.8484723, 0.050263605 ** 2, 0.1003909 ** 2, 34.649040 ** 2),
     1.433849, 94.995854, _MISC,
     "I. H. Malitson, Appl. Opt. 2, 1103-1107 (1963) (coefficients); nd/vd as listed for CAF2 in "
     + _ZEMAX_MISC + " (GC: Handbook of Optics Vol. II)", (230, 9700), "calcium fluoride crystal"),
    ("PMMA", "schott", (2.1864582, -0.00024475348, 0.014155787, -0.00044329781, 7.7664259e-05, -2.9936382e-06),
     1.491756, 57.440791, _MISC, _ZEMAX_MISC + ", entry PMMA (GC: Handbook of Optics Vol. II)",
     (365, 1060), "acrylic"),
    ("POLYCARB", "schott", (2.42838566, -3.86116645e-05, 0.0287574474, -0.000197897366, 0.000148358968, 1.38651935e-06),
     1.585470, 29.909185, _MISC, _ZEMAX_MISC + ", entry POLYCARB (GC: Handbook of Optics Vol. II)",
     (365, 1014), "polycarbonate"),
)

_GLASSES = {rec[0]: CatalogueGlass(*rec) for rec in _CATALOGUE}

# Exact (case-insensitive) names.
_BY_NAME = {name.upper(): g for name, g in _GLASSES.items()}
# Hyphen-less spellings ("NBK7", "HK9L"); only used when the request has no
# hyphen at all, so "NBK-7" is an error rather than a guess.
_BY_DEHYPHENATED = {}
for _name, _g in _GLASSES.items():
    _key = _name.upper().replace("-", "")
    if _key in _BY_NAME and _BY_NAME[_key] is not _g:
        # e.g. if both "SF1" and a glass literally named "S-F1" existed: the
        # plain name must win and the alias must not exist.
        continue
    if _key in _BY_DEHYPHENATED and _BY_DEHYPHENATED[_key] is not _g:
        raise RuntimeError(f"ambiguous hyphen-less glass name {_key!r}")
    _BY_DEHYPHENATED[_key] = _g
# Descriptive synonyms for the same material (never a different glass).
_SYNONYMS = {
    "FUSED SILICA": "F_SILICA",
    "FUSED_SILICA": "F_SILICA",
    "FUSED-SILICA": "F_SILICA",
    "FUSEDSILICA": "F_SILICA",
    "POLYCARBONATE": "POLYCARB",
}
del _name, _g, _key

AIR = Air()


def catalogue_names() -> list[str]:
    """Names of all catalogue glasses (canonical spelling), sorted."""
    return sorted(_GLASSES)


def _lookup(name: str) -> Material:
    key = name.strip().upper()
    if key == "AIR":
        return AIR
    if key in _BY_NAME:
        return _BY_NAME[key]
    if key in _SYNONYMS:
        return _GLASSES[_SYNONYMS[key]]
    if "-" not in key and key in _BY_DEHYPHENATED:
        return _BY_DEHYPHENATED[key]
    raise UnknownGlassError(name, _suggest(key))


def _suggest(key: str, n: int = 3) -> list[str]:
    """Close catalogue names, comparing both as typed and with hyphens removed."""
    names = list(_GLASSES)
    plain = {nm.upper().replace("-", ""): nm for nm in names}
    found = []
    for m in difflib.get_close_matches(key.replace("-", ""), list(plain), n=n, cutoff=0.6):
        found.append(plain[m])
    upper = {nm.upper(): nm for nm in names}
    for m in difflib.get_close_matches(key, list(upper), n=n, cutoff=0.6):
        found.append(upper[m])
    out = []
    for nm in found:
        if nm not in out:
            out.append(nm)
    return out[:n]


def get_material(spec) -> Material:
    """Resolve a prescription's material spec.

    ``spec`` may be

    * ``"air"`` (any case) -> :data:`AIR`;
    * a catalogue name, case-insensitive (``"N-BK7"``, ``"n-bk7"``), also
      without its hyphens (``"NBK7"``, ``"HK9L"``); a name that matches no
      glass raises :class:`UnknownGlassError` with close suggestions (a
      similar glass is never substituted);
    * a mapping with exactly the keys ``nd`` and ``vd`` -> :class:`ModelGlass`
      (``InputRangeError``, a ``ValueError``, for missing/extra keys or
      values out of range);
    * a :class:`Material` instance, returned as is.
    """
    if isinstance(spec, Material):
        return spec
    if isinstance(spec, str):
        return _lookup(spec)
    if isinstance(spec, Mapping):
        keys = set(spec)
        if keys != {"nd", "vd"}:
            missing = sorted({"nd", "vd"} - keys)
            extra = sorted((str(k) for k in keys - {"nd", "vd"}))
            why = []
            if missing:
                why.append("missing " + ", ".join(repr(k) for k in missing))
            if extra:
                why.append("unexpected " + ", ".join(repr(k) for k in extra))
            raise InputRangeError("model glass keys", sorted(str(k) for k in keys),
                                  "exactly 'nd' (> 1) and 'vd' (> 0) (" + "; ".join(why) + ")")
        return ModelGlass(spec["nd"], spec["vd"])
    raise TypeError(
        f"material must be 'air', a catalogue glass name, {{nd = ..., vd = ...}} or a Material, "
        f"got {type(spec).__name__}: {spec!r}")
