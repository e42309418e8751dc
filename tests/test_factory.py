"""The dataset factory with the pip bpy module: depth, round trip, determinism, resume."""
import json

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

from blender_addon.tools import factory  # noqa: E402
from dcdi_core.io.images import read_depth, read_image  # noqa: E402

SMALL = ["--resolution", "24", "32", "--samples", "2", "--psf-rays", "12", "--psf-wavelengths", "3"]


@pytest.fixture(autouse=True)
def cache(tmp_path_factory, monkeypatch):
    monkeypatch.setenv("DCDI_CACHE_DIR", str(tmp_path_factory.getbasetemp() / "psf-cache"))


def _run(out, *extra, recipe="tabletop", count=2):
    return factory.run(["--recipe", recipe, "--count", str(count), "--lens", "mos-s1", "--out", str(out),
                        "--seed", "5", *SMALL, *extra])


def test_depth_of_a_fronto_parallel_plane(tmp_path):
    assert _run(tmp_path, recipe="plane", count=1) == 0
    d = read_depth(tmp_path / "depth" / "plane-000000.exr")
    # the mos-s1 entrance pupil is its first vertex: depth = the plane's distance
    assert np.abs(d - 2.5).max() < 1e-4


def test_sample_round_trips_and_manifest(tmp_path):
    assert _run(tmp_path) == 0
    lines = [json.loads(x) for x in (tmp_path / "manifest.jsonl").read_text().splitlines()]
    assert [x["id"] for x in lines] == ["tabletop-000000", "tabletop-000001"]
    for rec in lines:
        img = read_image(tmp_path / "aif" / f"{rec['id']}.exr")
        depth = read_depth(tmp_path / "depth" / f"{rec['id']}.exr")
        assert img.shape == (24, 32, 3) and depth.shape == (24, 32)
        assert np.isfinite(img).all() and (depth > 0).all()
        for kind in ("aberrated", "baseline", "sharp"):
            assert read_image(tmp_path / "mos-s1" / kind / f"{rec['id']}.exr").shape == (24, 32, 3)
        assert rec["seed"] == factory.sample_seed(5, rec["index"]) and "blender" in rec["versions"]
        assert rec["render"]["denoising_prefilter"] == factory.RenderSettings().denoising_prefilter
        assert {"scene", "render", "read", "write", "simulate", "cpu_render"} <= rec["stage_seconds"].keys()


def _files(root):
    return {p.relative_to(root): p.read_bytes() for p in root.rglob("*.exr")}


def test_same_seed_same_bytes_and_resume_equals_uninterrupted(tmp_path, monkeypatch):
    a, b = tmp_path / "a", tmp_path / "b"
    assert _run(a, count=3) == 0
    monkeypatch.setenv("DCDI_FACTORY_STOP_AFTER", "1")
    assert _run(b, count=3) == 3                       # "killed" after one sample
    assert len((b / "manifest.jsonl").read_text().splitlines()) == 1
    monkeypatch.delenv("DCDI_FACTORY_STOP_AFTER")
    assert _run(b, count=3) == 0                       # the same command finishes the rest
    fa, fb = _files(a), _files(b)
    assert fa.keys() == fb.keys() and len(fa) == 15
    assert all(fa[k] == fb[k] for k in fa)
    ids = [json.loads(x)["id"] for x in (b / "manifest.jsonl").read_text().splitlines()]
    assert sorted(ids) == ["tabletop-000000", "tabletop-000001", "tabletop-000002"]
    assert not list(b.glob(".*"))                       # no temporary left behind


def test_shards_split_the_indices(tmp_path):
    assert _run(tmp_path, "--shard", "1/2", count=3) == 0
    ids = [json.loads(x)["id"] for x in (tmp_path / "manifest.jsonl").read_text().splitlines()]
    assert ids == ["tabletop-000001"]


@pytest.mark.slow
def test_bench_factory_quick(capsys):
    import importlib.util
    import sys
    from pathlib import Path
    spec = importlib.util.spec_from_file_location("dcdi_build", Path(__file__).resolve().parent.parent / "build.py")
    build = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(build)
    assert build.bench_factory(Path(sys.executable), quick=True) == 0
    assert "samples per hour" in capsys.readouterr().out


def test_render_noise_table_runs(capsys):
    from blender_addon.tools.render_noise import main
    assert main(["--resolution", "12", "16", "--reference", "8"]) == 0
    out = capsys.readouterr().out
    assert "| 4 | True | HIGH | ACCURATE | 2 |" in out and "| 6 | True | HIGH | NONE | 2 |" in out
    assert "| 8 | True | HIGH | ACCURATE | 2 | reference |" in out


def test_lens_simulator_equals_two_simulate_calls():
    # the simulator built once per lens (the factory's) must stay byte-equal to simulate() (depth-aware and baseline)
    from dcdi_core.optics.lens import load_lens
    from dcdi_core.psf.compute import PSFSettings
    from dcdi_core.render.geometry import ImageGeometry
    from dcdi_core.render.simulate import LensSimulator, simulate

    lens = load_lens("mos-s1")
    rng = np.random.default_rng(3)
    img = rng.uniform(0, 1, (40, 56, 3)).astype(np.float32)
    depth = rng.uniform(0.7, 12.0, (40, 56)).astype(np.float32)
    depth[:8, :8] = np.inf
    geom = ImageGeometry.full_sensor(lens, 40, 56)
    sim = LensSimulator(lens, geom, settings=PSFSettings(pupil_samples=12, n_wavelengths=3), baseline_depth_m=2.0)
    r = sim(img, depth)
    aware = simulate(img, depth, lens, geometry=sim.geometry, library=sim.library)
    plain = simulate(img, depth, lens, geometry=sim.geometry, library=sim.library, fixed_depth_m=2.0)
    assert np.array_equal(r.image, aware.image) and np.array_equal(r.sharp, aware.sharp)
    assert np.array_equal(r.baseline, plain.image)
    assert r.info["patches"] == aware.info["patches"]


def test_render_settings_refuse_bad_values():
    with pytest.raises(ValueError, match="denoising quality must be HIGH, BALANCED or FAST"):
        factory.RenderSettings(denoising_quality="ULTRA")
    with pytest.raises(ValueError, match=r"diffuse bounces must be an integer in \[0, 1024\]"):
        factory.RenderSettings(diffuse_bounces=-1)


def test_band_fractions():
    from blender_addon.tools.depth_histogram import BANDS, band_fractions
    d = np.array([0.5, 0.7, 0.99, 1.0, 3.0, 7.0, 10.0, 50.0, np.inf, np.inf])
    f = band_fractions(d)
    assert dict(zip(BANDS, f.round(2))) == {"<0.7": 0.1, "0.7-1": 0.2, "1-2": 0.1, "2-5": 0.1, "5-10": 0.1,
                                            ">10": 0.2, "inf": 0.2}
    with pytest.raises(ValueError, match="must be > 0 m or inf"):
        band_fractions(np.array([1.0, np.nan]))


def test_recipes_cover_the_depth_bands():
    # the paper's data spans 0.7 m to beyond 10 m: pooled over the three recipes every band
    # from 0.7 m to infinity holds a share of the pixels, and the room reaches closer than 1 m
    from blender_addon.tools.depth_histogram import BANDS, depth_histogram
    hist = depth_histogram(seeds=3, height=48, width=64)
    pooled = dict(zip(BANDS, np.mean([f for f, _, _ in hist.values()], axis=0)))
    assert pooled["<0.7"] < 0.01
    assert all(pooled[b] > 0.03 for b in BANDS[1:]), pooled
    assert hist["room"][2][0] < 1.0 and hist["room"][2][1] > 5.0
    assert hist["street"][0][-1] > 0.05                      # sky


def test_too_old_blender_is_refused_by_name(monkeypatch):
    monkeypatch.setattr(factory, "MIN_BLENDER", (99, 0, 0))
    with pytest.raises(SystemExit, match=r"is too old: the factory needs Blender >= 99\.0\.0"):
        factory.check_blender()
