"""The blur-scaled frame of `python -m lab report olf --frame-px`: a kernel
narrower than the frame goes through unchanged; a wide disc comes back
close, closer with more frame pixels; sums stay 1."""
from __future__ import annotations

import numpy as np

from lab.olf_report import frame_round_trip


def _disc(k: int, radius: float) -> np.ndarray:
    yy, xx = np.mgrid[:k, :k] - k // 2
    d = ((yy ** 2 + xx ** 2) <= radius ** 2).astype(np.float64)
    d = np.stack([d, d, d])
    return d / d.sum(axis=(-1, -2), keepdims=True)


def test_a_small_kernel_goes_through_unchanged():
    k = _disc(61, 3.0)[None]
    np.testing.assert_allclose(frame_round_trip(k, [2.0], 21), k, atol=1e-12)


def test_a_wide_disc_comes_back_closer_with_a_larger_frame():
    k = _disc(101, 40.0)[None]
    errors = []
    for m in (15, 31, 63):
        back = frame_round_trip(k, [80.0], m)
        np.testing.assert_allclose(back.sum(axis=(-1, -2)), 1.0, atol=1e-9)
        errors.append(float(np.abs(back - k).sum() / 3))
    assert errors[0] > errors[1] > errors[2] and errors[2] < 0.08, errors


def test_the_studys_frame_is_the_reports():
    """`lab olf-frame`'s targets and their way back are the report's round trip, in two steps."""
    from lab.olf_frame import from_frame, to_frame
    k = np.concatenate([_disc(101, 40.0)[None], _disc(101, 2.0)[None]])
    blur = np.array([80.0, 1.0])
    frames = to_frame(k, blur, 31)
    assert frames.shape == (2, 3, 31, 31) and np.allclose(frames.sum(axis=(-1, -2)), 1.0, atol=1e-6)
    np.testing.assert_allclose(from_frame(frames, blur, 101), frame_round_trip(k, blur, 31), atol=1e-6)
