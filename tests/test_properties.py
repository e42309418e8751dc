"""The engine's invariants on random inputs (hypothesis).

Profiles (tests/conftest.py): 'quick' in `python build.py test` (a few
examples each, derandomised: the same examples on every run), 'long' in
`python build.py test-slow` (hundreds, random). Each property also runs
against a planted bug (test_*_finds_a_planted_bug), so that a property that
cannot fail would show.

- every PSF is finite, non-negative and sums to one per channel (or is the
  zero kernel of a field the lens cannot image);
- a constant image stays constant through simulate, bokeh and the
  deconvolution;
- a kept range is bit-identical to the input (where no nearer object's
  blur reaches it);
- simulate never makes NaN or inf from finite input (any depth, NaN and
  negative included);
- a lens written and read back is the same lens;
- reading any file the CLI accepts (damaged EXR, PNG, TOML, .zmx bytes)
  works or raises one of the project's errors, never another exception.
"""
import math
import tomllib
import warnings
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from dcdi_core.errors import DcdiError
from dcdi_core.optics.lens import Lens, load_lens
from dcdi_core.psf.compute import PSFSettings

pytestmark = pytest.mark.property
ROOT = Path(__file__).resolve().parents[1]
TINY = PSFSettings(pupil_samples=8, n_wavelengths=3, kernel_size=11)
H, W = 32, 48
FIXTURES = [HealthCheck.function_scoped_fixture, HealthCheck.too_slow]


# ------------------------------------------------------------------ PSFs
def check_psf(kernel, zero_energy):
    k = np.asarray(kernel, np.float64)
    assert np.isfinite(k).all() and (k >= 0).all()
    sums = k.sum(axis=(-1, -2))
    if zero_energy:
        assert (sums == 0).all()
    else:
        assert np.allclose(sums, 1.0, atol=1e-5), sums


@given(lens_id=st.sampled_from(["mos-s1", "mos-s2", "6p", "double-gauss"]),
       field=st.floats(0.0, 1.2), depth=st.one_of(st.floats(0.05, 1e4), st.just(math.inf)),
       kernel=st.sampled_from([1, 3, 9, 21]))
@settings(suppress_health_check=FIXTURES)
def test_every_psf_is_non_negative_and_sums_to_one(lens_id, field, depth, kernel):
    from dcdi_core.psf.compute import psf
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")                 # the kernel-clips warning: the energy is renormalised
        b = psf(load_lens(lens_id), depth_m=depth, field=field,
                settings=PSFSettings(pupil_samples=8, n_wavelengths=3, kernel_size=kernel))
    check_psf(b.psf, bool(b.zero_energy))


def test_the_psf_property_finds_a_planted_bug():
    k = np.full((3, 5, 5), 1 / 25, np.float32)
    check_psf(k, False)
    k[1, 2, 2] += 0.01                                  # planted: one channel not normalised
    with pytest.raises(AssertionError):
        check_psf(k, False)


# ------------------------------------------------------------------ constant images
@pytest.fixture(scope="module")
def library():
    from dcdi_core.render.geometry import ImageGeometry
    from dcdi_core.psf.sources import open_library
    lens = load_lens("mos-s1")
    geom = ImageGeometry.full_sensor(lens, H, W)
    return lens, geom, open_library(lens, geom, TINY)


depths = st.lists(st.one_of(st.floats(0.3, 50.0), st.just(math.inf), st.just(math.nan), st.just(-1.0),
                            st.just(0.0)), min_size=4, max_size=4)


def depth_map(values, seed):
    """A (H, W) map of four patch-aligned blocks of ``values``, jittered."""
    rng = np.random.default_rng(seed)
    d = np.empty((H, W))
    for i, v in enumerate(values):
        d[(i // 2) * H // 2:(i // 2 + 1) * H // 2, (i % 2) * W // 2:(i % 2 + 1) * W // 2] = v
    return d * rng.uniform(0.9, 1.1, d.shape)


def constant_stays(run, value, depth):
    img = np.full((H, W, 3), value, np.float32)
    out = run(img, depth)
    assert np.isfinite(out).all()
    inner = out[8:-8, 8:-8]                             # the border reflects: constant too, but kept apart
    assert np.abs(inner - value).max() <= 1e-4 * max(1.0, value), np.abs(inner - value).max()


def _runs(library):
    from dcdi_core.correct import DeconvOptions, deconvolve
    from dcdi_core.render.bokeh import BokehOptions, bokeh
    from dcdi_core.render.simulate import SimulateOptions, simulate
    lens, geom, lib = library
    return {"simulate": lambda i, d: simulate(i, d, lens, SimulateOptions(geometry=geom, distortion=False),
                                              library=lib).image,
            "bokeh": lambda i, d: bokeh(i, d, lens, BokehOptions(keep=(1.0, 1.2), geometry=geom), library=lib).image,
            "deconvolution": lambda i, d: deconvolve(i, d, lens, DeconvOptions(), geometry=geom,
                                                     library=lib).image}


@given(value=st.floats(0.0, 50.0), values=depths, seed=st.integers(0, 2 ** 16),
       job=st.sampled_from(["simulate", "bokeh", "deconvolution"]))
@settings(suppress_health_check=FIXTURES)
def test_a_constant_image_stays_constant(library, value, values, seed, job):
    depth = depth_map(values, seed)
    assume((depth > 0).any())
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        constant_stays(_runs(library)[job], value, depth)


def test_the_constant_property_finds_a_planted_bug(library):
    run = _runs(library)["simulate"]
    depth = depth_map([0.8, 2.0, 5.0, 20.0], 0)
    constant_stays(run, 0.5, depth)
    with pytest.raises(AssertionError):                # planted: a patch's blend weights off by 0.1 %
        constant_stays(lambda i, d: run(i, d) * np.where(np.arange(W) % 16 == 3, 1.001, 1.0)[None, :, None],
                       0.5, depth)


# ------------------------------------------------------------------ the kept range
def kept_is_input(library, img, depth, keep):
    """The kept pixels that no nearer blurred pixel's blur can reach (an
    occluding object's halo rightly covers the kept range) are the input's,
    bit for bit."""
    from scipy.ndimage import maximum_filter

    from dcdi_core.render.bokeh import BokehOptions, bokeh
    lens, geom, lib = library
    out = bokeh(img, depth, lens, BokehOptions(keep=keep, geometry=geom), library=lib).image
    kept = (depth >= keep[0]) & (depth <= keep[1])
    nearer = (depth > 0) & ~kept & (depth < keep[1])
    reach = 2 * (lib.kernel_size // 2 + 2) + 1          # the kernel's radius (and a pixel of resampling)
    free = kept & ~maximum_filter(nearer, size=reach)
    np.testing.assert_array_equal(out[free], img[free])
    return out


@given(values=depths, seed=st.integers(0, 2 ** 16), near=st.floats(0.5, 10.0), span=st.floats(0.0, 5.0))
@settings(suppress_health_check=FIXTURES)
def test_the_kept_range_is_bit_identical_to_the_input(library, values, seed, near, span):
    depth = depth_map(values, seed)
    assume((depth > 0).any())
    img = np.random.default_rng(seed).uniform(0.0, 4.0, (H, W, 3)).astype(np.float32)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        kept_is_input(library, img, depth, (near, near + span))


def test_the_kept_range_property_finds_a_planted_bug(library, monkeypatch):
    from dcdi_core.render import bokeh as module
    depth = depth_map([1.0, 1.1, 5.0, 20.0], 0)
    img = np.random.default_rng(0).uniform(0, 1, (H, W, 3)).astype(np.float32)
    kept_is_input(library, img, depth, (0.8, 1.2))
    real = module._BokehScene.result

    def a_hair_brighter(self, image, info, pm=None):      # planted: the output off by a float32 step
        return real(self, np.nextafter(image, np.float32(np.inf)), info, pm)
    monkeypatch.setattr(module._BokehScene, "result", a_hair_brighter)
    with pytest.raises(AssertionError):
        kept_is_input(library, img, depth, (0.8, 1.2))


# ------------------------------------------------------------------ no NaN from finite input
@given(scale=st.floats(0.0, 1e4), values=depths, seed=st.integers(0, 2 ** 16), distortion=st.booleans())
@settings(suppress_health_check=FIXTURES)
def test_simulate_never_makes_nan_or_inf_from_finite_input(library, scale, values, seed, distortion):
    from dcdi_core.errors import RenderError
    from dcdi_core.render.simulate import SimulateOptions, simulate
    lens, geom, lib = library
    img = (np.random.default_rng(seed).uniform(0.0, 1.0, (H, W, 3)) * scale).astype(np.float32)
    depth = depth_map(values, seed)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            r = simulate(img, depth, lens, SimulateOptions(geometry=geom, distortion=distortion), library=lib)
    except RenderError:                                 # no valid depth at all: refused by name
        assert not (depth > 0).any()
        return
    assert np.isfinite(r.image).all() and (r.image >= 0).all()


# ------------------------------------------------------------------ lens files
def _shipped(lens_id):
    return tomllib.loads((ROOT / "lenses" / f"{lens_id}.toml").read_text())


@given(lens_id=st.sampled_from(["mos-s1", "mos-s2", "6p", "double-gauss"]), scale=st.floats(0.98, 1.02),
       t_scale=st.floats(1.0, 1.02))
@settings(suppress_health_check=FIXTURES)
def test_a_lens_written_and_read_back_is_the_same_lens(tmp_path_factory, lens_id, scale, t_scale):
    from dcdi_core.optics.zemax import write_toml
    from dcdi_core.optics.lens import lens_fingerprint
    d = _shipped(lens_id)
    for s in d["surface"]:                              # a nearby prescription, radii and gaps changed
        if isinstance(s["radius_mm"], float) and math.isfinite(s["radius_mm"]):
            s["radius_mm"] *= scale
        s["thickness_mm"] *= t_scale
    try:
        lens = Lens.from_dict(d)
    except DcdiError:
        return                                          # refused as a dict: nothing to round-trip
    path = write_toml(d, tmp_path_factory.mktemp("lens") / f"{lens_id}.toml")
    assert lens_fingerprint(Lens.from_toml(path)) == lens_fingerprint(lens)


# ------------------------------------------------------------------ damaged files
def _valid_files(folder: Path) -> dict:
    from dcdi_core.io.images import write_depth, write_image
    img = np.random.default_rng(0).uniform(0, 1, (6, 8, 3)).astype(np.float32)
    write_image(folder / "a.exr", img)
    write_depth(folder / "d.exr", img[..., 0] + 1)
    try:
        write_image(folder / "a.png", img)
    except DcdiError:
        pass                                            # no OpenImageIO: PNG is refused by name anyway
    zmx = ("VERS 190513 80 123457\nMODE SUDA 0 0\nUNIT MM X W X CM MR CPMM\nSURF 0\n  TYPE STANDARD\n"
           "  CURV 0.0\n  DISZ INFINITY\nSURF 1\n  STOP\n  TYPE STANDARD\n  CURV 0.02\n  DISZ 5\n"
           "  GLAS N-BK7 0 0 1.5168 64.17\n  DIAM 10\nSURF 2\n  TYPE STANDARD\n  CURV 0\n  DISZ 45\n"
           "  DIAM 10\nSURF 3\n  TYPE STANDARD\n  CURV 0\n  DIAM 5\n")
    (folder / "l.zmx").write_text(zmx)
    return {p.suffix + ("-depth" if p.name == "d.exr" else ""): p.read_bytes() for p in folder.iterdir()} | {
        ".toml": (ROOT / "lenses" / "mos-s1.toml").read_bytes()}


def read_any(kind: str, path: Path) -> None:
    """What the CLI does with a file of ``kind``; a project error is fine."""
    from dcdi_core.io.images import read_depth, read_image
    from dcdi_core.optics.zemax import read_zmx
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            if kind == ".exr-depth":
                read_depth(path)
            elif kind in (".exr", ".png"):
                read_image(path)
            elif kind == ".toml":
                load_lens(path)
            else:
                Lens.from_dict(read_zmx(path), path)
    except DcdiError:
        pass


@st.composite
def damage(draw, data: bytes):
    """``data`` with a few bytes changed, cut short, or grown."""
    b = bytearray(data)
    how = draw(st.sampled_from(["flip", "cut", "grow", "zero"]))
    if how == "cut":
        return bytes(b[:draw(st.integers(0, len(b)))])
    if how == "grow":
        return bytes(b) + draw(st.binary(min_size=1, max_size=64))
    for _ in range(draw(st.integers(1, 8))):
        i = draw(st.integers(0, len(b) - 1))
        b[i] = 0 if how == "zero" else draw(st.integers(0, 255))
    return bytes(b)


_FILES: dict = {}


@given(data=st.data(), kind=st.sampled_from([".exr", ".exr-depth", ".png", ".toml", ".zmx"]))
@settings(suppress_health_check=FIXTURES)
def test_a_damaged_file_is_read_or_refused_with_a_project_error(tmp_path_factory, data, kind):
    if not _FILES:
        _FILES.update(_valid_files(tmp_path_factory.mktemp("valid")))
    assume(kind in _FILES)
    bad = data.draw(damage(_FILES[kind]))
    path = tmp_path_factory.mktemp("damaged") / ("f" + kind.split("-")[0])
    path.write_bytes(bad)
    read_any(kind, path)


def test_the_damaged_file_property_finds_a_planted_bug(tmp_path, monkeypatch):
    from dcdi_core.io import rawexr
    files = _valid_files(tmp_path)
    (tmp_path / "cut.exr").write_bytes(files[".exr"][:200])
    read_any(".exr", tmp_path / "cut.exr")

    def careless(*a, **k):                              # planted: a reader that lets struct.error out
        import struct
        raise struct.error("unpack requires a buffer of 4 bytes")
    monkeypatch.setattr(rawexr.ExrFile, "_parse", careless)
    monkeypatch.setattr("dcdi_core.io.images._oiio", lambda: None)
    with pytest.raises(Exception) as e:
        read_any(".exr", tmp_path / "cut.exr")
    assert not isinstance(e.value, DcdiError)
