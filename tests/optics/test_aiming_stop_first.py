"""A stop in front (MOS-S1, MOS-S2): pupil_rays does not trace its rays to
the stop a second time, and its rays are bit-identical to the checked path's."""
from __future__ import annotations

import numpy as np
import pytest

from dcdi_core.optics import aiming
from dcdi_core.optics.aiming import pupil_rays, sources, stop_grid
from dcdi_core.optics.lens import load_lens


@pytest.mark.parametrize("lens_id", ["mos-s1", "mos-s2"])
def test_a_stop_in_front_needs_no_second_trace(lens_id, monkeypatch):
    lens = load_lens(lens_id)
    assert aiming._stop_is_first_plane(lens)
    aimed = sources(lens, [0.8, 2.0, np.inf], field=[0.0, 0.5, 1.0])
    targets = stop_grid(lens, 21)
    fast = pupil_rays(lens, aimed, targets)
    calls = []
    real = aiming._stop_xy
    monkeypatch.setattr(aiming, "_stop_is_first_plane", lambda lens: False)
    monkeypatch.setattr(aiming, "_stop_xy", lambda *a: calls.append(1) or real(*a))
    checked = pupil_rays(lens, aimed, targets)
    assert calls and checked[3] < 1e-7                  # the check found the linear start on target
    for a, b in zip(fast[:3], checked[:3]):
        np.testing.assert_array_equal(a, b)


def test_a_stop_behind_a_surface_is_still_aimed_by_newton():
    lens = load_lens("double-gauss")
    assert not aiming._stop_is_first_plane(lens)
