"""The layered bokeh spreads a layer's blur as far as its kernels reach, not
only as far as the tent blend of the patches that hold the layer's pixels."""

from dataclasses import replace

import numpy as np
import pytest

from dcdi_core.optics.lens import load_lens
from dcdi_core.psf.compute import PSFSettings
from dcdi_core.psf.library import LibraryGrid, PSFLibrary
from dcdi_core.render.geometry import ImageGeometry
from dcdi_core.render.bokeh import BokehOptions, bokeh

pytestmark = pytest.mark.filterwarnings("ignore::dcdi_core.psf.compute.KernelTooSmallWarning")


@pytest.fixture(scope="module")
def lens_lib():
    lens = load_lens("6p")
    full = ImageGeometry.full_sensor(lens, 1280, 1920)
    geom = ImageGeometry.from_pixel_pitch(lens, 96, 96, full.pixel_pitch_mm, center_px=(300.0, 400.0))
    lib = PSFLibrary(lens, PSFSettings(pupil_samples=24, n_wavelengths=3, kernel_size=41, band_nm=(400.0, 700.0),
                                       pixel_pitch_mm=full.pixel_pitch_mm), LibraryGrid(n_fields=8, n_depths=4), None)
    return lens, geom, lib


def test_a_lone_light_blurs_out_to_its_kernels_reach(lens_lib):
    """One bright pixel near the lens over a black far background, a kept
    subject elsewhere: nothing occludes the light, so its halo is the one it
    has when the whole frame lies at its depth (every patch then holds the
    light's layer). The identity kernel on the patches holding none of the
    light's layer used to cut the halo ~8 px beyond the light's own patch."""
    lens, geom, lib = lens_lib
    img = np.zeros((96, 96, 3), np.float32)
    img[40, 40] = 50.0
    img[80:, 80:] = 0.2
    keep = (1.1, 1.3)
    alone = np.full((96, 96), 10.0)           # the background far behind
    alone[40, 40] = 0.4                       # the light near: wide kernels
    alone[80:, 80:] = 1.2                     # the kept subject, away from the light
    whole = np.where(alone == 10.0, 0.4, alone)
    got = bokeh(img, alone, lens, BokehOptions(keep=keep, geometry=geom), library=lib).image
    want = bokeh(img, whole, lens, BokehOptions(keep=keep, geometry=geom), library=lib).image
    halo = np.zeros((96, 96), bool)
    halo[20:61, 20:61] = True
    halo[32:49, 32:49] = False                # beyond the light's own 16-px patch and its tents
    assert want[halo].sum() > 0.05 * want[20:61, 20:61].sum()      # a halo worth testing
    np.testing.assert_allclose(got[halo].sum(), want[halo].sum(), rtol=0.02)
    assert np.isfinite(got).all()


def test_a_faint_layer_behind_stays_as_faint_as_its_coverage():
    """The layered composite (bokeh._composite_block): what lies behind a
    layer counts as whole where its coverage reaches OPAQUE_COVER (the colour
    spread from around fills a hidden part: no dark seam), and in proportion
    where it is fainter: a bright light's faint blur (coverage 0.002, colour
    30 once normalised) seen under a nearly opaque layer stays faint instead
    of lighting it up. Where the layer covers nothing, what lies behind is
    left as it was."""
    from dcdi_core.render.bokeh import OPAQUE_COVER, _composite_block
    board = 0.5

    def over(behind_colour, behind_cover, cover):
        col = np.full((1, 1, 3), behind_colour, np.float32)
        acc = np.full((1, 1, 3), behind_cover, np.float32)
        blurred = np.concatenate([np.full(3, board * cover), np.full(3, cover)]).astype(np.float32)[None, None]
        _composite_block(col, acc, blurred)
        return float(col[0, 0, 0]), float(acc[0, 0, 0])

    got, acc = over(30.0, 0.002, 0.97)
    # counted whole, the light behind would add 30 x 0.03 = 0.9: in proportion, 30 x 0.002 / 0.05 x 0.03
    assert abs(got - board) < 0.05 and acc == pytest.approx(0.97 + 0.03 * 0.002, rel=1e-5)
    # behind seen enough: whole, as a continuous surface crossing layers needs
    for seen in (OPAQUE_COVER, 0.3, 1.0):
        got, _ = over(0.2, seen, 0.5)
        assert got == pytest.approx(0.5 * board + 0.5 * 0.2, rel=1e-5)
    # nothing behind: the layer's own colour, normalised
    assert over(0.0, 0.0, 0.01)[0] == pytest.approx(board, rel=1e-5)
    # a layer that covers nothing leaves what lies behind bit for bit
    assert over(0.123, 0.4, 0.0) == (np.float32(0.123), np.float32(0.4))


def test_a_blur_the_kernel_clips_is_rendered_at_reduced_resolution(monkeypatch, tmp_path):
    """BokehOptions.large_blur: with the fitted kernel capped far below a
    layer's blur (MAX_FITTED_KERNEL made 15 px here; the 6P's far background
    needs 63), that layer is blurred at 1/f of the resolution with PSFs
    traced at f times the pitch: five bright lights' bokeh is much closer to
    a reference whose 121-px kernels hold it than with the clipped kernel
    (which shrinks each disc to the kernel), the sharp subject is kept as it
    is, and a constant image stays constant."""
    import dcdi_core.psf.library as psf_library
    monkeypatch.setenv("DCDI_CACHE_DIR", str(tmp_path))
    lens = load_lens("6p")
    geom = ImageGeometry.from_pixel_pitch(lens, 96, 128, 0.0122, center_px=(47.5, 63.5))
    rng = np.random.default_rng(0)
    img = np.full((96, 128, 3), 0.05, np.float32)
    for y, x in ((15, 20), (20, 100), (80, 30), (75, 110), (48, 15)):
        img[y - 1:y + 2, x - 1:x + 2] = 20.0
    img[30:66, 40:80] = 0.2 + 0.6 * rng.random((36, 40, 3))
    depth = np.full((96, 128), 10.0, np.float32)
    depth[30:66, 40:80] = 1.2
    fast = PSFSettings(pupil_samples=24, n_wavelengths=3)

    def run(image=img, **kw):
        return bokeh(image, depth, lens, BokehOptions(focus_m=1.2, keep=(1.1, 1.3), geometry=geom, **kw))
    ref = run(fit_kernel=False, large_blur=False, settings=replace(fast, kernel_size=121)).image
    monkeypatch.setattr(psf_library, "MAX_FITTED_KERNEL", 15)
    clipped = run(settings=replace(fast, kernel_size=15), large_blur=False).image
    large = run(settings=replace(fast, kernel_size=15))
    assert large.info["large_blur_factor"] in (4, 8) and large.info["large_blur_layers"] >= 1
    far = depth > 5
    err = {k: float(np.sqrt(np.mean((v - ref)[far] ** 2))) for k, v in (("clipped", clipped), ("large", large.image))}
    assert err["large"] < 0.5 * err["clipped"], err
    assert np.abs(large.image - img)[34:62, 44:76].max() < 1e-5            # the subject, in focus, as it was
    flat = run(np.full_like(img, 0.5), settings=replace(fast, kernel_size=15)).image
    assert np.abs(flat - 0.5).max() < 2e-3
    # the coarse PSFs' trace reports its bins and stops on a cancel (an empty cache: they are traced)
    from dcdi_core.render.base import Cancelled
    monkeypatch.setenv("DCDI_CACHE_DIR", str(tmp_path / "empty"))
    opts = BokehOptions(focus_m=1.2, keep=(1.1, 1.3), geometry=geom, settings=replace(fast, kernel_size=15))
    with pytest.raises(Cancelled):
        bokeh(img, depth, lens, opts, cancelled=lambda: True)
    seen = {}
    for large_blur in (False, True):                   # the fine bins (cached by now) and then the coarse ones
        monkeypatch.setenv("DCDI_CACHE_DIR", str(tmp_path / f"empty-{large_blur}"))
        seen[large_blur] = []
        bokeh(img, depth, lens, replace(opts, large_blur=large_blur),
              progress=lambda done, total, out=seen[large_blur]: out.append((done, total)))
    assert len(seen[True]) > len(seen[False]) and seen[True][-1][0] == seen[True][-1][1]


def test_a_ray_maps_large_blur_takes_its_coarse_psfs_from_the_map(monkeypatch):
    """A library served by a ray map (a catalogue lens) blurs a layer its
    kernel clips at reduced resolution with coarse PSFs from the same map:
    nothing is traced, and a constant image stays constant."""
    import dcdi_core.psf.library as psf_library
    from dcdi_core.psf.raymap import RayMapLibrary, open_raymap
    from dcdi_core.shipped import raymap_file as shipped_raymap
    lens = load_lens("zeiss-jena-tessar-50mm-f2-8")
    geom = ImageGeometry.from_pixel_pitch(lens, 64, 96, 0.02, center_px=(31.5, 47.5))
    lib = RayMapLibrary(open_raymap(shipped_raymap(lens.id)), lens,
                        PSFSettings(kernel_size=15, pupil_samples=24, n_wavelengths=3, pixel_pitch_mm=0.02,
                                    focus_distance_m=1.2))
    monkeypatch.setattr(psf_library, "MAX_FITTED_KERNEL", 15)

    def no_trace(*a, **k):
        raise AssertionError("traced")
    monkeypatch.setattr("dcdi_core.psf.library.compute_sources", no_trace)
    depth = np.full((64, 96), 10.0, np.float32)
    depth[20:44, 30:66] = 1.2
    out = bokeh(np.full((64, 96, 3), 0.5, np.float32), depth, lens,
                BokehOptions(focus_m=1.2, keep=(1.1, 1.3), geometry=geom), library=lib)
    assert out.info["large_blur_factor"] >= 2
    assert np.abs(out.image - 0.5).max() < 2e-3


def test_coarse_layers_blur_a_wide_blur_at_reduced_resolution_close_to_the_full_one(monkeypatch, tmp_path):
    """BokehOptions.coarse_blur (the error budget's coarse layers): the far
    background, whose every kernel holds half its energy well beyond the
    rule's radius, is blurred at 1/f of the resolution with PSFs made at f
    times the pitch; the result stays close to every layer at full
    resolution (lights' discs included), the sharp subject is untouched, a
    constant image stays constant, and a rule no layer reaches changes
    nothing."""
    from dcdi_core.psf.raymap import RayMapLibrary, open_raymap
    from dcdi_core.shipped import raymap_file as shipped_raymap
    monkeypatch.setenv("DCDI_CACHE_DIR", str(tmp_path))
    lens = load_lens("zeiss-sonnar-50mm-f1-5")
    geom = ImageGeometry.from_pixel_pitch(lens, 96, 128, 0.03, center_px=(47.5, 63.5))
    rng = np.random.default_rng(1)
    img = (0.1 + 0.3 * rng.random((96, 128, 3))).astype(np.float32)
    for y, x in ((15, 20), (20, 100), (80, 30)):
        img[y - 1:y + 2, x - 1:x + 2] = 5.0
    depth = np.full((96, 128), 10.0, np.float32)
    depth[30:66, 40:80] = 0.9
    lib = RayMapLibrary(open_raymap(shipped_raymap(lens.id)), lens,
                        PSFSettings(pupil_samples=16, n_wavelengths=3, kernel_size=61, pixel_pitch_mm=0.03,
                                    focus_distance_m=0.9), LibraryGrid(n_fields=8))

    def run(image=img, **kw):
        return bokeh(image, depth, lens, BokehOptions(focus_m=0.9, keep=(0.85, 0.95), geometry=geom, **kw),
                     library=lib)
    full = run().image
    coarse = run(coarse_blur=2.0)
    assert coarse.info.get("coarse_blur_layers", 0) >= 1
    psnr = -10 * np.log10(np.mean((coarse.image / 5.0 - full / 5.0) ** 2))
    assert 35 < psnr < 200, psnr
    assert np.abs(coarse.image - img)[34:62, 44:76].max() < 1e-5          # the subject, in focus, as it was
    flat = run(np.full_like(img, 0.5), coarse_blur=2.0).image
    assert np.abs(flat - 0.5).max() < 2e-3
    never = run(coarse_blur=1000.0)
    assert "coarse_blur_layers" not in never.info and np.array_equal(never.image, full)


@pytest.mark.parametrize("bad", [0.5, 0, -2.0, float("nan"), float("inf"), True, "4"])
def test_a_coarse_rule_that_means_nothing_is_refused(bad):
    with pytest.raises(Exception, match="coarse_blur"):
        BokehOptions(focus_m=2.0, coarse_blur=bad)
