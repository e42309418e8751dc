"""Depth estimation: the project's network (train, resume, export, serve),
the public estimators through stand-ins of their packages, and the refusal
of a checkpoint that cannot be read, by name."""
import sys

import numpy as np
import pytest

torch = pytest.importorskip("torch")
from support.depth_stand_ins import _stand_in, install_stand_ins  # noqa: E402,F401


def _depth_config(data, **kw):
    from dcdi_core.models.depth.config import DepthTrainConfig
    base = dict(data=str(data), widths=(4, 8), iters=6, batch=2, crop=16, checkpoint_every=3,
                val_fraction=1 / 6, test_fraction=2 / 6)
    base.update(kw)
    return DepthTrainConfig(**base)


def test_depth_network_resumes_exactly_and_is_served_from_its_file(pairs, tmp_path):  # noqa: F811
    from dcdi_core.models.depth.export import export_depthnet
    from dcdi_core.models.depth.estimators import load_estimator
    from dcdi_core.models.depth.train import train_depth
    full = train_depth(_depth_config(pairs), tmp_path / "full")

    class Kill(Exception):
        pass

    def kill(step):
        if step == 4:
            raise Kill
    with pytest.raises(Kill):
        train_depth(_depth_config(pairs), tmp_path / "killed", on_step=kill)
    resumed = train_depth(_depth_config(pairs), tmp_path / "killed")
    for (k, a), b in zip(full.ema.state_dict().items(), resumed.ema.state_dict().values()):
        assert torch.equal(a, b), k
    assert set(full.validation) == {"abs_rel", "rmse", "delta1"}
    meta = export_depthnet(tmp_path / "full", tmp_path / "d.npz")
    assert meta["lens"] == "mos-s2" and meta["step"] == 6
    est = load_estimator("dcdi", tmp_path / "d.npz")
    img = np.random.default_rng(0).uniform(0, 1, (30, 44, 3)).astype(np.float32)
    d = est.estimate(img)
    assert d.shape == (30, 44) and d.dtype == np.float32 and np.isfinite(d).all() and (d > 0).all()
    with pytest.raises(Exception, match="image"):
        est.estimate(np.full((30, 44, 3), np.nan, np.float32))


def test_depth_network_overfits_one_pair(tmp_path):
    """It learns the depth, not just a lower loss: on a scene whose depth
    follows its colour (red blocks at 1 m, the rest at 5 m), the predicted
    depth ends within 15 % (AbsRel) of the truth."""
    from conftest import PAIR_FAST as FAST

    from dcdi_core.models.dacn.data import DA2TConfig, build_pairs, finished_pairs, load_pair, pair_path
    from dcdi_core.dataset.rgbd import RGBDFrame, RGBDSource
    from dcdi_core.models.common.metrics import depth_scores
    from dcdi_core.models.depth.train import predict_depth, train_depth

    class Coloured(RGBDSource):
        def ids(self):
            return [f"s{k}" for k in range(3)]

        def load(self, id):
            rng = np.random.default_rng(int(id[1:]))
            red = rng.uniform(0, 1, (12, 16)) < 0.5
            img = np.where(red[..., None], [0.8, 0.1, 0.1], [0.1, 0.3, 0.8]) * rng.uniform(0.7, 1, (12, 16, 1))
            img = np.kron(img, np.ones((4, 4, 1))).astype(np.float32)
            dep = np.kron(np.where(red, 1.0, 5.0), np.ones((4, 4))).astype(np.float32)
            return RGBDFrame(id, id, img, dep, "test")
    build_pairs(Coloured(), tmp_path / "p", DA2TConfig(lens="mos-s2", noise=None, perturb_fraction=0.0, **FAST))
    cfg = _depth_config(tmp_path / "p", iters=300, batch=4, crop=32, lr=3e-3, checkpoint_every=300,
                        widths=(8, 16), ema_decay=0.0, val_fraction=0.0, test_fraction=0.0)
    losses = []
    result = train_depth(cfg, tmp_path / "run", progress=lambda s, n, loss: losses.append(loss))
    assert np.mean(losses[-20:]) < 0.25 * np.mean(losses[:10])
    p = load_pair(pair_path(tmp_path / "p", sorted(finished_pairs(tmp_path / "p"))[0]))
    s = depth_scores(predict_depth(result.model.eval(), np.array(p.capture)), np.array(p.depth))
    assert s["abs_rel"] < 0.15, s


def test_depth_scores_against_direct_formulas():
    from dcdi_core.models.common.metrics import depth_scores
    t = np.array([[1.0, 2.0], [4.0, np.inf]])
    p = np.array([[1.1, 2.0], [6.0, 3.0]])
    s = depth_scores(p, t)
    assert s["pixels"] == 3
    assert np.isclose(s["abs_rel"], (0.1 + 0 + 0.5) / 3)
    assert np.isclose(s["rmse"], np.sqrt((0.01 + 0 + 4) / 3))
    assert np.isclose(s["delta1"], 2 / 3)


def test_public_estimators_through_stand_ins(tmp_path, monkeypatch):
    from dcdi_core.models.depth.estimators import load_estimator, srgb_uint8
    checkpoints = install_stand_ins(monkeypatch, tmp_path)
    img = np.random.default_rng(1).uniform(0, 1, (20, 24, 3)).astype(np.float32)
    est = load_estimator("depth-anything-v2", checkpoints["depth-anything-v2"])
    assert est.model.kw == {"encoder": "vits", "features": 64, "out_channels": [48, 96, 192, 384], "max_depth": 20.0}
    expected = 1 + 4 * srgb_uint8(img).mean(axis=2) / 255
    for backend, ck in checkpoints.items():
        np.testing.assert_allclose(load_estimator(backend, ck).estimate(img), expected, rtol=1e-6, err_msg=backend)


def test_an_unreadable_checkpoint_is_refused_by_name(tmp_path, monkeypatch):
    from dcdi_core.models.depth.estimators import load_estimator
    from dcdi_core.errors import ModelError, ModelFileError
    bad = tmp_path / "depth_anything_v2_metric_vkitti_vitl.pth"
    bad.write_bytes(b"not a checkpoint")
    with pytest.raises(ModelFileError, match=r"depth_anything_v2_metric_vkitti_vitl\.pth.*depth-anything-v2"):
        load_estimator("depth-anything-v2", bad)
    (tmp_path / "u").mkdir()
    (tmp_path / "u" / "config.json").write_text("{}")
    (tmp_path / "u" / "model.safetensors").write_bytes(b"\xff" * 16)
    with pytest.raises(ModelFileError, match="unidepth safetensors"):
        load_estimator("unidepth", tmp_path / "u")
    with pytest.raises(ModelFileError, match="no such depth-pro checkpoint"):
        load_estimator("depth-pro", tmp_path / "missing.pt")
    bad_npz = tmp_path / "d.npz"
    np.savez(bad_npz, x=np.zeros(2))
    with pytest.raises(ModelFileError, match="d.npz"):
        load_estimator("dcdi", bad_npz)
    with pytest.raises(Exception, match="depth backend"):
        load_estimator("midas", bad)
    torch.save({"w": torch.zeros(1)}, tmp_path / "depth_pro.pt")        # readable, but no package here
    monkeypatch.setitem(sys.modules, "depth_pro", None)
    with pytest.raises(ModelError, match="install Depth Pro"):
        load_estimator("depth-pro", tmp_path / "depth_pro.pt")
