"""The catalogue of photographic lenses (lenses/*.toml beyond the paper's
four): each names its source, keeps its stated focal length and f-number,
traces as stated, images its whole field and stops down."""
import math
import re

import numpy as np
import pytest
from conftest import PAPER_LENSES

from dcdi_core.optics.aperture import Aperture, stopped_down
from dcdi_core.optics.lens import available_lenses, load_lens
from dcdi_core.optics.paraxial import first_order
from dcdi_core.psf.compute import PSFSettings, psf

CATALOGUE = sorted(set(available_lenses()) - set(PAPER_LENSES))
FULL_FRAME_SEMI_DIAGONAL_MM = math.hypot(36.0, 24.0) / 2
# a patent (US, FR, DE, GB, JP number) or a book with its page
SOURCE = re.compile(r"\b(US|FR|DE|GB|JP)\s?[A-Z]?\d[\d,.\- ]{4,}|\bpp?\. ?\d+")


def test_the_catalogue_covers_what_photographers_reach_for():
    assert len(CATALOGUE) >= 12 and len(available_lenses()) >= 16
    efl = {i: first_order(load_lens(i)).effective_focal_length_mm for i in CATALOGUE}
    assert min(efl.values()) <= 28.0 and max(efl.values()) >= 100.0
    fast = [i for i in CATALOGUE if first_order(load_lens(i)).f_number <= 2.0 * 1.03]
    assert len(fast) >= 3


@pytest.mark.parametrize("lens_id", CATALOGUE)
def test_each_lens_names_its_source_and_traces_as_stated(lens_id):
    lens = load_lens(lens_id)
    assert SOURCE.search(lens.source), lens.source
    fo = first_order(lens)
    stated = lens.stated
    assert fo.effective_focal_length_mm == pytest.approx(stated["effective_focal_length_mm"], rel=0.01)
    assert fo.f_number == pytest.approx(stated["f_number"], rel=0.03)
    # full frame, the sensor at the paraxial focus for infinity
    assert lens.sensor.semi_diagonal_mm == pytest.approx(FULL_FRAME_SEMI_DIAGONAL_MM, rel=1e-3)
    assert abs(fo.in_focus_object_distance_m) > 1e3
    # a short name for the panel's list (the source is in its own field)
    assert len(lens.name) <= 28


@pytest.mark.parametrize("lens_id", CATALOGUE)
@pytest.mark.filterwarnings("ignore::dcdi_core.psf.compute.KernelTooSmallWarning")   # the corners' flare wide open
def test_each_lens_images_its_field_and_stops_down(lens_id):
    lens = load_lens(lens_id)
    s = PSFSettings(kernel_size=41, pupil_samples=16, n_wavelengths=3, pixel_pitch_mm=0.03, focus_distance_m=3.0)
    for field in (0.0, 0.7, 1.0):
        b = psf(lens, depth_m=3.0, field=field, settings=s)     # in focus: the aberrations alone
        assert not b.zero_energy and np.isfinite(b.psf).all()
        assert np.allclose(b.psf.sum(axis=(-1, -2)), 1.0, atol=1e-4)
        assert b.vignetted_fraction.max() < 0.9
    n = 2.0 * first_order(lens).f_number
    assert first_order(stopped_down(lens, Aperture(n, 7))).f_number == pytest.approx(n, rel=1e-9)
