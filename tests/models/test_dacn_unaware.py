"""The depth-unaware pipeline at the shipped design's size (the study's
``refine@2m`` row): its training pairs are the one-depth captures told that
depth, refining their one-depth deconvolution, and it is evaluated told
that depth too."""
import json

import numpy as np
import pytest

from conftest import dacn_config, pairs  # noqa: F401

torch = pytest.importorskip("torch")


@pytest.fixture(scope="module")
def derived(pairs, tmp_path_factory):  # noqa: F811
    from dcdi_core.models.dacn.unaware import derive_pairs
    root = tmp_path_factory.mktemp("told")
    derive_pairs(pairs, root)
    return root


def test_derived_pairs_are_the_one_depth_captures_told_that_depth(pairs, derived):  # noqa: F811
    from dcdi_core.correct.deconvolution import deconvolve
    from dcdi_core.models.dacn.data import finished_pairs, frame_geometry, load_pair, pair_path
    from dcdi_core.optics.lens import load_lens
    src, dst = finished_pairs(pairs), finished_pairs(derived)
    assert sorted(src) == sorted(dst)
    assert json.loads((derived / "da2t.json").read_text())["told_depth_m"] == 2.0
    lens = load_lens("mos-s2")
    for pid in sorted(src)[:2]:
        a, b = load_pair(pair_path(pairs, pid), src[pid]), load_pair(pair_path(derived, pid), dst[pid])
        assert np.array_equal(b.capture, a.baseline) and np.array_equal(b.target, a.target)
        imaged = ~np.isnan(a.depth)
        assert np.array_equal(np.isnan(b.depth), ~imaged) and np.all(b.depth[imaged] == 2.0)
        assert dst[pid]["told_depth_m"] == 2.0 and dst[pid]["geometry"] == src[pid]["geometry"]
        # independent of the one-depth option: the deconvolution of a depth map that is 2 m everywhere
        geom = frame_geometry(lens, *a.depth.shape, src[pid].get("sensor_px"), src[pid].get("top_left"))
        flat = deconvolve(np.array(a.baseline), np.where(imaged, 2.0, np.nan), lens, geometry=geom).image
        assert np.abs(np.asarray(b.deconvolved) - flat)[imaged].mean() < 2e-3
        assert not np.allclose(b.deconvolved, a.deconvolved, atol=1e-3)     # not the depth-aware one


def test_deriving_again_adds_nothing_and_other_settings_are_refused(pairs, derived, tmp_path):  # noqa: F811
    from dcdi_core.errors import InputRangeError
    from dcdi_core.models.dacn.unaware import derive_pairs
    from dcdi_core.errors import ModelError
    n = len((derived / "pairs.jsonl").read_text().splitlines())
    assert len(derive_pairs(pairs, derived)) == n
    assert len((derived / "pairs.jsonl").read_text().splitlines()) == n
    with pytest.raises(InputRangeError, match="da2t.json: told depth.*2 m"):
        derive_pairs(pairs, tmp_path / "x", 5.0)
    cfg = json.loads((derived / "da2t.json").read_text())
    (tmp_path / "y").mkdir()
    (tmp_path / "y" / "da2t.json").write_text(json.dumps(dict(cfg, derived_from="elsewhere")))
    with pytest.raises(ModelError, match="other DA2T settings .derived_from"):
        derive_pairs(pairs, tmp_path / "y")
    with pytest.raises(InputRangeError, match="derived pairs"):
        derive_pairs(derived, tmp_path / "z")


def test_a_run_trained_told_one_depth_is_evaluated_told_it(pairs, derived, tmp_path, capsys,  # noqa: F811
                                                           monkeypatch):
    from dcdi_core.cli import main
    from dcdi_core.models.dacn import correct as correct_mod
    from dcdi_core.models.dacn.correct import load_dacn
    from dcdi_core.models.dacn.train import train_dacn
    from dcdi_core.models.dacn.unaware import Correction, told_depth
    arch = dict(channels=8, groups=1, blocks=1)
    for name, data in (("told", derived), ("aware", pairs)):
        train_dacn(dacn_config(data, iters=2, checkpoint_every=2, config="refine", arch=arch), tmp_path / name)
    told, info = load_dacn(tmp_path / "told")
    aware, info_aware = load_dacn(tmp_path / "aware")
    assert told_depth(info) == 2.0 and told_depth(info_aware) is None
    seen = []
    real = correct_mod.correct
    monkeypatch.setattr(correct_mod, "correct", lambda m, img, d, **kw: seen.append((m, d, kw["deconvolved"]))
                        or real(m, img, d, **kw))
    fix = Correction({told: 2.0, aware: None}, "mos-s2", pairs)
    img = np.random.default_rng(0).uniform(0, 1, (48, 64, 3)).astype(np.float32)
    depth = np.where(np.arange(64) < 30, 0.9, 5.0)[None, :] * np.ones((48, 1), np.float32)
    depth[0, 0] = np.nan
    dec = np.full_like(img, 0.5)
    from dcdi_core.render.geometry import ImageGeometry
    from dcdi_core.optics.lens import load_lens
    geom = ImageGeometry.full_sensor(load_lens("mos-s2"), 48, 64)
    for m in (told, told, aware):
        fix(m, img, depth, deconvolved=dec, geometry=geom)
    (m1, d1, dec1), (_, _, dec2), (m3, d3, dec3) = seen
    assert np.all(d1[~np.isnan(depth)] == 2.0) and np.isnan(d1[0, 0]) and dec1 is dec2   # deconvolved once
    assert not np.allclose(dec1, dec) and d3 is depth and dec3 is dec
    assert main(["dacn", "eval", str(tmp_path / "told"), "--data", str(pairs), "--compare",
                 f"aware={tmp_path / 'aware'}"]) == 0
    assert "told 2 m everywhere" in capsys.readouterr().out


def test_dcdi_correct_tells_such_a_run_its_depth_too(derived, tmp_path):
    from dataclasses import replace

    from dcdi_core.correct import DeconvOptions
    from dcdi_core.models.dacn.correct import correct
    from dcdi_core.models.dacn.train import train_dacn
    from dcdi_core.optics.lens import load_lens
    from dcdi_core.app.correction_rule import Deconvolution, load_network
    from dcdi_core.psf.sources import PSFRequest
    from dcdi_core.render.geometry import ImageGeometry
    train_dacn(dacn_config(derived, iters=2, checkpoint_every=2, config="refine",
                           arch=dict(channels=8, groups=1, blocks=1)), tmp_path / "told")
    lens = load_lens("mos-s2")
    geom = ImageGeometry.full_sensor(lens, 48, 64)
    net = replace(load_network(tmp_path / "told", "mos-s2"), deconvolution=Deconvolution(lens, psf=PSFRequest(source="trace")),
                  geometry=geom)
    rng = np.random.default_rng(1)
    img = rng.uniform(0.1, 0.9, (48, 64, 3)).astype(np.float32)
    depth = np.where(np.arange(64) < 30, 0.9, 5.0)[None, :] * np.ones((48, 1), np.float32)
    out, _ = net.run(img, depth)
    told = np.full_like(depth, 2.0)
    dec, _ = Deconvolution(lens, options=DeconvOptions(one_depth_m=2.0), geometry=geom,
                           psf=PSFRequest(source="trace")).run(
        img, told)
    want = correct(net.model, img, told, deconvolved=dec, geometry=geom)
    assert np.allclose(out, np.clip(want, 0, None), atol=1e-6)
    aware, _ = net.run(img, np.full_like(depth, 2.0))
    assert np.allclose(out, aware, atol=1e-6)              # the depth map given does not matter to it
