"""The Omni-Lens-Field as a PSF source: the OLF-backed library the renderer is
handed, the choice between the OLF and tracing (`--psf-source`), and
`dcdi psf / simulate / bokeh` served by it."""
import json
import math
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from dcdi_core.cli import main
from lab.cli import main as lab_main
from dcdi_core.io.images import read_image, write_depth, write_image
from dcdi_core.models import ModelError
from dcdi_core.psf.sources import OLFLibrary, psf_source
from dcdi_core.psf.olf import OmniLensField
from dcdi_core.optics.lens import load_lens
from dcdi_core.psf.compute import PSFSettings
from dcdi_core.render.geometry import ImageGeometry
from dcdi_core.render.psfmap import psf_map
from dcdi_core.render.synthetic import synthetic_rgbd

torch = pytest.importorskip("torch")

ROOT = Path(__file__).resolve().parents[2]
FAST = dict(pupil_samples=16, n_wavelengths=3, n_fields=3, n_depths=2, offgrid=6, held_out=4)
# the PSF settings that OLF learned, as command-line options
LEARNED = ["--rays", "16", "--wavelengths", "3"]
PITCH = 0.0122          # mm: the pixel pitch of mos-s1 and 6p


@pytest.fixture(autouse=True)
def no_basis(monkeypatch):
    """The OLF against tracing alone: no shipped PSF basis goes first (the
    basis's place in the choice: tests/psf/test_psf_basis.py)."""
    from dcdi_core.psf import sources as library
    monkeypatch.setattr(library, "shipped_store", lambda lens_id, focus_stack=False: None)


@pytest.fixture(scope="module")
def olf_file(tmp_path_factory):
    from dcdi_core.models.olf.data import PSFDataConfig
    from dcdi_core.models.olf.export import export_olf
    from dcdi_core.models.olf.config import OLFTrainConfig
    from dcdi_core.models.olf.train import train
    torch.set_num_threads(1)
    d = tmp_path_factory.mktemp("olf-source")
    config = OLFTrainConfig(data=PSFDataConfig(lenses=("mos-s1", "6p"), **FAST), size="tiny", iters=8, batch=16,
                            lr=3e-3, seed=0, threads=1)
    result = train(config, d / "run", cache_dir=d / "cache")
    export_olf(result, d / "olf.npz", dtype="float16")
    return d / "olf.npz", d / "cache"


@pytest.fixture
def cache_env(olf_file, monkeypatch):
    monkeypatch.setenv("DCDI_CACHE_DIR", str(olf_file[1]))
    return olf_file[0]


def _changed_lens_file(tmp_path) -> Path:
    """mos-s1's file with one radius changed by 1 % (same id)."""
    text = (ROOT / "lenses" / "mos-s1.toml").read_text()
    radii = [m for m in re.finditer(r"^radius_mm = (-?[0-9.]+)$", text, re.M)]
    m = radii[0]
    text = text[:m.start(1)] + repr(float(m.group(1)) * 1.01) + text[m.end(1):]
    path = tmp_path / "mos-s1.toml"
    path.write_text(text)
    return path


def test_olf_backed_library_serves_the_olf_at_its_grid(olf_file):
    path, _ = olf_file
    olf = OmniLensField.load(path)
    lens = load_lens("6p")
    lib = OLFLibrary(olf, lens)
    assert lib.kernel_size == olf.kernel_size("6p") and lib.pixel_pitch_mm == pytest.approx(PITCH)
    assert not lib.computed.any()                      # lazy: bins filled when asked for
    depths = np.array([0.7, 1.3, math.inf])
    got = lib.at(lib.fields[:, None], depths[None, :])
    # between bins: linear in diopters between the network's PSFs at the two neighbouring bins (weights by hand)
    dio, d = lib.diopters, 1.0 / 1.3
    i = int(np.nonzero(dio >= d)[0].max())
    w = (dio[i] - d) / (dio[i] - dio[i + 1])
    assert 0.05 < w < 0.95
    want = (1 - w) * olf.psf(lens, lib.fields, lib.depths_m[i]) + w * olf.psf(lens, lib.fields, lib.depths_m[i + 1])
    assert np.allclose(got[:, 1], want, atol=1e-5)
    assert got.min() >= 0 and np.abs(got.sum(axis=(-1, -2)) - 1).max() < 1e-5
    # the renderer takes it as it is; only the bins the depth map needs are run
    geom = ImageGeometry.from_pixel_pitch(lens, 48, 64, PITCH)
    lib2 = OLFLibrary(olf, lens)
    pm = psf_map(lib2, geom, np.full((48, 64), 2.0))
    assert pm.kernels.shape[-1] == lib.kernel_size and 0 < lib2.computed.sum() <= 2
    assert np.abs(pm.kernels.sum(axis=(-1, -2)) - 1).max() < 1e-5
    assert lib2.last_network_s > 0
    with pytest.raises(ModelError, match="not saved"):
        lib2.save(path.with_name("x.npz"))


def test_renderer_never_imports_models():
    for f in (ROOT / "dcdi_core" / "render").glob("*.py"):
        assert not re.search(r"^\s*(from|import)\s+[.\w]*models", f.read_text(), re.M), f


def test_source_is_the_olf_where_it_covers_the_request_else_tracing(olf_file, tmp_path, monkeypatch):
    path, _ = olf_file
    lens = load_lens("mos-s1")
    learned = PSFSettings(pupil_samples=16, n_wavelengths=3)
    src = psf_source(lens, olf_file=path, pixel_pitch_mm=PITCH, settings=learned)
    assert src.kind == "olf" and isinstance(src.library, OLFLibrary) and str(path) in src.message
    # each way of not being covered: traced, saying why
    changed = load_lens(_changed_lens_file(tmp_path))
    cases = [(changed, {}, "differs optically"), (load_lens("mos-s2"), {}, "did not learn lens 'mos-s2'"),
             (lens, {"pixel_pitch_mm": 0.006}, "pixel pitch 6 um is finer"),
             (lens, {"focus_m": 2.0}, "prescribed focus only"),
             (lens, {"settings": PSFSettings()}, "pupil_samples 64 .it learned 16"),
             (lens, {"kernel_size": 15}, "15 px kernel"),
             (lens, {"custom_response": True}, "spectral response")]
    for l_, kw, why in cases:
        kw = {"pixel_pitch_mm": PITCH, "settings": learned} | kw
        src = psf_source(l_, olf_file=path, **kw)
        assert src.kind == "trace" and src.library is None and re.search(why, src.message), (why, src.message)
        with pytest.raises(ModelError, match="psf_source olf.*" + why):
            psf_source(l_, olf_file=path, source="olf", **kw)
    # a coarser pitch: served, its kernels area-resampled (tests/psf/test_psf_pitch.py)
    src = psf_source(lens, olf_file=path, pixel_pitch_mm=0.05, settings=learned)
    assert src.kind == "olf" and "50 um pixels" in src.message and "area-resampled" in src.message
    assert psf_source(lens, olf_file=path, source="trace").kind == "trace"
    # no OLF at all (none shipped, none given): tracing, saying so
    import dcdi_core.psf.sources as runtime_library
    monkeypatch.setattr(runtime_library, "SHIPPED", tmp_path / "none-shipped.npz")
    monkeypatch.setattr(runtime_library, "olf_rays_file", lambda: None)
    src = psf_source(lens, olf_file=None, pixel_pitch_mm=PITCH, settings=learned)
    assert src.kind == "trace" and src.library is None and "no OLF file ships" in src.message


def test_cli_psf_from_the_olf_has_the_traced_form(cache_env, tmp_path, capsys):
    path = cache_env
    olf = OmniLensField.load(path)
    argv = ["psf", "mos-s1", "--field", "0.5", "--depth", "2", *LEARNED, "--olf", str(path)]
    assert main(argv + ["--psf-source", "olf", "--out", str(tmp_path / "olf.npz"), "--json"]) == 0
    out = capsys.readouterr()
    assert json.loads(out.out)["psf_source"] == "olf" and "Omni-Lens-Field" in out.err
    assert main(argv + ["--psf-source", "trace", "--kernel", str(olf.kernel_size("mos-s1")),
                        "--out", str(tmp_path / "trace.npz")]) == 0
    capsys.readouterr()
    with np.load(tmp_path / "olf.npz") as a, np.load(tmp_path / "trace.npz") as b:
        assert a.files == b.files and a["psf"].shape == b["psf"].shape and a["psf"].dtype == b["psf"].dtype
        assert float(a["pixel_pitch_mm"]) == pytest.approx(float(b["pixel_pitch_mm"]))
        assert np.allclose(a["psf"], olf.psf(load_lens("mos-s1"), 0.5, 2.0), atol=1e-6)
    # default: the OLF where it covers; other settings or a depth outside its range: traced, said why
    assert main(argv) == 0 and "from the Omni-Lens-Field" in capsys.readouterr().err
    assert main(argv[:-4] + ["--olf", str(path)]) == 0
    assert "n_wavelengths 31 (it learned 3)" in capsys.readouterr().err
    assert main(["psf", "mos-s1", "--field", "0.5", "--depth", "0.5", *LEARNED, "--olf", str(path)]) == 0
    assert "traced instead" in capsys.readouterr().err
    assert main(["psf", "mos-s1", "--field", "0.5", "--depth", "0.5", *LEARNED, "--olf", str(path),
                 "--psf-source", "olf"]) == 2
    assert "depth_m = 0.5" in capsys.readouterr().err


def test_cli_changed_prescription_is_traced_not_served(cache_env, tmp_path, capsys):
    changed = _changed_lens_file(tmp_path)
    argv = ["psf", str(changed), "--field", "0.5", "--depth", "2", *LEARNED, "--olf", str(cache_env)]
    assert main(argv) == 0
    err = capsys.readouterr().err
    assert "PSFs traced" in err and "differs optically" in err and "not served" in err
    assert main(argv + ["--psf-source", "olf"]) == 2
    assert "differs optically" in capsys.readouterr().err


def test_cli_simulate_and_bokeh_served_by_the_olf(cache_env, tmp_path, capsys):
    img, _ = synthetic_rgbd(48, 64, seed=2)
    depth = np.where(np.arange(64)[None, :] < 32, 1.2, 1e10) * np.ones((48, 1))   # few depth bins to trace
    write_image(tmp_path / "aif.exr", img)
    write_depth(tmp_path / "depth.exr", depth)
    common = ["--image", str(tmp_path / "aif.exr"), "--depth", str(tmp_path / "depth.exr"),
              "--image-pixel-pitch", str(PITCH), *LEARNED, "--olf", str(cache_env)]
    assert main(["simulate", "--lens", "mos-s1", "-o", str(tmp_path / "s.exr"), "--no-distortion", *common]) == 0
    out = capsys.readouterr()
    assert json.loads(out.out)["psf_source"] == "olf" and "Omni-Lens-Field" in out.err
    assert main(["simulate", "--lens", "mos-s1", "-o", str(tmp_path / "t.exr"), "--no-distortion", *common,
                 "--psf-source", "trace", "--kernel", str(OmniLensField.load(cache_env).kernel_size("mos-s1"))]) == 0
    assert json.loads(capsys.readouterr().out)["psf_source"] == "trace"
    s, t = read_image(tmp_path / "s.exr"), read_image(tmp_path / "t.exr")
    assert s.shape == img.shape and np.isfinite(s).all() and np.abs(s - t).mean() < 0.05
    assert main(["bokeh", "--lens", "6p", "--keep", "1.1", "1.3", "-o", str(tmp_path / "b.exr"), *common]) == 0
    assert json.loads(capsys.readouterr().out)["psf_source"] == "olf"
    # a focus distance the OLF did not learn: traced, said why
    assert main(["bokeh", "--lens", "6p", "--focus", "2", "-o", str(tmp_path / "f.exr"), *common]) == 0
    out = capsys.readouterr()
    assert json.loads(out.out)["psf_source"] == "trace" and "prescribed focus only" in out.err


@pytest.fixture(scope="module")
def focus_olf_file(olf_file):
    """The olf_file's lenses with the 6P learned across focus (0.7 m to inf, 3 bins, and its prescribed focus)."""
    from dcdi_core.models.olf.data import PSFDataConfig
    from dcdi_core.models.olf.export import export_olf
    from dcdi_core.models.olf.config import OLFTrainConfig
    from dcdi_core.models.olf.train import train
    path, cache = olf_file
    config = OLFTrainConfig(data=PSFDataConfig(lenses=("mos-s1", "6p"), focus_lenses=("6p",), **FAST), size="tiny",
                            iters=4, batch=16, lr=3e-3, seed=0, threads=1)
    result = train(config, path.parent / "focus-run", cache_dir=cache)
    export_olf(result, path.parent / "focus.npz", dtype="float16")
    return path.parent / "focus.npz"


def test_cli_bokeh_refocused_is_served_by_an_olf_that_learned_focus(focus_olf_file, olf_file, monkeypatch, tmp_path,
                                                                     capsys):
    monkeypatch.setenv("DCDI_CACHE_DIR", str(olf_file[1]))
    img, _ = synthetic_rgbd(48, 64, seed=2)
    depth = np.where(np.arange(64)[None, :] < 32, 1.2, 1e10) * np.ones((48, 1))
    write_image(tmp_path / "aif.exr", img)
    write_depth(tmp_path / "depth.exr", depth)
    common = ["--image", str(tmp_path / "aif.exr"), "--depth", str(tmp_path / "depth.exr"),
              "--image-pixel-pitch", str(PITCH), *LEARNED, "--olf", str(focus_olf_file)]
    for focus, kind, said in (("2", "olf", "focus 2 m"), ("prescribed", "olf", "prescribed focus"),
                              ("0.5", "trace", "outside the learned 0.7 m to inf m")):
        assert main(["bokeh", "--lens", "6p", "--focus", focus, "-o", str(tmp_path / f"b{focus}.exr"), *common]) == 0
        out = capsys.readouterr()
        assert json.loads(out.out)["psf_source"] == kind and said in out.err, out.err
    assert main(["bokeh", "--lens", "6p", "--keep", "1.1", "1.3", "-o", str(tmp_path / "k.exr"), *common]) == 0
    assert json.loads(capsys.readouterr().out)["psf_source"] == "olf"


def test_olf_info_lists_shipped_files(capsys):
    assert main(["olf", "info"]) == 0
    text = capsys.readouterr().out
    from dcdi_core.psf.sources import shipped_olf_files
    files = shipped_olf_files()
    if not files:
        assert "no OLF file ships" in text
    else:
        assert all(str(f) in text for f in files) and "held-out" in text


@pytest.mark.slow
def test_report_olf_quick(cache_env, tmp_path, capsys):
    assert lab_main(["report", "olf", "--olf", str(cache_env), "--quick", "--out", str(tmp_path)]) == 0
    data = json.loads((tmp_path / "olf.json").read_text())
    rec = data["files"][0]
    assert set(rec["fresh"]) == {"mos-s1", "6p"} and rec["map"]["network"] > 0
    assert rec["downstream"]["simulate"]["psnr_db"] > 10 and "bokeh" in rec["downstream"]
    assert (tmp_path / "olf-error-vs-storage.png").read_bytes()[:4] == b"\x89PNG"
    assert "| mos-s1 |" in (tmp_path / "olf.md").read_text()


def test_bundled_runtime_serves_psf_maps_with_torch_blocked(olf_file):
    code = f"""
import sys
sys.modules["torch"] = None
import numpy as np
from dcdi_core.psf.sources import OLFLibrary
from dcdi_core.psf.olf import OmniLensField
from dcdi_core.optics.lens import load_lens
from dcdi_core.render.geometry import ImageGeometry
from dcdi_core.render.psfmap import psf_map
lens = load_lens("6p")
lib = OLFLibrary(OmniLensField.load({str(olf_file[0])!r}), lens)
pm = psf_map(lib, ImageGeometry.from_pixel_pitch(lens, 32, 48, {PITCH}), np.full((32, 48), 3.0))
assert abs(pm.kernels.sum(axis=(-1, -2)) - 1).max() < 1e-5
print("ok")
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT,
                         env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"})
    assert out.returncode == 0 and out.stdout.strip().endswith("ok"), out.stderr
