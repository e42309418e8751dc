"""Where `dcdi dof` keeps the correction when the depth was read from the
capture's blur (dcdi_core.app.depth.DofDepthRule), and when it refuses:
a sure depth near the target's focus keeps it, a broad posterior over far
depths leaves the capture as it is; the weight stays in [0, 1] and finite
on extreme posteriors; a refusal is one line that asks for a depth map and
writes nothing; --uncertain-depth accept runs with a note."""
from __future__ import annotations

import json
from functools import partial

import numpy as np
import pytest

from conftest import write_rgbd_scene

from dcdi_core.app import depth as depth_app
from dcdi_core.app.depth import DofDepthRule, target_blur
from dcdi_core.cli import main
from dcdi_core.dfd.estimate import TilePosterior, blur_diameter_px
from dcdi_core.optics.lens import load_lens

DEPTHS = np.array([0.7, 1.0, 1.2, 1.5, 2.0, 3.0, 5.0, 10.0])


def posterior(weights, estimate_m, camera_px=10.0, tiles=(2, 3)):
    p = np.asarray(weights, float)
    p = p / p.sum()
    n = len(DEPTHS)
    return TilePosterior(DEPTHS, np.broadcast_to(p[:, None, None], (n, *tiles)).copy(),
                         np.full(tiles, estimate_m), np.full((n, *tiles), camera_px), 32)


def blur_6p_at(focus_m):
    return target_blur(load_lens("6p"), 0.0122, focus_m)


def test_a_sure_depth_in_the_target_focus_keeps_the_correction():
    post = posterior([0, 0, 1, 0, 0, 0, 0, 0], 1.2)
    rule = DofDepthRule()
    assert (rule.gain(post, blur_6p_at(1.2)) > 0).all()
    mask = rule.mask(post, blur_6p_at(1.2), (64, 96))
    assert mask.shape == (64, 96) and np.allclose(mask, 1.0)
    assert rule.verdict(float(mask.mean())) is None


def test_a_broad_posterior_over_far_depths_leaves_the_capture():
    """The demo's failure: a far board read at 2 m with the posterior spread
    over 2-10 m, the target focused at 1.2 m: the correction would leave it
    too sharp, so it is left out, and too little is left to correct."""
    post = posterior([0, 0, 0, 0, 1, 1, 1, 1], 2.0)
    rule = DofDepthRule()
    assert (rule.gain(post, blur_6p_at(1.2)) < 0).all()
    mask = rule.mask(post, blur_6p_at(1.2), (64, 96))
    assert np.allclose(mask, 0.0)
    assert "only 0%" in rule.verdict(float(mask.mean()))


@pytest.mark.parametrize("camera_px", [0.0, 1e-9, 1e6])
@pytest.mark.parametrize("weights", [[1] * 8, [1, 0, 0, 0, 0, 0, 0, 0], [0] * 7 + [1]])
def test_the_weight_is_finite_and_within_0_1_on_extreme_posteriors(camera_px, weights):
    for focus in (0.7, 1.2, float("inf"), "prescribed"):
        for est in (0.7, 10.0):
            post = posterior(weights, est, camera_px)
            g = DofDepthRule().gain(post, blur_6p_at(focus))
            m = DofDepthRule().mask(post, blur_6p_at(focus), (40, 70))
            assert np.isfinite(g).all() and np.isfinite(m).all() and 0.0 <= m.min() and m.max() <= 1.0


def test_the_target_blur_is_zero_in_focus_and_in_the_kept_range():
    lens = load_lens("6p")
    at = target_blur(lens, 0.0122, 1.2)
    assert at(np.array([1.2]))[0] == pytest.approx(0.0, abs=1e-9) and at(np.array([0.7]))[0] > at(np.array([1.0]))[0]
    inf = target_blur(lens, 0.0122, float("inf"))
    assert inf(np.array([2.0]))[0] == pytest.approx(2 * inf(np.array([4.0]))[0])
    keep = target_blur(lens, 0.0122, keep=(1.0, 2.0))
    assert keep(np.array([1.0, 1.5, 2.0])).max() == 0.0 and keep(np.array([0.7, 5.0])).min() > 0


def test_the_blur_diameter_of_a_point_and_a_disc():
    k = np.zeros((3, 33, 33))
    k[:, 16, 16] = 1.0
    assert blur_diameter_px(k) == pytest.approx(np.sqrt(4 / np.pi))
    yy, xx = np.mgrid[-16:17, -16:17]
    disc = (yy ** 2 + xx ** 2 <= 10 ** 2).astype(float)
    assert blur_diameter_px(np.stack([disc] * 3)) == pytest.approx(20.0, rel=0.02)


@pytest.fixture
def scene(tmp_path, monkeypatch):
    write_rgbd_scene(tmp_path, monkeypatch, 48, 64)
    return tmp_path


FAST = ["--rays", "16", "--wavelengths", "3", "--kernel", "15", "--psf-source", "trace"]


def test_dof_refuses_in_one_line_and_writes_nothing_or_runs_when_accepted(scene, capsys, monkeypatch):
    monkeypatch.setattr(depth_app, "DofDepthRule", partial(DofDepthRule, min_share=1.01))   # refuses any frame
    args = ["dof", "--image", str(scene / "aif.exr"), "--lens", "mos-s1", "--keep", "0.7", "1.5", *FAST,
            "--camera", "mos-s2", "--method", "deconv", "--depth-backend", "blur"]
    assert main([*args, "-o", str(scene / "p.exr")]) != 0
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--depth DEPTH.exr" in err and "too uncertain" in err
    assert not (scene / "p.exr").exists()
    assert main([*args, "--uncertain-depth", "accept", "-o", str(scene / "q.exr")]) == 0
    out = json.loads(capsys.readouterr().out)
    assert any("too uncertain" in n for n in out["notes"]) and (scene / "q.exr").exists()
