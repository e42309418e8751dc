"""Lens reports: first-order data, real-ray checks and the stated values side by side."""
from __future__ import annotations

import math


from .analysis import best_focus_depth_m, distortion, real_field_angle_deg, working_f_number
from .lens import Lens
from .paraxial import first_order


def _finite(x):
    """JSON-safe number: inf -> the string "inf" (JSON has no infinity)."""
    if isinstance(x, float) and math.isinf(x):
        return "inf" if x > 0 else "-inf"
    return x


def lens_info(lens: Lens, wavelength_nm: float | None = None, *, real_rays: bool | str = True) -> dict:
    """Everything `dcdi lens info` prints, as a JSON-ready dict (mm, m, degrees, nm).
    ``real_rays``: True, the real-ray figures too (about 1 s: the best
    focus, the working F-number); 'field', the fields of view alone (what a
    panel shows, ~0.02 s); False, first order only."""
    fo = first_order(lens, wavelength_nm)
    sd = lens.sensor.semi_diagonal_mm
    info = {
        "id": lens.id,
        "name": lens.name,
        "file": lens.path,
        "wavelength_nm": fo.wavelength_nm,
        "effective_focal_length_mm": fo.effective_focal_length_mm,
        "back_focal_length_mm": fo.back_focal_length_mm,
        "front_focal_length_mm": fo.front_focal_length_mm,
        "f_number": fo.f_number,
        "entrance_pupil_position_mm": fo.entrance_pupil_position_mm,
        "entrance_pupil_diameter_mm": fo.entrance_pupil_diameter_mm,
        "exit_pupil_position_mm": fo.exit_pupil_position_mm,
        "exit_pupil_diameter_mm": fo.exit_pupil_diameter_mm,
        "sensor_distance_mm": fo.sensor_distance_mm,
        "sensor_defocus_mm": fo.sensor_distance_mm - fo.back_focal_length_mm,
        "total_track_mm": lens.total_track_mm,
        "in_focus_object_distance_m": _finite(fo.in_focus_object_distance_m),
        "in_focus_is_virtual": bool(fo.in_focus_is_virtual),
        "sensor_semi_diagonal_mm": sd,
        "pixel_pitch_mm": lens.sensor.pixel_pitch_mm or (
            2 * sd / math.hypot(*lens.sensor.resolution_px) if lens.sensor.resolution_px else None),
        "resolution_px": list(lens.sensor.resolution_px) if lens.sensor.resolution_px else None,
        "paraxial_half_field_of_view_deg": math.degrees(math.atan(sd / fo.effective_focal_length_mm)),
        "stated": dict(lens.stated),
    }
    if real_rays:
        # a figure the real rays cannot give (no chief ray reaches the field, no
        # ray through the stop) is None (null; left out of the table), never a sentinel
        half = _figure(real_field_angle_deg(lens, [1.0], wavelength_nm)[0])
        info["half_field_of_view_deg"] = half
        info["field_of_view_deg"] = None if half is None else 2 * half
        if lens.sensor.resolution_px:
            rows, cols = lens.sensor.resolution_px
            diag = math.hypot(rows, cols)
            v, h = (_figure(a) for a in real_field_angle_deg(lens, [rows / diag, cols / diag], wavelength_nm))
            info["vertical_field_of_view_deg"] = None if v is None else 2 * v
            info["horizontal_field_of_view_deg"] = None if h is None else 2 * h
        if real_rays == "field":
            return info
        info["distortion_at_field_1"] = (float(distortion(lens, [half], wavelength_nm)[0])
                                         if half is not None and half > 0 else None)
        info["working_f_number"] = _figure(working_f_number(lens, wavelength_nm))
        info["best_focus_object_distance_m"] = _finite(best_focus_depth_m(lens, wavelength_nm))
    return info


def _figure(v) -> float | None:
    """A real-ray figure, or None where the rays gave none (a negative angle, inf or NaN)."""
    v = float(v)
    return v if math.isfinite(v) and v >= 0 else None


def format_info(info: dict) -> str:
    """Human-readable table of :func:`lens_info`."""
    stated = info.get("stated", {})
    rows = [
        ("effective focal length", "effective_focal_length_mm", "mm", "effective_focal_length_mm"),
        ("back focal length (last vertex)", "back_focal_length_mm", "mm", None),
        ("sensor distance (last vertex)", "sensor_distance_mm", "mm", None),
        ("sensor - paraxial focus", "sensor_defocus_mm", "mm", None),
        ("F-number (paraxial)", "f_number", "", "f_number"),
        ("F-number (real, working)", "working_f_number", "", None),
        ("entrance pupil position", "entrance_pupil_position_mm", "mm from 1st vertex", None),
        ("entrance pupil diameter", "entrance_pupil_diameter_mm", "mm", None),
        ("exit pupil position", "exit_pupil_position_mm", "mm from last vertex", None),
        ("exit pupil diameter", "exit_pupil_diameter_mm", "mm", None),
        ("in-focus object distance", "in_focus_object_distance_m", "m (negative: virtual)", None),
        ("best-focus object distance (real, on axis)", "best_focus_object_distance_m", "m", None),
        ("sensor semi-diagonal", "sensor_semi_diagonal_mm", "mm", None),
        ("field of view (diagonal, real)", "field_of_view_deg", "deg", None),
        ("field of view (vertical, real)", "vertical_field_of_view_deg", "deg", None),
        ("field of view (horizontal, real)", "horizontal_field_of_view_deg", "deg", None),
        ("distortion at field 1", "distortion_at_field_1", "", None),
    ]
    out = [f"{info['id']}: {info['name']}  (at {info['wavelength_nm']:.2f} nm)"]
    for label, key, unit, skey in rows:
        if key not in info or info[key] is None:
            continue
        v = info[key]
        val = f"{v:.6g}" if isinstance(v, float) else str(v)
        line = f"  {label:<44} {val:>12} {unit}"
        if skey and skey in stated:
            line += f"   [stated: {stated[skey]}]"
        out.append(line)
    # stated values that measure another quantity than any computed row: on lines of their own
    for key, label, unit in (("image_semi_diameter_mm", "stated image semi-diameter (source's table)", "mm"),
                             ("field_of_view_deg", "stated field of view (source's table)", "deg")):
        if key in stated:
            note = stated.get("field_of_view_note" if key == "field_of_view_deg" else "sensor_note")
            out.append(f"  {label:<44} {stated[key]!s:>12} {unit}"
                       + (f"   ({note})" if note else "   (as the source gives it, a diagonal, vertical or "
                          "horizontal angle: compare with those above)" if key == "field_of_view_deg" else ""))
    if info.get("in_focus_is_virtual"):
        out.append("  note: the in-focus object is VIRTUAL: the sensor sits in front of the paraxial "
                   "focus, so no real object depth is in paraxial focus.")
    return "\n".join(out)
