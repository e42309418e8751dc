"""Depth from the capture's own blur (dcdi_core.dfd): fronto-parallel
textured planes at several depths read back within a stated error, a
textureless region of low confidence, never NaN nor a depth outside the
library's range, bad input refused in one line; the CLI end to end."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from dcdi_core.app import PSFRequest, open_source
from dcdi_core.correct.noise import NoiseModel
from dcdi_core.dataset.leaves import leaves_rgbd
from dcdi_core.dfd import DepthFromBlurOptions, estimate_depth
from dcdi_core.dfd.fill import box, guided, spread
from dcdi_core.errors import InputRangeError
from dcdi_core.optics.lens import load_lens
from dcdi_core.render.geometry import ImageGeometry
from dcdi_core.render.noise import add_sensor_noise
from dcdi_core.render.simulate import SimulateOptions, simulate

ROOT = Path(__file__).resolve().parents[2]
H, W = 128, 160


@pytest.fixture(scope="module")
def camera():
    lens = load_lens("mos-s1")
    g = ImageGeometry.from_pixel_pitch(lens, H, W, 0.0122)
    return lens, g, open_source(lens, g, PSFRequest()).library


def capture_of(camera, img, depth, seed=1):
    lens, g, lib = camera
    return add_sensor_noise(simulate(img, depth, lens, SimulateOptions(geometry=g), library=lib).image, seed=seed)


@pytest.mark.parametrize("depth_m", [0.8, 1.2, 2.5])
def test_a_textured_plane_is_read_back_within_its_error(camera, depth_m):
    """A dead-leaves plane at one depth, noisy, at 12.2 um: the median of
    the confident tiles within 20 % of the plane's depth (measured: 2-8 %),
    and the plane nearer than 1 m never read beyond 2 m."""
    img, _, _ = leaves_rgbd(5, H, W)
    cap = capture_of(camera, img, np.full((H, W), depth_m, np.float32))
    est = estimate_depth(cap, camera[2], camera[1], noise=NoiseModel.sensor())
    sure = est.tile_confidence >= 0.3
    assert sure.mean() > 0.3
    read = np.median(1.0 / est.tile_diopters[sure])
    assert abs(read - depth_m) / depth_m < 0.2, (depth_m, read)
    assert abs(np.median(est.depth_m) - depth_m) / depth_m < 0.2


@pytest.fixture(scope="module")
def camera_s2():
    lens = load_lens("mos-s2")
    g = ImageGeometry.from_pixel_pitch(lens, H, W, 0.0122)
    return lens, g, open_source(lens, g, PSFRequest()).library


@pytest.mark.parametrize("lens_fixture", ["camera", "camera_s2"])
@pytest.mark.parametrize("depth_m", [0.8, 1.2, 2.5])
def test_a_plane_with_a_photograph_like_texture_is_read_within_its_error(request, lens_fixture, depth_m):
    """Natural-statistics textures (1/f^a spectra, edges, natural colours:
    dataset.natural), two per depth and lens, noisy, at 12.2 um: the
    confident tiles' median within 30 % of the plane's depth (measured over
    four textures: MOS-S1 2-21 %, MOS-S2 2-26 %, the worst at 2.5 m and
    1.2 m), and the posterior a distribution over the hypotheses."""
    from dcdi_core.dataset.natural import NaturalTextureOptions, natural_texture
    cam = request.getfixturevalue(lens_fixture)
    for seed in (0, 1):
        img = natural_texture(np.random.default_rng(seed), 256, NaturalTextureOptions(contrast_range=(0.3, 0.9)))
        est = estimate_depth(capture_of(cam, img[:H, :W], np.full((H, W), depth_m, np.float32)), cam[2], cam[1],
                             noise=NoiseModel.sensor())
        sure = est.tile_confidence >= 0.3
        assert sure.mean() >= 0.25                     # measured 0.30-1.00
        read = np.median(1.0 / est.tile_diopters[sure])
        assert abs(read - depth_m) / depth_m < 0.3, (seed, read)
        post = est.posterior
        assert np.allclose(post.posterior.sum(0), 1.0) and (post.posterior >= 0).all()
        assert post.posterior.shape[1:] == est.tile_diopters.shape == post.camera_blur_px.shape[1:]
        assert np.isfinite(post.camera_blur_px).all() and (post.camera_blur_px >= 1.0).all()


def test_near_and_far_planes_are_told_apart(camera):
    """Left half at 0.8 m, right half at 4 m: the left read within 20 %,
    the right at least 1.5 times farther (far depths are the weak ones:
    measured 1.65 m here, the blur changes little beyond 2 m)."""
    img, _, _ = leaves_rgbd(6, H, W)
    depth = np.where(np.arange(W)[None, :] < W // 2, 0.8, 4.0).astype(np.float32) * np.ones((H, 1), np.float32)
    est = estimate_depth(capture_of(camera, img, depth), camera[2], camera[1], noise=NoiseModel.sensor())
    left, right = np.median(est.depth_m[:, :W // 2 - 16]), np.median(est.depth_m[:, W // 2 + 16:])
    assert abs(left - 0.8) / 0.8 < 0.2 and right > 1.5 * left, (left, right)


def test_a_textureless_region_has_low_confidence(camera):
    """A flat grey frame with noise: no tile is confident, and the depth is
    still finite and inside the library's range."""
    img = np.full((H, W, 3), 0.3, np.float32)
    cap = capture_of(camera, img, np.full((H, W), 1.5, np.float32))
    est = estimate_depth(cap, camera[2], camera[1], noise=NoiseModel.sensor())
    textured = estimate_depth(capture_of(camera, leaves_rgbd(5, H, W)[0], np.full((H, W), 1.0, np.float32)),
                              camera[2], camera[1], noise=NoiseModel.sensor())
    assert est.tile_confidence.max() < 0.5 < textured.tile_confidence.mean() + 0.2
    assert est.confidence.mean() < textured.confidence.mean() / 2


@pytest.mark.parametrize("kind", ["black", "white clipped", "one bright pixel", "tiny values"])
def test_extreme_captures_give_finite_depths_in_range(camera, kind):
    lens, g, lib = camera
    img = {"black": np.zeros((H, W, 3)), "white clipped": np.ones((H, W, 3)),
           "one bright pixel": np.zeros((H, W, 3)), "tiny values": np.full((H, W, 3), 1e-30)}[kind]
    if kind == "one bright pixel":
        img[H // 2, W // 2] = 1.0
    est = estimate_depth(img.astype(np.float32), lib, g)
    assert np.isfinite(est.depth_m).all() and np.isfinite(est.confidence).all()
    assert est.depth_m.min() >= lib.grid.near_m - 1e-6 and est.depth_m.max() <= lib.grid.far_m + 1e-6
    assert 0.0 <= est.confidence.min() and est.confidence.max() <= 1.0
    if kind == "white clipped":
        assert est.confidence.max() == 0.0


def test_bad_input_is_refused_before_work(camera):
    lens, g, lib = camera
    img = np.zeros((H, W, 3), np.float32)
    bad = img.copy()
    bad[3, 4, 1] = np.nan
    with pytest.raises(InputRangeError, match="NaN or infinite"):
        estimate_depth(bad, lib, g)
    with pytest.raises(InputRangeError, match="capture shape"):
        estimate_depth(img[..., 0], lib, g)
    with pytest.raises(InputRangeError, match="geometry"):
        estimate_depth(img[:64], lib, g)
    for kw in ({"tile": 4}, {"window": 16, "tile": 32}, {"temperature": 0.0}, {"max_frequency": 0.9},
               {"amplitude_steps": ()}, {"model_error": -1.0}):
        with pytest.raises(InputRangeError):
            DepthFromBlurOptions(**kw)


def test_fill_spreads_confident_values_and_keeps_constants():
    v = np.array([[1.0, 5.0, 5.0], [1.0, 5.0, 5.0]])
    w = np.array([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    out = spread(v, w)
    assert np.allclose(out, 1.0)                               # the unsure tiles take the sure ones' value
    x = np.random.default_rng(0).random((20, 30))
    assert np.allclose(box(np.full((20, 30), 2.0), 3), 2.0)
    assert np.allclose(guided(x, np.full((20, 30), 0.7), 4, 0.01), 0.7)
    brute = np.array([[x[max(i - 2, 0):i + 3, max(j - 2, 0):j + 3].mean() for j in range(30)] for i in range(20)])
    assert np.allclose(box(x, 2), brute)


def test_cli_estimate_writes_depth_and_confidence(tmp_path, camera):
    from dcdi_core.io.images import read_depth, write_image
    img, _, _ = leaves_rgbd(7, H, W)
    cap = capture_of(camera, img, np.full((H, W), 1.0, np.float32))
    write_image(tmp_path / "cap.exr", cap)
    cmd = [sys.executable, "-m", "dcdi_core", "depth", "estimate", "--image", str(tmp_path / "cap.exr"),
           "--camera", "mos-s1", "--image-pixel-pitch", "0.0122", "-o", str(tmp_path / "d.exr"),
           "--confidence", str(tmp_path / "c.exr")]
    p = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert p.returncode == 0, p.stderr
    out = json.loads(p.stdout)
    d, c = read_depth(tmp_path / "d.exr"), read_depth(tmp_path / "c.exr")
    assert d.shape == (H, W) and np.isfinite(d).all() and 0.7 <= d.min() and d.max() <= 10.0
    assert 0 <= c.min() and c.max() <= 1 and out["lens"] == "mos-s1" and out["pixel_pitch_mm"] == 0.0122
    bad = subprocess.run(cmd[:7] + ["--camera", "no-such-lens", "-o", str(tmp_path / "x.exr")],
                         capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert bad.returncode == 2 and bad.stderr.count("\n") == 1 and "Traceback" not in bad.stderr, bad.stderr
    assert not (tmp_path / "x.exr").exists()


def test_bench_depth_quick_prints_the_whole_process_and_its_stages(capsys):
    from dcdi_core.cli import main
    assert main(["bench", "depth", "--quick"]) == 0
    out = capsys.readouterr().out
    line = next(ln for ln in out.splitlines() if ln.strip().startswith("dcdi depth estimate"))
    assert " s (" in line and "s CPU" in line and "goal" not in line          # no goal at the quick size
    assert "in process:" in out and "evidence" in out


def test_a_refinement_is_held_to_what_each_tiles_blur_allows(camera):
    """A refinement that says 10 m everywhere, on a plane at 0.8 m: held
    (the default), the sure tiles stay near 0.8 m; free
    (refine_within=None), they go to 10 m."""
    from dataclasses import replace

    from dcdi_core.dfd import DepthFromBlurOptions
    img, _, _ = leaves_rgbd(5, H, W)
    cap = capture_of(camera, img, np.full((H, W), 0.8, np.float32))

    def far(features, depths):
        return np.full(features.shape[1:], np.log(10.0))
    held = estimate_depth(cap, camera[2], camera[1], noise=NoiseModel.sensor(), refine=far)
    free = estimate_depth(cap, camera[2], camera[1], replace(DepthFromBlurOptions(), refine_within=None),
                          noise=NoiseModel.sensor(), refine=far)
    sure = held.tile_confidence >= 0.5
    assert sure.any() and np.median(1.0 / held.tile_diopters[sure]) < 1.2
    assert np.allclose(1.0 / free.tile_diopters, 10.0)
    with pytest.raises(InputRangeError, match="refine_within"):
        DepthFromBlurOptions(refine_within=(0.9, 0.1))


def _direct_nll(sp, K, amplitude, rho, eta, shape):
    """The likelihood written directly: C = D + P v v^H inverted with complex u = v / D."""
    P = amplitude[:, None] * shape
    v = sp.a[..., None] * K
    v2 = v.real ** 2 + v.imag ** 2
    D = sp.noise[..., None] + rho * P[:, None, :] * v2 + eta * P[:, None, :] * (sp.a ** 2)[..., None]
    u = v / D
    q = (v2 / D).sum(1)
    form = ((u.real ** 2 + u.imag ** 2) * sp.power).sum(1)
    for i, (a, b) in enumerate(((0, 1), (0, 2), (1, 2))):
        form += 2.0 * (np.conj(u[:, a]) * u[:, b] * sp.cross[:, i]).real
    quad = (sp.power / D).sum(1) - P * form / (1.0 + P * q)
    logdet = np.log(D).sum(1) + np.log1p(P * q)
    return (quad + sp.count * logdet).sum(-1, dtype=np.float64)


def test_the_likelihoods_real_form_equals_the_direct_one(camera):
    """The evidence's likelihood (all-real terms made once per hypothesis)
    against the direct complex Sherman-Morrison form, on a capture's
    windows, random transfer functions and amplitudes: within float32
    rounding."""
    from dcdi_core.dfd import evidence
    lens, g, lib = camera
    img, _, _ = leaves_rgbd(5, H, W)
    cap = capture_of(camera, img, np.full((H, W), 1.2, np.float32))
    blocks = evidence.bins(64, 0.71)
    sp = evidence.WindowSpectra(cap, 32, 64, blocks, NoiseModel.sensor(), (0.0, 0.7))
    rng = np.random.default_rng(0)
    n, nb = sp.power.shape[0], sp.power.shape[2]
    K = (rng.uniform(0, 1, (n, 3, nb)) * np.exp(1j * rng.uniform(-3, 3, (n, 3, nb)))).astype(np.complex64)
    for amplitude in (sp.a0, sp.a0 * 30.0):
        for shape in sp.shapes:
            fast = sp.nll(K, amplitude, 0.02, 0.01, shape)
            direct = _direct_nll(sp, K, amplitude, 0.02, 0.01, shape)
            assert np.allclose(fast, direct, rtol=1e-4, atol=1e-3 * np.abs(direct).mean())
