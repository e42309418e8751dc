"""A capture's frame, made once per job and handed to every stage.

The frame of a capture is where its pixels lie on the sensor of the lens that
took it: the pixel pitch (mm), the optical axis (row, col px) and the size,
with the PSF settings of that sensor (its focus). The capture's record
(``io.capture_record``: what the file remembers of how it was made) gives the
defaults of what the user did not say (``records.recorded_defaults``), with
notes for the user. The depth estimate, the correction and the registry's
pitch checks of one job all read the same frame: nothing is planned twice.
"""
from __future__ import annotations

from dataclasses import dataclass

from ..render.request import RenderRequest
from .records import recorded_defaults


@dataclass(frozen=True)
class CaptureFrame:
    """``lens`` (an ``optics.lens.Lens``), ``render`` (the request with the
    record's defaults), ``plan`` (its ``render.request.RenderPlan`` for this
    capture: ``geometry``, ``settings``), ``recorded`` (the record or None),
    ``notes`` (lines the record gave), ``shape`` (H, W) and ``image_name``."""

    lens: object
    render: RenderRequest
    plan: object
    recorded: object
    notes: tuple
    shape: tuple
    image_name: str

    @property
    def geometry(self):
        return self.plan.geometry

    @property
    def pitch_mm(self) -> float:
        """The capture's pixel pitch on the sensor, mm."""
        return self.plan.geometry.pixel_pitch_mm

    def serves(self, lens, shape) -> bool:
        """Whether this frame is the one of a capture of ``shape`` (H, W) through ``lens``."""
        return lens is self.lens and tuple(shape) == tuple(self.shape)


def capture_frame(lens, render: RenderRequest | None, recorded, shape, image_name: str = "the capture") -> CaptureFrame:
    """The frame of a capture of ``shape`` (H, W) through ``lens``:
    ``render``'s geometry and PSF settings, the record's where ``render``
    leaves them open, else the capture spanning the sensor's diagonal."""
    render, notes = recorded_defaults(render, lens, recorded, shape, image_name)
    render = render or RenderRequest(lens)
    plan = render.plan(*shape, image=image_name)
    return CaptureFrame(lens, render, plan, recorded, tuple(notes), tuple(int(n) for n in shape), image_name)
