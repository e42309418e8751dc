"""`python -m lab olf-basis`: the basis is orthonormal and holds what it was
made of; coefficients interpolated between grid points are exact for a field
linear in the inputs and fall back to the nearest point outside the grid."""
from __future__ import annotations

import numpy as np

from lab.olf_basis import basis_of, coefficients, features, interpolated, rebuilt


def test_the_basis_is_orthonormal_and_holds_its_frames():
    rng = np.random.default_rng(0)
    shapes = rng.random((5, 3, 9, 9))
    frames = rng.random((200, 5)) @ shapes.reshape(5, -1)        # rank 5 around no mean
    frames = frames.reshape(200, 3, 9, 9)
    mean, basis = basis_of(frames, 6)
    np.testing.assert_allclose(basis @ basis.T, np.eye(6), atol=1e-10)
    back = rebuilt(coefficients(frames, mean, basis), mean, basis, frames.shape[1:])
    np.testing.assert_allclose(back, frames, atol=1e-9)
    mean, basis = basis_of(frames, 2)          # too few: it must show
    back = rebuilt(coefficients(frames, mean, basis), mean, basis, frames.shape[1:])
    assert np.abs(back - frames).max() > 1e-3


def test_interpolation_is_exact_for_a_linear_field_and_nearest_outside():
    g = np.stack(np.meshgrid(np.linspace(0, 1, 4), np.linspace(0, 1.4, 5), np.linspace(0, 1.4, 3),
                             indexing="ij"), -1).reshape(-1, 3)
    coef = np.stack([g @ [1.0, 2.0, -3.0], g @ [0.5, 0.0, 1.0]], -1)
    inside = np.array([[0.3, 0.7, 0.2], [0.9, 1.1, 1.3]])
    np.testing.assert_allclose(interpolated(g, coef, inside), np.stack([inside @ [1.0, 2.0, -3.0],
                                                                        inside @ [0.5, 0.0, 1.0]], -1), atol=1e-9)
    outside = np.array([[1.5, 0.0, 0.0]])
    np.testing.assert_allclose(interpolated(g, coef, outside), coef[[np.argmin(((g - [1.5, 0, 0]) ** 2).sum(1))]])


def test_the_mlps_inputs_carry_the_signed_blur():
    x = np.array([[0.5, 1.0, 0.5], [0.5, 0.5, 1.0]])
    f = features(x, 100.0)
    assert f.shape == (2, 4) and f[0, 3] == -f[1, 3] == 1.0
