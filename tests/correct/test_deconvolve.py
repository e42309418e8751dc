"""The deconvolution (dcdi_core.correct) against what it must do: recover a
band-limited image from its noise-free simulation, use depth where depth
matters, keep clipped highlights and depth edges free of NaN and overshoot,
and refuse bad input before any work."""
import math

import numpy as np
import pytest

from dcdi_core.correct import DeconvOptions, NoiseModel, deconvolve, estimate_noise
from dcdi_core.errors import InputRangeError
from dcdi_core.psf.sources import psf_source
from dcdi_core.optics.lens import load_lens
from dcdi_core.render.geometry import ImageGeometry
from dcdi_core.render.simulate import SimulateOptions, LensSimulator

PITCH = 0.0122                     # mm: the paper's pixel pitch, where the shipped basis serves MOS-S1 as stored
QUIET = NoiseModel(0.0, 1e-5)      # noise-free captures: a small prior keeps the cut windows from ringing


@pytest.fixture(scope="module")
def mos_s1():
    lens = load_lens("mos-s1")
    src = psf_source(lens, pixel_pitch_mm=PITCH)
    assert src.kind in ("basis", "olf"), src.message           # no tracing in these tests
    return lens, src.library


def _geometry(lens, h, w, off=(150.0, 200.0)):
    """A crop of the sensor at the paper's pitch, off axis (the axis up and left of it)."""
    return ImageGeometry.from_pixel_pitch(lens, h, w, PITCH, center_px=(h / 2 - 0.5 - off[0], w / 2 - 0.5 - off[1]))


def _band_limited(h, w, seed, sigma_px=4.0):
    """Smooth colour texture in [0.15, 0.85]: noise low-passed by a Gaussian of sigma_px."""
    rng = np.random.default_rng(seed)
    f = np.fft.fftfreq(h)[:, None] ** 2 + np.fft.fftfreq(w)[None, :] ** 2
    g = np.exp(-2 * (np.pi * sigma_px) ** 2 * f)
    x = np.stack([np.fft.ifft2(np.fft.fft2(rng.normal(size=(h, w))) * g).real for _ in range(3)], -1)
    x = (x - x.mean()) / (4 * x.std())
    return np.clip(0.5 + x, 0.15, 0.85).astype(np.float32)


def _natural(h, w, seed):
    """Colour texture with a photograph's 1/f amplitude spectrum, in [0.1, 0.9]."""
    rng = np.random.default_rng(seed)
    f = np.sqrt(np.fft.fftfreq(h)[:, None] ** 2 + np.fft.fftfreq(w)[None, :] ** 2)
    amp = 1.0 / np.maximum(f, 1.0 / max(h, w))
    x = np.stack([np.fft.ifft2(np.fft.fft2(rng.normal(size=(h, w))) * amp).real for _ in range(3)], -1)
    x = (x - x.mean()) / (4 * x.std())
    return np.clip(0.5 + x, 0.1, 0.9).astype(np.float32)


def _psnr(a, b, mask):
    return 10 * math.log10(1.0 / float(np.mean((a[mask] - b[mask]) ** 2)))


def _inner(shape, margin):
    m = np.zeros(shape[:2], bool)
    m[margin:-margin, margin:-margin] = True
    return m


def test_a_noise_free_band_limited_image_is_recovered(mos_s1):
    lens, lib = mos_s1
    h, w = 96, 128
    geom = _geometry(lens, h, w)
    img = _band_limited(h, w, seed=1)
    depth = np.where(np.arange(w)[None, :] < w // 2, 1.5, 4.0) * np.ones((h, 1))
    r = LensSimulator(lens, SimulateOptions(geometry=geom), library=lib)(img, depth)
    # with 3 kernel radii of context (the default's 1.5 trade about 4 dB of this noise-free case for speed)
    res = deconvolve(r.image, r.depth, lens, DeconvOptions(noise=QUIET, pad=60), geometry=geom, library=lib)
    inner = _inner(img.shape, 24) & ~np.isnan(r.depth)
    before, after = _psnr(r.image, r.sharp, inner), _psnr(res.image, r.sharp, inner)
    assert after >= 30.0 and after > before + 6.0, (before, after)
    fast = deconvolve(r.image, r.depth, lens, DeconvOptions(noise=QUIET), geometry=geom, library=lib)
    assert _psnr(fast.image, r.sharp, inner) > before + 2.5


def test_depth_aware_beats_one_depth_on_two_planes_that_blur_differently(mos_s1):
    """Left half at 0.75 m, right half at infinity: their PSFs differ; the
    deconvolution with each patch's depth beats the one with 2 m everywhere."""
    lens, lib = mos_s1
    h, w = 96, 160
    geom = _geometry(lens, h, w, off=(0.0, 0.0))
    img = _natural(h, w, seed=2)
    depth = np.where(np.arange(w)[None, :] < w // 2, 0.75, np.inf) * np.ones((h, 1))
    r = LensSimulator(lens, SimulateOptions(geometry=geom), library=lib)(img, depth, noise={}, seed=3)
    noise = NoiseModel.sensor()
    aware = deconvolve(r.image, r.depth, lens, DeconvOptions(noise=noise), geometry=geom, library=lib)
    one = deconvolve(r.image, r.depth, lens, DeconvOptions(noise=noise, one_depth_m=2.0), geometry=geom, library=lib)
    inner = _inner(img.shape, 20) & ~np.isnan(r.depth)
    cap, a, o = (_psnr(x, r.sharp, inner) for x in (r.image, aware.image, one.image))
    assert a > o + 1.0 and a > cap + 0.5, (cap, a, o)


def test_clipped_highlights_and_depth_edges_give_no_nan_and_no_overshoot(mos_s1):
    """A clipped light and a depth edge (0.8 m | 8 m): finite, within [0, 1]
    (a sensor's capture), the clipped pixels as captured, at most 15 % above
    the truth's maximum away from the frame's border, and the edge no worse
    than in the capture."""
    lens, lib = mos_s1
    h, w = 80, 96
    geom = _geometry(lens, h, w)
    img = _band_limited(h, w, seed=4, sigma_px=1.0)
    img[30:40, 40:50] = 6.0                               # a light: clipped in the capture
    depth = np.where(np.arange(w)[None, :] < 60, 0.8, 8.0) * np.ones((h, 1))    # a depth edge
    r = LensSimulator(lens, SimulateOptions(geometry=geom), library=lib)(img, depth, noise={}, seed=5)
    cap = np.clip(r.image, 0.0, 1.0)                      # the sensor saturates
    res = deconvolve(cap, r.depth, lens, DeconvOptions(), geometry=geom, library=lib)
    out = res.image
    assert np.isfinite(out).all() and out.min() >= 0.0 and out.max() <= 1.0
    clipped = (cap >= 0.98).any(axis=2)
    assert clipped.any() and np.array_equal(out[clipped], cap[clipped])   # masked, not amplified
    assert res.info["clipped_px"] == int(clipped.sum())
    # the same scene without the light: the depth edge alone
    img[30:40, 40:50] = 0.5
    r = LensSimulator(lens, SimulateOptions(geometry=geom), library=lib)(img, depth, noise={}, seed=5)
    out = deconvolve(np.clip(r.image, 0, 1), r.depth, lens, DeconvOptions(), geometry=geom, library=lib).image
    inner = _inner(img.shape, res.info["kernel_px"] // 2 + 1)
    assert out[inner].max() <= 1.15 * r.sharp[inner].max()
    band = np.zeros((h, w), bool)
    band[20:60, 52:68] = True
    rms = [float(np.sqrt(np.mean((a[band] - r.sharp[band]) ** 2))) for a in (np.clip(r.image, 0, 1), out)]
    assert rms[1] <= rms[0], rms


def test_constant_zero_and_unknown_depth_stay_what_they_are(mos_s1):
    lens, lib = mos_s1
    geom = _geometry(lens, 40, 56)
    depth = np.full((40, 56), 2.0)
    for value in (0.0, 0.37):
        res = deconvolve(np.full((40, 56, 3), value, np.float32), depth, lens, geometry=geom, library=lib)
        assert np.abs(res.image - value).max() < 1e-4
    cap = np.random.default_rng(0).uniform(0, 1, (40, 56, 3)).astype(np.float32)
    res = deconvolve(cap, np.full((40, 56), np.nan), lens, geometry=geom, library=lib)
    assert np.array_equal(res.image, cap)                  # no depth anywhere: left as it is


def test_images_smaller_than_a_window_and_odd_sizes(mos_s1):
    lens, lib = mos_s1
    for h, w in ((9, 13), (17, 33)):
        geom = _geometry(lens, h, w)
        cap = np.random.default_rng(h).uniform(0.2, 0.8, (h, w, 3)).astype(np.float32)
        res = deconvolve(cap, np.full((h, w), 1.3), lens, geometry=geom, library=lib)
        assert res.image.shape == (h, w, 3) and np.isfinite(res.image).all()


def test_noise_estimate_finds_the_sensor_model():
    rng = np.random.default_rng(0)
    x = np.repeat(np.linspace(0.05, 0.9, 200)[None, :], 160, 0)[..., None] * np.ones(3, np.float32)
    model = NoiseModel.sensor(5000.0, 5.0)
    noisy = x + rng.normal(size=x.shape) * np.sqrt(model.variance(x))
    est = estimate_noise(noisy)
    assert est.gain == pytest.approx(model.gain, rel=0.15)
    assert est.variance(0.5) == pytest.approx(model.variance(0.5), rel=0.15)


@pytest.mark.parametrize("kw, name", [({"patch": 15}, "patch"), ({"weight": 0.0}, "weight"),
                                      ({"weight": math.nan}, "weight"), ({"layer_step_diopters": 0.0}, "layer_step"),
                                      ({"one_depth_m": -1.0}, "one_depth_m"), ({"clip_level": 0.0}, "clip_level"),
                                      ({"pad": 1}, "pad"), ({"method": "rl"}, "method"),
                                      ({"iterations": 0}, "iterations"), ({"prior": "flat"}, "prior")])
def test_bad_options_are_refused_by_name(kw, name):
    with pytest.raises(InputRangeError, match=name):
        DeconvOptions(**kw)


def test_bad_inputs_are_refused_before_any_work(mos_s1):
    lens, lib = mos_s1
    geom = _geometry(lens, 20, 24)
    good = np.zeros((20, 24, 3), np.float32)
    with pytest.raises(InputRangeError, match="capture shape"):
        deconvolve(good[..., 0], np.ones((20, 24)), lens, geometry=geom, library=lib)
    with pytest.raises(InputRangeError, match="non-finite"):
        deconvolve(np.full((20, 24, 3), np.nan, np.float32), np.ones((20, 24)), lens, geometry=geom, library=lib)
    with pytest.raises(InputRangeError, match="depth map shape"):
        deconvolve(good, np.ones((20, 25)), lens, geometry=geom, library=lib)


def test_hqs_keeps_edges_better_than_wiener_on_a_piecewise_constant_scene(mos_s1):
    """Flat colour blocks (the total-variation prior's own kind of image) at
    the paper's pitch with sensor noise: HQS beats the Wiener filter."""
    lens, lib = mos_s1
    h, w = 96, 128
    geom = _geometry(lens, h, w)
    rng = np.random.default_rng(7)
    blocks = rng.uniform(0.15, 0.85, (6, 8, 3))
    img = np.kron(blocks, np.ones((16, 16, 1))).astype(np.float32)
    r = LensSimulator(lens, SimulateOptions(geometry=geom), library=lib)(img, np.full((h, w), 3.0), noise={}, seed=8)
    noise = NoiseModel.sensor()
    wiener = deconvolve(r.image, r.depth, lens, DeconvOptions(noise=noise), geometry=geom, library=lib)
    hqs = deconvolve(r.image, r.depth, lens, DeconvOptions(noise=noise, method="hqs"), geometry=geom, library=lib)
    inner = _inner(img.shape, 20)
    cap, wi, hq = (_psnr(x, r.sharp, inner) for x in (r.image, wiener.image, hqs.image))
    assert np.isfinite(hqs.image).all() and hqs.info["algorithm"] == "hqs"
    assert hq > wi + 0.5 and wi > cap, (cap, wi, hq)
