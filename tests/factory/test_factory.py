"""The dataset factory with the pip bpy module: depth, round trip, determinism, resume."""
import json

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

from blender_addon.factory import batch as factory  # noqa: E402
from blender_addon.factory import blender, samples  # noqa: E402
from blender_addon.factory.options import parse  # noqa: E402
from blender_addon.factory.render import RenderSettings  # noqa: E402
from blender_addon.factory.settings import settings_differences  # noqa: E402
from dcdi_core.dataset.factory_folder import finished_ids, settings_from_manifest  # noqa: E402
from dcdi_core.io.images import read_depth, read_image  # noqa: E402

SMALL = ["--resolution", "24", "32", "--cycles-samples", "2", "--psf-rays", "12", "--psf-wavelengths", "3"]


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
        assert rec["seed"] == samples.sample_seed(5, rec["index"]) and "blender" in rec["versions"]
        assert rec["render"]["denoising_prefilter"] == RenderSettings().denoising_prefilter
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
    spec = importlib.util.spec_from_file_location("dcdi_build", Path(__file__).resolve().parents[2] / "build.py")
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
    from dcdi_core.render.simulate import SimulateOptions, LensSimulator, simulate

    lens = load_lens("mos-s1")
    rng = np.random.default_rng(3)
    img = rng.uniform(0, 1, (40, 56, 3)).astype(np.float32)
    depth = rng.uniform(0.7, 12.0, (40, 56)).astype(np.float32)
    depth[:8, :8] = np.inf
    geom = ImageGeometry.full_sensor(lens, 40, 56)
    sim = LensSimulator(lens, SimulateOptions(geometry=geom, settings=PSFSettings(pupil_samples=12, n_wavelengths=3), baseline_depth_m=2.0))
    r = sim(img, depth)
    aware = simulate(img, depth, lens, SimulateOptions(geometry=sim.geometry), library=sim.library)
    plain = simulate(img, depth, lens, SimulateOptions(geometry=sim.geometry), library=sim.library, fixed_depth_m=2.0)
    assert np.array_equal(r.image, aware.image) and np.array_equal(r.sharp, aware.sharp)
    assert np.array_equal(r.baseline, plain.image)
    assert r.info["patches"] == aware.info["patches"]


def test_render_settings_refuse_bad_values():
    with pytest.raises(ValueError, match="denoising quality must be HIGH, BALANCED or FAST"):
        RenderSettings(denoising_quality="ULTRA")
    with pytest.raises(ValueError, match=r"diffuse bounces must be an integer in \[0, 1024\]"):
        RenderSettings(diffuse_bounces=-1)


def test_band_fractions():
    from blender_addon.tools.depth_histogram import BANDS, band_fractions
    d = np.array([0.5, 0.7, 0.99, 1.0, 3.0, 7.0, 10.0, 50.0, np.inf, np.inf])
    f = band_fractions(d)
    assert dict(zip(BANDS, f.round(2))) == {"<0.7": 0.1, "0.7-1": 0.2, "1-2": 0.1, "2-5": 0.1, "5-10": 0.1,
                                            ">10": 0.2, "inf": 0.2}
    with pytest.raises(ValueError, match="must be > 0 m or inf"):
        band_fractions(np.array([1.0, np.nan]))


def test_recipes_cover_the_depth_bands():
    # the paper's data spans 0.7 m to beyond 10 m: pooled over the three recipes every band from
    # 0.7 m on holds a share of the pixels; the indoor recipes keep most of theirs at 1-5 m, as
    # indoor RGB-D data does, and reach closer than 1 m; the street reaches beyond 10 m
    from blender_addon.tools.depth_histogram import BANDS, depth_histogram
    hist = depth_histogram(seeds=3, height=48, width=64)
    pooled = dict(zip(BANDS, np.mean([f for f, _, _ in hist.values()], axis=0)))
    assert pooled["<0.7"] < 0.01
    assert all(pooled[b] > 0.03 for b in BANDS[1:-1]), pooled
    for indoor in ("room", "tabletop"):
        bands = dict(zip(BANDS, hist[indoor][0]))
        assert bands["1-2"] + bands["2-5"] >= 0.6, (indoor, bands)
        assert hist[indoor][2][0] < 1.0
    assert hist["street"][0][-2] + hist["street"][0][-1] > 0.2      # beyond 10 m


def test_too_old_blender_is_refused_by_name(monkeypatch, capsys):
    monkeypatch.setattr(blender, "MIN_BLENDER", (99, 0, 0))
    with pytest.raises(SystemExit, match=r"is too old: the factory needs Blender >= 99\.0\.0") as info:
        blender.check_blender()
    assert info.value.code == 2                      # as every refusal of the factory
    err = capsys.readouterr().err
    assert err.startswith("factory: error: Blender ") and err.count("\n") == 1


# ------------------------------------------------------------------ refusals, resume, repair (issue 11)
def _refused(capsys, out, *args, says):
    import time
    t = time.perf_counter()
    code = factory.run(["--out", str(out), *args])
    dt = time.perf_counter() - t
    err = capsys.readouterr().err.strip()
    assert code == 2 and err.startswith("factory: error:") and "\n" not in err and "Traceback" not in err, err
    for s in says:
        assert s in err, err
    return err, dt


@pytest.mark.parametrize("args, says", [
    (["--recipe", "kitchen"], ["--recipe", "'kitchen'", "room, tabletop, street, leaves, plane"]),
    (["--recipe", "room", "--lens", "no-such-lens"], ["no lens 'no-such-lens'", "mos-s1"]),
    (["--recipe", "room", "--resolution", "0", "0"], ["--resolution", "'0 0'", "from 4 to 65536"]),
    (["--recipe", "room", "--count", "-1"], ["--count", "-1", ">= 0"]),
    (["--recipe", "room", "--shard", "2/2"], ["--shard", "'2/2'", "0 <= I < N"]),
    (["--recipe", "room", "--cycles-samples", "0"], ["--cycles-samples", "[1, 65536]"]),
    (["--recipe", "room", "--psf-rays", "100000"], ["--rays 100000", "GiB", "lower --rays"]),
])
def test_bad_arguments_are_refused_in_one_line_and_leave_no_folder(tmp_path, capsys, args, says):
    out = tmp_path / "new" / "ds"
    full = [*args, "--count", "2"] if "--count" not in args else args
    _, dt = _refused(capsys, out, *full, says=says)
    assert not (tmp_path / "new").exists() and dt < 1.0


def test_an_out_that_is_a_file_or_read_only_is_refused(tmp_path, capsys, monkeypatch):
    f = tmp_path / "file"
    f.write_text("x")
    _refused(capsys, f, "--recipe", "room", "--count", "1", says=[str(f), "--out must be a folder"])
    assert f.read_text() == "x"
    ro = tmp_path / "ro"
    ro.mkdir()
    real = __import__("os").access
    monkeypatch.setattr("os.access", lambda p, mode: False if str(p) == str(ro) else real(p, mode))
    _refused(capsys, ro / "ds", "--recipe", "room", "--count", "1", says=[str(ro), "not writable"])
    assert list(ro.iterdir()) == []


def test_a_failed_first_sample_leaves_no_folder(tmp_path, capsys, monkeypatch):
    from dcdi_core.errors import RenderError

    def broken(*a, **k):
        raise RenderError("the scene could not be rendered")
    monkeypatch.setattr(samples, "render_rgbd", broken)
    out = tmp_path / "ds"
    _refused(capsys, out, "--recipe", "tabletop", "--count", "1", *SMALL, says=["could not be rendered"])
    assert not out.exists()


def test_resume_with_other_settings_is_refused_by_name(tmp_path, capsys):
    assert _run(tmp_path, count=1) == 0
    before = (tmp_path / "manifest.jsonl").read_bytes()
    settings = json.loads((tmp_path / "dataset.json").read_text())
    assert settings["resolution"] == [24, 32] and settings["lenses"] == ["mos-s1"] and settings["seed"] == 5
    capsys.readouterr()

    def args(**over):
        a = {"--recipe": "tabletop", "--count": "2", "--seed": "5", "--lens": "mos-s1", "--resolution": "24 32",
             "--cycles-samples": "2", "--psf-rays": "12", "--psf-wavelengths": "3"}
        a.update({"--" + k.replace("_", "-"): v for k, v in over.items()})
        return [x for k, v in a.items() for x in (k, *v.split())]
    for over, says in [({"lens": "mos-s2"}, "--lens: the folder mos-s1, this run mos-s2"),
                       ({"resolution": "24 40"}, "--resolution: the folder 24 32, this run 24 40"),
                       ({"cycles_samples": "3"}, "--cycles-samples: the folder 2, this run 3"),
                       ({"seed": "6"}, "--seed: the folder 5, this run 6"),
                       ({"psf_rays": "10"}, "--psf-rays: the folder 12, this run 10")]:
        _refused(capsys, tmp_path, *args(**over), says=[says, "Rerun with the folder's settings"])
    err, _ = _refused(capsys, tmp_path, *args(seed="6", resolution="24 40"),
                      says=["--seed: the folder 5, this run 6", "--resolution: the folder 24 32"])
    assert (tmp_path / "manifest.jsonl").read_bytes() == before
    assert _run(tmp_path, count=2) == 0                 # the same settings (a larger count) resume


def test_torn_manifest_record_is_repaired_and_stale_temporaries_removed(tmp_path, capsys):
    assert _run(tmp_path, count=2) == 0
    manifest = tmp_path / "manifest.jsonl"
    lines = manifest.read_text().splitlines(keepends=True)
    manifest.write_text(lines[0] + lines[1][:len(lines[1]) // 2])          # killed while appending the 2nd
    stale = [tmp_path / "aif" / ".tabletop-000001.exr.k3j2x9qa.tmp.exr", tmp_path / ".tabletop-000001.render.exr"]
    for p in stale:
        p.write_bytes(b"partial")
    keep = tmp_path / "aif" / ".notes"                                       # not a temporary of the run
    keep.write_text("mine")
    assert finished_ids(manifest) == {"tabletop-000000"}
    capsys.readouterr()
    assert _run(tmp_path, count=2) == 0
    out = capsys.readouterr().out
    assert "dropped a torn last record" in out and "removed 2 stale temporary file(s)" in out
    assert "1 samples to do" in out
    recs = [json.loads(x) for x in manifest.read_text().splitlines()]
    assert [r["id"] for r in recs] == ["tabletop-000000", "tabletop-000001"]
    assert not any(p.exists() for p in stale) and keep.read_text() == "mine"


def test_a_folder_from_before_the_settings_record_is_compared_by_its_manifest():
    rec = {"id": "room-000000", "recipe": "room", "dataset_seed": 0, "resolution": [480, 640],
           "render": {"engine": "CYCLES", "samples": 8, "seconds": 3.2}, "psf_settings": {"pupil_samples": 64},
           "lenses": {"mos-s1": {"baseline_depth_m": 2.0}}}
    have = settings_from_manifest(rec)
    want = dict(have, resolution=[240, 320], render={"samples": 8}, lenses=["mos-s1", "6p"],
                shard="0/1", lens_fingerprints={})
    diffs = settings_differences(have, want)
    assert diffs == ["--lens: the folder mos-s1, this run mos-s1 6p",
                     "--resolution: the folder 480 640, this run 240 320"]


def test_a_second_run_into_the_same_folder_is_refused(tmp_path):
    from dcdi_core.errors import DatasetError
    lock = factory._lock(tmp_path)
    try:
        with pytest.raises(DatasetError, match="another factory run is writing into this folder"):
            factory._lock(tmp_path)
    finally:
        lock.close()
    factory._lock(tmp_path).close()                     # free again


def test_add_lens_simulates_a_new_lens_on_the_finished_samples(tmp_path, capsys):
    assert _run(tmp_path, count=1) == 0
    capsys.readouterr()
    two = ["--recipe", "tabletop", "--count", "2", "--lens", "mos-s1", "--lens", "mos-s2", "--out", str(tmp_path),
           "--seed", "5", *SMALL]
    assert factory.run(two) == 2
    assert "--add-lens" in capsys.readouterr().err                       # refused, with the way out named
    assert factory.run([*two, "--add-lens"]) == 0
    assert "adding mos-s2 to 1 finished samples" in capsys.readouterr().out
    recs = [json.loads(x) for x in (tmp_path / "manifest.jsonl").read_text().splitlines()]
    assert [sorted(r["lenses"]) for r in recs] == [["mos-s1", "mos-s2"]] * 2
    for sid in ("tabletop-000000", "tabletop-000001"):
        assert read_image(tmp_path / "mos-s2" / "aberrated" / f"{sid}.exr").shape == (24, 32, 3)
    assert json.loads((tmp_path / "dataset.json").read_text())["lenses"] == ["mos-s1", "mos-s2"]
    assert factory.run(two) == 0                                         # now the folder's own settings


def test_help_tells_images_from_render_samples(capsys):
    with pytest.raises(SystemExit):
        parse(["--help"])
    out = " ".join(capsys.readouterr().out.split())
    assert "--count N images in the whole dataset" in out and "--cycles-samples SPP Cycles render samples" in out
    assert "--samples" not in out.replace("--cycles-samples", "")


def test_the_module_runs_the_factory():
    import subprocess
    import sys
    from pathlib import Path
    root = Path(__file__).resolve().parents[2]
    p = subprocess.run([sys.executable, "-m", "blender_addon.factory", "--help"], cwd=root,
                       capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr
    assert "--recipe RECIPE" in p.stdout and "--cycles-samples SPP" in p.stdout


def test_the_samples_help_quotes_the_measured_default(capsys):
    """--cycles-samples' help gives the default's PSNR that docs/factory.md's
    render-noise table measures on today's scenes (its bold row), not an old figure."""
    import re
    from pathlib import Path
    table = (Path(__file__).resolve().parents[2] / "docs" / "factory.md").read_text()
    row = next(line for line in table.splitlines() if line.startswith("| **8** |"))
    db = re.findall(r"\*\*([\d.]+)\*\*", row)[1]
    with pytest.raises(SystemExit):
        parse(["--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert f"default 8: {db} dB" in text
