"""What a capture file remembers of how it was made, and how a job reads it
back as its defaults (``io.capture_record``'s record)."""
from __future__ import annotations


def simulated_record(lens, geometry, *, focus_distance_m, psf_source: str, noise: dict | None = None,
                     seed: int | None = None, distortion: bool = True, extra: dict | None = None):
    """The record of a capture simulated through ``lens`` on ``geometry``
    (the sensor's frame): lens and prescription, pixel pitch (mm), optical
    axis (row, col px), image size, focus (m, None: as prescribed), PSF
    source ('basis', 'cache', 'trace', ...), noise model (``noise``: the
    simulation's full well and read noise, electrons, with its ``seed``;
    None: noiseless), distortion applied or not."""
    from ..io.capture_record import CaptureRecord, prescription_sha256
    if noise:
        noise = {"full_well_electrons": float(noise["full_well_electrons"]),
                 "read_noise_electrons": float(noise["read_noise_electrons"]), "seed": int(seed)}
    return CaptureRecord(kind="simulated", lens_id=lens.id, prescription_sha256=prescription_sha256(lens),
                         pixel_pitch_mm=float(geometry.pixel_pitch_mm),
                         axis_px=(float(geometry.center_px[0]), float(geometry.center_px[1])),
                         image_size=(int(geometry.height), int(geometry.width)),
                         focus_distance_m=None if focus_distance_m is None else float(focus_distance_m),
                         psf_source=psf_source, noise=noise or None, distortion_applied=bool(distortion),
                         extra=dict(extra or {}))


def recorded_defaults(render, lens, record, shape, image_name: str, *, focus: bool = True,
                      lens_bound: bool = True):
    """(``render`` with the capture's recorded geometry as its defaults,
    notes): the pixel pitch and optical axis where the request gives neither
    a pitch nor a sensor size, the sensor's focus where the PSF settings
    leave it unset; an explicit value wins. A record made for another image
    size (the file was resized or cropped since) is ignored, with a note.
    ``render`` None: the lens's defaults. ``focus`` False: leave the focus
    alone (a bokeh's focus is its own).

    ``lens_bound``: the job's lens is the capture's (correct, depth, the
    camera of dof), so a ``lens`` other than the recorded one is refused
    naming both. False (a bokeh: its lens is the one whose depth of field is
    wanted): another lens is the user's choice, and the record, which
    describes the capture's lens's sensor, is not used (a note says so).

    A value taken from the record that the job cannot use (an axis outside
    the image, a focus the lens cannot reach) is refused naming the file and
    the record's field, never an option the user did not give."""
    from dataclasses import replace

    from ..errors import InputRangeError
    from ..render.request import RenderRequest
    if record is None or lens is None:
        return render, []
    if record.lens_id is not None and record.lens_id != lens.id:
        if not lens_bound:
            return render, [f"{image_name} records a capture through {record.lens_id}: its recorded geometry is "
                            f"not used for {lens.id}'s depth of field"]
        raise InputRangeError("lens", lens.id,
                              f"the lens the capture was made with, {record.lens_id} (recorded in {image_name})")
    if record.image_size is not None and shape is not None and tuple(record.image_size) != tuple(shape):
        return render, [f"{image_name} records a {record.image_size[0]} x {record.image_size[1]} px capture but "
                        f"is {shape[0]} x {shape[1]} px (resized or cropped since): its record is ignored"]
    render = render or RenderRequest(lens)
    changes, labels = {}, {}
    blame = f"the capture record of {image_name}:"
    if render.image_pitch_mm is None and render.sensor_size is None and record.pixel_pitch_mm is not None:
        changes["image_pixel_pitch_mm"] = float(record.pixel_pitch_mm)
        labels["image_pixel_pitch_mm"] = f"{blame} pixel_pitch_mm"
        if render.axis_px is None and record.axis_px is not None:
            changes["axis_px"] = tuple(float(a) for a in record.axis_px)
            labels["axis_px"] = f"{blame} axis_px"
    if focus and render.psf.focus_distance_m is None and record.focus_distance_m is not None:
        _check_recorded_focus(lens, float(record.focus_distance_m), render.psf.wavelength_nm, blame)
        changes["psf"] = replace(render.psf, focus_distance_m=float(record.focus_distance_m))
    from ..io.capture_record import prescription_sha256
    notes = []
    if record.prescription_sha256 is not None and record.prescription_sha256 != prescription_sha256(lens):
        notes.append(_prescription_note(record, lens, image_name))
    if not changes:
        return render, notes
    # the request checks its values again, naming the record's fields where they came from it
    return replace(render, **changes, labels={**render.labels, **labels}), notes


def _prescription_note(record, lens, image_name: str) -> str:
    """Why the recorded prescription differs from ``lens``: another stop
    (the record's iris against the lens's), else an edited or perturbed copy."""
    made = (record.extra or {}).get("iris") or ""
    here = getattr(lens, "iris", "")
    if made or here:
        return (f"{image_name} was made with {lens.id} {f'stopped down ({made})' if made else 'wide open'}, this "
                f"job's {lens.id} is {f'stopped down ({here})' if here else 'wide open'}: give the capture's "
                "--f-number and --blades to use its PSFs; used as given")
    return (f"{image_name} was made with a different prescription of {lens.id} (perturbed or edited: its "
            "prescription hash differs); it is used as given")


def _check_recorded_focus(lens, focus_m: float, wavelength_nm, blame: str) -> None:
    """A recorded focus the lens cannot be focused at, refused naming the record's field."""
    from ..errors import InputRangeError
    from ..optics.paraxial import refocused
    try:
        refocused(lens, focus_m, wavelength_nm)
    except InputRangeError as e:
        raise InputRangeError(f"{blame} focus_distance_m", focus_m, e.allowed) from None
