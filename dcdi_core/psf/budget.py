"""The error budget: how far a job's picture may be from the converged one,
and the least PSF work that keeps it there.

A job's budget is a PSNR (dB, peak 1: the paper's scale) of its render
against the render with converged PSFs (:data:`REFERENCE`: 96 x 96 pupil
rays, 31 wavelengths, the source's full field grid) at the job's own size.
Three knobs set nearly all of the PSF work of a ray map or a trace, which
is proportional to rays x wavelengths x fields, and a fourth most of the
blur's:

- ``pupil_samples``: the pupil grid's N (N x N rays over the stop);
- ``n_wavelengths``: the spectral quadrature's nodes over 400-700 nm;
- ``field_step_px``: the fields at most this many image pixels apart
  (``sampling.field_grid``; None: the source's full grid);
- ``coarse_blur``: a depth layer whose kernels hold half their energy
  beyond coarse_blur x f px is blurred at 1/f of the resolution
  (``render.bokeh.BokehOptions``; None: every layer the kernel holds at
  full resolution). A bokeh's knob only;
- ``support_eps``: the energy each kernel's crop may leave out (the FFT
  windows' size; a fast lens's faint halo is wide). A bokeh's knob only.

The time a plan is expected to take is the table's: the reference's PSF
seconds x the PSF work's fraction, plus the blur's seconds, measured with
the cheapest PSFs at each blur knob's level (the blur knobs' savings taken
as independent; the pixels' ratio squared at another pitch); the planner
picks the fastest plan within the budget.

What each knob alone costs in error was measured per lens and per pixel
pitch (``dcdi bench quality LENS``; the tables ship in
``psf/data/quality/LENS.json``, written by ``python -m lab quality-tables``)
on the built-in synthetic scene (textures from 0.8 m to infinity, bright
lights at 6 m) wide open, focused at 2 m. The knobs' errors are independent
and add in squared error (measured: rays 32 + 9 wavelengths + fields 16 px
apart predict 65.9 dB for the Sonnar 50/1.5 at 360 x 240, the render gives
66.4), so :func:`plan` picks the cheapest combination whose summed squared
error, with a safety margin of :data:`MARGIN_DB`, is within the budget.

A table is used for the next measured pitch at least as fine as the job's
(errors grow as the blur spans more pixels: the conservative side). At a
pitch finer than any measured one, each knob's squared error is scaled by
the square of the pitches' ratio (:data:`EXTRAPOLATION_POWER`: an error's
amplitude in proportion to the blur's size in pixels, 6 dB per halving of
the pitch, where the Sonnar 50/1.5 measured 2.8-3.2 dB from 480 to 960
px), up to :data:`MAX_EXTRAPOLATION` times finer. Beyond that, and for a
lens without a table, nothing is planned: the request's own settings, said
in the plan's ``why``.
"""
from __future__ import annotations

import itertools
import json
import math
from dataclasses import dataclass, replace
from pathlib import Path

from ..errors import InputRangeError
from ..io.npzfile import FileCache

QUALITY_DIR = Path(__file__).resolve().parent / "data" / "quality"
FORMAT = "dcdi-quality-table"
FORMAT_VERSION = 1
KNOBS = ("pupil_samples", "n_wavelengths", "field_step_px", "coarse_blur", "support_eps")
# the blur's knobs: their seconds are the blur's, measured with the cheapest PSFs
BLUR_KNOBS = ("coarse_blur", "support_eps")
# the converged render every error is measured against
REFERENCE = {"pupil_samples": 96, "n_wavelengths": 31, "field_step_px": None, "coarse_blur": None,
             "support_eps": 1e-3}
# what a job without a plan uses (the engine's full-quality defaults)
FULL = {"pupil_samples": 64, "n_wavelengths": 31, "field_step_px": None, "coarse_blur": None, "support_eps": 1e-3}
# the planned error is kept this far inside the budget: the table's scene is not the user's
MARGIN_DB = 3.0
# each job's default budget (dB): the viewport preview, everything else
DEFAULT_DB = {"preview": 30.0, "render": 40.0}
# a budget outside this range is refused: below it a picture is garbage, above it nothing is planned
BUDGET_RANGE_DB = (20.0, 80.0)
# rays at most this many pixels apart where they land in the frame's widest blur: a bright light's
# disc drawn by fewer shows the pupil grid (a 40-px disc of 16 x 16 rays at 40 x the background,
# 43 dB on the frame, is visibly a grid of dots), which a frame's PSNR does not weigh
RAY_SPACING_PX = 1.0
# ... for blurs up to the widest kernel drawn at one pitch (a wider layer is drawn coarser)
WIDEST_DRAWN_PX = 129
# a table's pitch serves a job's within this relative rounding
PITCH_RTOL = 0.02
# beyond the finest measured pitch: squared error x (measured pitch / job's pitch) ** this
EXTRAPOLATION_POWER = 2.0
# ... up to this ratio of the pitches (the 1920 x 1080 frame from a 480 x 270 table is 4)
MAX_EXTRAPOLATION = 4.5


def check_budget(value, name: str = "max_error_db") -> float | None:
    """``value`` (dB) as a float in :data:`BUDGET_RANGE_DB`, or None (no plan)."""
    if value is None:
        return None
    lo, hi = BUDGET_RANGE_DB
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    if not ok or not lo <= float(value) <= hi:
        raise InputRangeError(name, value, f"a PSNR in dB from {lo:g} (a rough preview) to {hi:g} "
                                           "(indistinguishable from the converged PSFs), or none")
    return float(value)


@dataclass(frozen=True)
class QualityPlan:
    """The PSF work chosen for a budget: the knobs (None: the source's own
    full grid of fields), the expected PSNR against the converged render
    (None: not measured for this lens or pitch), the budget, the relative
    cost (the reference = 1) and why, one line."""

    pupil_samples: int
    n_wavelengths: int
    field_step_px: float | None
    coarse_blur: float | None
    support_eps: float
    expected_db: float | None
    budget_db: float
    cost: float
    why: str
    planned: bool = True
    seconds: float = math.nan

    def apply(self, settings):
        """``settings`` (``compute.PSFSettings``; None: the defaults) with the
        plan's rays and wavelengths (unchanged where nothing was planned)."""
        if not self.planned:
            return settings
        from .compute import PSFSettings
        return replace(settings or PSFSettings(), pupil_samples=self.pupil_samples, n_wavelengths=self.n_wavelengths)

    def as_dict(self) -> dict:
        if not self.planned:
            return {"budget_db": self.budget_db, "expected_db": None, "plan": self.why}
        return {"budget_db": self.budget_db, "expected_db": self.expected_db, "pupil_samples": self.pupil_samples,
                "n_wavelengths": self.n_wavelengths, "field_step_px": self.field_step_px,
                "coarse_blur": self.coarse_blur, "support_eps": self.support_eps, "relative_cost": round(self.cost, 4),
                "expected_s": None if math.isnan(self.seconds) else round(self.seconds, 3), "plan": self.why}


def table_path(lens_id: str, folder: Path | None = None) -> Path:
    from ..names import check_name
    return (folder or QUALITY_DIR) / f"{check_name(lens_id, 'lens id', error=InputRangeError)}.json"


def _number(v, lo: float = 0.0, *, lo_open: bool = False) -> bool:
    return (isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
            and (v > lo if lo_open else v >= lo))


def _read(path) -> dict:
    """A table file, every field the planner reads checked (ValueError: not a table to plan by)."""
    from ..io.jsontext import loads
    if Path(path).stat().st_size > 1_000_000:
        raise ValueError(f"{path}: larger than any error table")
    t = loads(Path(path).read_text(encoding="utf-8"), path)
    if not isinstance(t, dict) or t.get("format") != FORMAT or t.get("version") != FORMAT_VERSION:
        raise ValueError(f"{path}: not a {FORMAT} version {FORMAT_VERSION} file")
    ok = (isinstance(t.get("lens_fingerprint"), str) and _number(t.get("stop_semi_diameter_mm"), lo_open=True)
          and isinstance(t.get("sizes"), list) and t["sizes"])
    for row in t.get("sizes") or []:
        ok = ok and isinstance(row, dict) and all(_number(row.get(k), lo_open=True) for k in ("rows", "cols",
                                                                                            "pixel_pitch_mm"))
        ok = ok and _number(row.get("reference_s")) and _number(row.get("blur_s", 0.0))
        knobs = row.get("knobs") if isinstance(row, dict) else None
        ok = ok and isinstance(knobs, dict) and all(k in KNOBS for k in knobs)
        for levels in (knobs or {}).values() if ok else ():
            ok = ok and isinstance(levels, list) and all(
                isinstance(x, list) and len(x) == 3 and (_number(x[0], lo_open=True))
                and (x[1] is None or _number(x[1])) and _number(x[2]) for x in levels)
    if not ok:
        raise ValueError(f"{path}: a field is missing or out of range")
    return t


_TABLES = FileCache(_read, 32, "error tables")


def load_table(lens_id: str, folder: Path | None = None) -> dict | None:
    """The lens's measured table (``dcdi bench quality``), or None."""
    p = table_path(lens_id, folder)
    if not p.is_file():
        return None
    try:
        return _TABLES(p)
    except (OSError, ValueError):
        return None


def _opened_fingerprint(lens, stop_mm: float) -> str:
    """The fingerprint of ``lens`` with its stop as the table was measured
    (round, ``stop_mm``): a stopped-down lens shares its table."""
    from ..optics.lens import lens_fingerprint
    i = lens.stop_index
    stop = replace(lens.surfaces[i], semi_diameter_mm=stop_mm, blades=0, blade_rotation_deg=0.0)
    return lens_fingerprint(lens.with_surfaces(lens.surfaces[:i] + (stop,) + lens.surfaces[i + 1:]))


def _row_for(table: dict, pitch_mm: float) -> tuple[dict | None, float]:
    """(the measured pitch that serves ``pitch_mm``: the coarsest at least as
    fine, else the finest within :data:`MAX_EXTRAPOLATION`; the factor its
    squared errors are scaled by), or (None, nan)."""
    rows = [r for r in table["sizes"] if r["pixel_pitch_mm"] <= pitch_mm * (1.0 + PITCH_RTOL)]
    if rows:
        return max(rows, key=lambda r: r["pixel_pitch_mm"]), 1.0
    finest = min(table["sizes"], key=lambda r: r["pixel_pitch_mm"])
    ratio = finest["pixel_pitch_mm"] / pitch_mm
    if ratio > MAX_EXTRAPOLATION:
        return None, math.nan
    return finest, ratio ** EXTRAPOLATION_POWER


def _n_fields(step_px, semi_diagonal_mm: float, pitch_mm: float) -> int:
    from .library import LibraryGrid
    from .sampling import field_grid
    return field_grid(LibraryGrid(), semi_diagonal_mm, pitch_mm, step_px).n_fields


def _cost(rays: int, wavelengths: int, fields: int) -> float:
    """PSF work relative to the reference: rays x wavelengths x fields."""
    from .library import LibraryGrid
    ref = REFERENCE["pupil_samples"] ** 2 * REFERENCE["n_wavelengths"] * LibraryGrid().n_fields
    return rays * rays * wavelengths * fields / ref


def _db(mse: float) -> float:
    return math.inf if mse <= 0 else -10.0 * math.log10(mse)


def full_plan(budget_db: float, why: str, fixed: dict | None = None) -> QualityPlan:
    """No plan: the request's own settings (the full-quality defaults unless
    the user set them); no error is claimed."""
    k = {**FULL, **(fixed or {})}
    return QualityPlan(int(k["pupil_samples"]), int(k["n_wavelengths"]), k["field_step_px"], k["coarse_blur"],
                       float(k["support_eps"]), None, budget_db, math.nan, why, planned=False)


def min_rays(blur_px: float | None) -> int:
    """The fewest pupil rays (N of N x N) that land at most :data:`RAY_SPACING_PX`
    apart across a blur of ``blur_px`` pixels (its diameter; at most
    :data:`WIDEST_DRAWN_PX`); 1 without a blur."""
    if blur_px is None or not blur_px > 0:
        return 1
    return int(math.ceil(min(float(blur_px), WIDEST_DRAWN_PX) / RAY_SPACING_PX))


def plan(lens, pixel_pitch_mm: float, budget_db: float, fixed: dict | None = None, *,
         folder: Path | None = None, blur_px: float | None = None) -> QualityPlan:
    """The cheapest knobs whose expected error keeps the render of ``lens``
    at ``pixel_pitch_mm`` (mm) within ``budget_db`` (dB against the
    converged render), :data:`MARGIN_DB` inside it. ``fixed``: knobs the
    user set (kept as they are; their measured error counts, or, unmeasured,
    none is claimed). ``blur_px``: the frame's widest defocus blur (its
    diameter, px): the rays are at least :func:`min_rays` of it (or the
    reference's), whatever the error table allows."""
    budget = check_budget(budget_db)
    fixed = {k: v for k, v in (fixed or {}).items() if k in KNOBS}
    table = load_table(lens.id, folder)
    if table is None:
        return full_plan(budget, f"no error table of {lens.id} (dcdi bench quality): full quality", fixed)
    if _opened_fingerprint(lens, table["stop_semi_diameter_mm"]) != table["lens_fingerprint"]:
        return full_plan(budget, f"{lens.id} differs from the prescription its error table was measured on: "
                                 "full quality", fixed)
    row, scale = _row_for(table, pixel_pitch_mm)
    if row is None:
        finest = min(r["pixel_pitch_mm"] for r in table["sizes"])
        return full_plan(budget, f"{pixel_pitch_mm * 1000:.4g} um pixels are more than {MAX_EXTRAPOLATION:g} x finer "
                                 f"than the {finest * 1000:.4g} um {lens.id}'s error table was measured at: "
                                 "full quality", fixed)
    # each knob's choices: (value, squared error, blur seconds or None) from its measured levels and the
    # reference (no error); a knob the table lacks (an older table's blur knobs) has the reference only
    blur_full = float(row.get("blur_s", math.nan))
    choices = {}
    for k in KNOBS:
        measured = row["knobs"].get(k, [])
        blur = k in BLUR_KNOBS
        # a level measured without effect (None: a coarse rule that coarsened nothing) is not offered
        levels = [(v, mse * scale, (t if blur else None)) for v, mse, t in measured if mse is not None]
        levels.append((REFERENCE[k], 0.0, blur_full if blur else None))
        if k == "pupil_samples" and k not in fixed:
            floor = min(min_rays(blur_px), REFERENCE[k])
            levels = [x for x in levels if x[0] >= floor]
        if k in fixed:
            hit = [(m, t) for v, m, t in levels if v == fixed[k]]
            levels = [(fixed[k], *(hit[0] if hit else (math.nan, blur_full if blur else None)))]
        choices[k] = levels
    allowed = 10.0 ** (-(budget + MARGIN_DB) / 10.0)
    sd = lens.sensor.semi_diagonal_mm
    # the seconds a plan takes: the reference's PSFs x the work's fraction, plus the blur at its knobs
    # (each blur knob's saving against the full blur, taken as independent)
    full_ok = math.isfinite(blur_full) and blur_full > 0
    psf_s = max(float(row["reference_s"]) - (blur_full if full_ok else 0.0), 0.0)
    pixels = (row["pixel_pitch_mm"] / pixel_pitch_mm) ** 2
    best = None
    for combo in itertools.product(*(choices[k] for k in KNOBS)):
        (r, er, _), (w, ew, _), (f, ef, _), (c, ec, tc), (e, ee, te) = combo
        mse = er + ew + ef + ec + ee
        if not mse <= allowed and not math.isnan(mse):
            continue
        cost = _cost(int(r), int(w), _n_fields(f, sd, pixel_pitch_mm))
        blur = blur_full
        if full_ok:
            blur = blur_full * (tc / blur_full if tc and math.isfinite(tc) else 1.0) \
                * (te / blur_full if te and math.isfinite(te) else 1.0)
        seconds = psf_s * cost + (blur * pixels if full_ok else 0.0)
        key = (seconds, cost)
        if best is None or key < best[0]:
            best = (key, int(r), int(w), f, c, e, mse)
    if best is None:          # even the reference's knobs: the fixed ones alone miss the budget
        return full_plan(budget, f"the knobs given cannot keep {lens.id} within {budget:g} dB "
                                 "(their own error is larger)", fixed)
    (seconds, cost), r, w, f, c, e, mse = best
    expected = None if math.isnan(mse) else min(_db(mse), 99.0)
    size = f"{row['cols']} x {row['rows']}" + ("" if scale == 1.0 else f", its errors x {scale:.3g} at this finer pitch")
    floor = "" if "pupil_samples" in fixed or min_rays(blur_px) <= 16 else \
        f" (at least {min(min_rays(blur_px), REFERENCE['pupil_samples'])}: the widest blur {blur_px:.0f} px)"
    return QualityPlan(r, w, f, c, float(e), expected, budget, cost,
                       f"{r} x {r} rays{floor}, {w} wavelengths, fields "
                       + ("from the source's grid" if f is None else f"{f:g} px apart")
                       + ("" if c is None else f", layers blurring {c:g} x f px and more at 1/f")
                       + ("" if e == REFERENCE["support_eps"] else f", kernels cropped to all but {e:g} of their energy")
                       + (f": about {expected:.0f} dB from the converged render" if expected is not None else "")
                       + f" ({lens.id}'s error table at {row['pixel_pitch_mm'] * 1000:.4g} um, {size}; "
                         f"{cost:.3g} of the reference's PSF work)", seconds=seconds)


__all__ = ["QualityPlan", "plan", "min_rays", "RAY_SPACING_PX", "full_plan", "check_budget", "load_table", "table_path", "KNOBS", "REFERENCE",
           "FULL", "DEFAULT_DB", "MARGIN_DB", "BUDGET_RANGE_DB", "QUALITY_DIR"]
