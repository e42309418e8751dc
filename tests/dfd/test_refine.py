"""The learned refinement of the depth from blur: the numpy runtime equals
the torch network it was exported from, training overfits a tiny case, and
a shipped refinement runs only at the pixel pitch it learned."""
from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from dcdi_core.models.depth import refine as R  # noqa: E402
from dcdi_core.errors import ModelFileError  # noqa: E402
from dcdi_core.models.runtime.dfd_refine import DfdRefiner  # noqa: E402

C, LOG = 12, 5


def test_numpy_runtime_equals_the_torch_network(tmp_path):
    config = R.RefineConfig(width=8, dilations=(1, 2, 1), seed=3)
    torch.manual_seed(0)
    model = R.build(config, C)
    for m in model:
        if hasattr(m, "weight"):
            torch.nn.init.normal_(m.weight, std=0.2)
            torch.nn.init.normal_(m.bias, std=0.1)
    R.export(model, tmp_path / "r.npz", "mos-s1", config, C, LOG, {"pixel_pitch_mm": 0.0122, "tile_px": 32})
    x = np.random.default_rng(1).normal(size=(C, 9, 13)).astype(np.float32)
    with torch.no_grad():
        want = x[LOG] + model(torch.from_numpy(x[None]))[0, 0].numpy()
    got = DfdRefiner(tmp_path / "r.npz")(x)
    np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-5)


def test_training_overfits_a_tiny_case():
    """The true depth 35 % farther than the evidence says on every tile: learned within 2 %."""
    rng = np.random.default_rng(0)
    items = []
    for _ in range(2):
        f = rng.normal(size=(C, 6, 8)).astype(np.float32)
        f[LOG] = np.log(rng.uniform(1, 5, size=(6, 8)))
        items.append({"features": f, "target": (np.exp(f[LOG]) * 1.35).astype(np.float32)})
    before = R.evaluate(R.build(R.RefineConfig(width=8), C), items, LOG)
    model, curve = R.train(items, R.RefineConfig(width=8, iters=300, lr=1e-2), LOG)
    assert before > 0.25 and R.evaluate(model, items, LOG) < 0.02 and curve[-1][1] < curve[0][1]


def test_a_refinement_runs_only_at_its_pitch_and_for_its_lens(tmp_path, monkeypatch):
    from dcdi_core.app import depth
    from dcdi_core import shipped as registry
    config = R.RefineConfig(width=4, dilations=(1, 1))
    R.export(R.build(config, C), tmp_path / "dfd-refine-mos-s1.npz", "mos-s1", config, C, LOG,
             {"pixel_pitch_mm": 0.0122, "tile_px": 32})
    monkeypatch.setattr(registry, "WEIGHTS_DIR", tmp_path)
    refiner, why = depth.refinement("auto", "mos-s1", 0.0122)
    assert refiner is not None and why == ""
    refiner, why = depth.refinement("auto", "mos-s1", 0.0352)
    assert refiner is None and "12.2 um" in why and "35.2 um" in why
    assert depth.refinement(None, "mos-s1", 0.0122) == (None, "")
    assert depth.refinement("auto", "mos-s2", 0.0122) == (None, "")
    with pytest.raises(ModelFileError, match="trained for lens mos-s1"):
        depth.refinement(tmp_path / "dfd-refine-mos-s1.npz", "mos-s2", 0.0122)
    with pytest.raises(ModelFileError, match="channels"):
        DfdRefiner(tmp_path / "dfd-refine-mos-s1.npz").check(C + 1, 32)


def test_a_posterior_of_other_hypotheses_is_resampled_onto_the_learned_ones(tmp_path):
    """A library of another depth grid (a traced one: 11 hypotheses, the
    basis: 21): the posterior is carried over in inverse depth, each tile's
    mass kept at 1 and its peak where it was."""
    learned = list(1.0 / np.append(np.linspace(1 / 0.7, 0.1, 20), 1e-300))
    config = R.RefineConfig(width=4, dilations=(1, 1))
    R.export(R.build(config, 21 + 7), tmp_path / "r.npz", "mos-s1", config, 21 + 7, 21,
             {"pixel_pitch_mm": 0.0122, "tile_px": 32, "hypotheses_m": learned})
    r = DfdRefiner(tmp_path / "r.npz")
    have = 1.0 / np.append(np.linspace(1 / 0.7, 0.1, 10), 1e-300)
    post = np.zeros((11, 2, 3), np.float32)
    post[3] = 1.0                                          # all mass at the 4th of the 11
    f = np.concatenate([post, np.ones((7, 2, 3), np.float32)])
    r.check(len(f), 32, 11)
    out = r.resample(f, have)
    assert out.shape == (28, 2, 3)
    np.testing.assert_allclose(out[:21].sum(0), 1.0, rtol=1e-5)
    peak = np.asarray(learned)[out[:21, 0, 0].argmax()]
    assert abs(1 / peak - 1 / have[3]) < 0.05             # the same inverse depth, to a bin
    np.testing.assert_array_equal(out[21:], f[11:])
    with pytest.raises(ModelFileError, match="channels"):
        r.check(len(f) + 1, 32, 11)
