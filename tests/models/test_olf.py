"""The Omni-Lens-Field: spec, data, training (seeded, exact resume), export
and the numpy runtime (with torch blocked)."""
import json
import math
import os
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from dcdi_core.models import (CheckpointMismatchError, LensMismatchError, ModelFileError,
                              OutsideTrainedRangeError)
from dcdi_core.models.olf.spec import SIZES, OLFSpec
from dcdi_core.models.olf.data import PSFDataConfig, energy_kernel_size
from dcdi_core.psf.olf import OmniLensField, encode_paper, encode_radial
from dcdi_core.errors import DcdiError, InputRangeError
from dcdi_core.optics.lens import load_lens

torch = pytest.importorskip("torch")

from conftest import Killed, kill_at  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
# tiny PSFs and grids: every library here builds in well under a second
FAST = dict(pupil_samples=16, n_wavelengths=3, n_fields=3, n_depths=2, offgrid=6, held_out=4)


def _config(variant="radial", lenses=("mos-s1",), iters=6, **kw):
    from dcdi_core.models.olf.config import OLFTrainConfig
    data = PSFDataConfig(lenses=lenses, variant=variant, **FAST)
    return OLFTrainConfig(data=data, size="tiny", iters=iters, batch=16, lr=3e-3, seed=0, threads=1, **kw)


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    torch.set_num_threads(1)
    return tmp_path_factory.mktemp("psf-cache")


@pytest.fixture(scope="module")
def exported(cache, tmp_path_factory):
    """A radial OLF of two lenses (different k) and a paper OLF, briefly trained and exported."""
    from dcdi_core.models.olf.export import export_olf
    from dcdi_core.models.olf.train import train
    out = {}
    d = tmp_path_factory.mktemp("olf")
    for variant in ("radial", "paper"):
        result = train(_config(variant, ("mos-s1", "mos-s2"), iters=8), d / f"{variant}.run", cache_dir=cache)
        export_olf(result, d / f"{variant}.npz")
        out[variant] = (result, d / f"{variant}.npz")
    return out


# ------------------------------------------------------------------- spec
def test_paper_config_has_the_papers_parameter_count():
    from dcdi_core.models.olf.arch import OLF, count_parameters
    spec = OLFSpec.sized("paper", ["mos-s1", "mos-s2", "double-gauss", "6p"], [41] * 4, "paper")
    assert spec.trunk_shapes()[:3] == [(4, 512), (512, 2048), (2048, 2048)]
    assert spec.param_count() == 32_368_051                   # 32.4 M, 123.5 MiB in float32
    assert count_parameters(OLF(spec)) == spec.param_count()
    assert list(SIZES) == ["tiny", "small", "medium", "large", "paper"]
    radial = OLFSpec.sized("radial", ["mos-s1", "6p"], [41, 67], "small", focus=True)
    assert radial.n_inputs == 2 + 1 + 2 and radial.head_shapes() == [(256, 3 * 41 ** 2), (256, 3 * 67 ** 2)]
    assert count_parameters(OLF(radial)) == radial.param_count()
    with pytest.raises(InputRangeError, match="kernel_size"):
        OLFSpec("radial", ["mos-s1"], [40])


# ------------------------------------------------------------------- data
def test_kernel_size_holds_the_energy():
    k = 41
    psf = np.zeros((2, 3, k, k), np.float32)
    psf[0, :, 20, 20] = 1.0                          # a point
    psf[1, :, 15:26, 15:26] = 1.0 / 121              # an 11 x 11 box
    assert energy_kernel_size(psf, np.zeros((2, 3)), 0.99)[0] == 11
    # 2 % fell outside the 41 px: even all of them hold only 98 %
    size, held = energy_kernel_size(psf, np.full((2, 3), 0.02), 0.99)
    assert size == 41 and held == pytest.approx(0.98)


def test_paper_targets_are_the_library_kernels_rotated_to_the_patch(cache):
    from dcdi_core.models.olf.data import build_data, paper_targets_from_library
    data = build_data(PSFDataConfig(lenses=("mos-s2",), variant="paper", **FAST), cache_dir=cache)
    ls = data.lenses[0]
    lib = ls.libraries[0]
    # below the axis (row centre 967.5 > 639.5, column centre 959.5 on it): outward = +row, no rotation
    t = paper_targets_from_library(ls, np.array([60.0]), np.array([59.5]), np.array([1.3]))[0]
    f = ls.geometry.field(60 * 16 + 7.5, 59.5 * 16 + 7.5)
    ref = lib.at(f, 1.3)
    assert np.abs(t - ref / ref.max(axis=(-1, -2), keepdims=True)).max() < 1e-5
    # to the right of the axis: the kernel's radial rows become columns
    t = paper_targets_from_library(ls, np.array([39.5]), np.array([100.0]), np.array([1.3]))[0]
    ref = lib.at(ls.geometry.field(639.5, 100 * 16 + 7.5), 1.3)
    rotated = np.swapaxes(ref, -1, -2)[..., ::-1, :]           # out[i, j] = in[j, k - 1 - i]
    assert np.abs(t - rotated / ref.max(axis=(-1, -2), keepdims=True)).max() < 1e-5
    assert t.max() == pytest.approx(1.0)


def test_held_out_points_are_traced_off_the_training_points(exported):
    result, _ = exported["radial"]
    for ls in result.data.lenses:
        train_x = np.concatenate([ls.grid_x, ls.off_x])
        for x in ls.val_x:
            assert not (np.abs(train_x - x).max(axis=1) < 1e-6).any()
        assert len(ls.val_x) == FAST["held_out"] and np.allclose(ls.val_y.sum(axis=(-1, -2)), 1, atol=1e-5)


# --------------------------------------------------------------- runtime
def test_numpy_runtime_equals_torch(exported):
    rng = np.random.default_rng(0)
    for variant, (result, path) in exported.items():
        olf = OmniLensField.load(path)
        model = result.ema
        for li, lens_id in enumerate(olf.lens_ids):
            if variant == "radial":
                x = encode_radial(olf.spec, li, rng.uniform(0, 1, 32), rng.uniform(0, 1 / 0.7, 32))
                call = lambda m, t: m(t, li)   # noqa: E731
            else:
                x = encode_paper(olf.spec, li, rng.uniform(0, 79, 32), rng.uniform(0, 119, 32),
                                 rng.uniform(0.7, 10, 32))
                call = lambda m, t: m(t)       # noqa: E731
            with torch.no_grad():
                t32 = call(model, torch.tensor(x, dtype=torch.float32)).numpy()
                t64 = call(model.double(), torch.tensor(x, dtype=torch.float64)).numpy()
                model.float()
            assert np.abs(olf.forward(x, li, np.float64) - t64).max() < 1e-5
            assert np.abs(olf.forward(x, li, np.float32) - t32).max() < 1e-4


def test_radial_psfs_are_non_negative_and_sum_to_one(exported):
    result, path = exported["radial"]
    olf = OmniLensField.load(path)
    lens = load_lens("mos-s2")
    fields = np.linspace(0, 1, 7)[:, None]
    depths = np.array([0.7, 0.9, 2.0, 9.99, 10.0, 1e10, math.inf])[None, :]
    p = olf.psf(lens, fields, depths)
    assert p.shape == (7, 7, 3, olf.kernel_size("mos-s2"), olf.kernel_size("mos-s2"))
    assert p.min() >= 0 and np.abs(p.sum(axis=(-1, -2)) - 1).max() < 1e-5
    # at or beyond the far limit: the infinity PSF
    assert np.array_equal(p[:, 4], p[:, 6]) and np.array_equal(p[:, 5], p[:, 6])
    with torch.no_grad():   # and the torch module by construction, for any input
        x = torch.randn(64, result.spec.n_inputs) * 10
        out = result.model(x, 1)
        lens = torch.arange(64) % 2                          # a batch of both lenses: one list per head
        mixed = result.model(x, lens)
    assert out.min() >= 0 and (out.sum(dim=(-1, -2)) - 1).abs().max() < 1e-5
    assert [m.shape[-1] for m in mixed] == list(result.spec.kernel_sizes)
    assert torch.allclose(mixed[1], out[1::2], atol=1e-6)


def test_changed_prescription_is_not_served(exported):
    _, path = exported["radial"]
    olf = OmniLensField.load(path)
    lens = load_lens("mos-s1")
    assert olf.covers(lens)
    surfaces = list(lens.surfaces)
    surfaces[1] = replace(surfaces[1], radius_mm=surfaces[1].radius_mm * 1.01)
    changed = lens.with_surfaces(surfaces)
    with pytest.raises(LensMismatchError, match="differs optically.*trace") as e:
        olf.psf(changed, 0.5, 2.0)
    assert str(path) in str(e.value) and isinstance(e.value, DcdiError)
    assert not olf.covers(changed)
    with pytest.raises(LensMismatchError, match="not one this OLF learned"):
        olf.psf(load_lens("6p"), 0.5, 2.0)


def test_requests_outside_the_trained_ranges_are_refused(exported):
    olf = OmniLensField.load(exported["radial"][1])
    lens = load_lens("mos-s1")
    with pytest.raises(OutsideTrainedRangeError, match=r"depth_m = 0.5.*>= 0.7 m") as e:
        olf.psf(lens, 0.5, [2.0, 0.5])
    assert str(exported["radial"][1]) in str(e.value)
    with pytest.raises(OutsideTrainedRangeError, match=r"field = 1.2.*\[0.0, 1.0\]"):
        olf.psf(lens, 1.2, 2.0)
    with pytest.raises(OutsideTrainedRangeError, match="focus_m"):
        olf.psf(lens, 0.5, 2.0, focus_m=1.5)
    for bad in (0.0, -1.0, math.nan):
        with pytest.raises(InputRangeError, match="depth_m"):
            olf.psf(lens, 0.5, bad)
    paper = OmniLensField.load(exported["paper"][1])
    with pytest.raises(OutsideTrainedRangeError, match="row"):
        paper.patch_psf(lens, 80, 0, 2.0)
    k = paper.patch_psf(lens, [0, 79.0], [0, 119], [0.7, 50.0])
    assert np.abs(k.sum(axis=(-1, -2)) - 1).max() < 1e-5          # renormalised for convolution
    assert np.allclose(k[1], paper.patch_psf(lens, 79.0, 119, 10.0), atol=1e-7)   # >= 10 m: the 10 m PSF


def test_export_file_metadata_and_checksum(exported, tmp_path):
    _, path = exported["radial"]
    with np.load(path, allow_pickle=False) as z:
        meta = json.loads(str(z["meta"]))
        arrays = {k: z[k] for k in z.files}
    assert meta["variant"] == "radial" and meta["version"] == 1 and len(meta["checksum"]) == 64
    from dcdi_core.optics.lens import lens_fingerprint
    for entry in meta["lenses"]:
        assert entry["fingerprint"] == lens_fingerprint(load_lens(entry["id"]))
        for key in ("kernel_size", "pixel_pitch_mm", "field_range", "depth_range_m", "focus_range_m"):
            assert key in entry
    assert [e["kernel_size"] for e in meta["lenses"]] == meta["spec"]["kernel_sizes"]
    assert meta["held_out"]["mean"]["rel_l1"] > 0
    arrays["head0.bias"] = arrays["head0.bias"] + 1e-3          # an edited file
    bad = tmp_path / "edited.npz"
    np.savez(bad, **arrays)
    with pytest.raises(ModelFileError, match="checksum"):
        OmniLensField.load(bad)
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(ModelFileError, match="junk.npz"):
        OmniLensField.load(tmp_path / "junk.npz")


def test_runtime_runs_with_torch_blocked(exported):
    _, path = exported["radial"]
    code = f"""
import sys
sys.modules["torch"] = None          # as in Blender's Python: no torch
import numpy as np
import dcdi_core.models, dcdi_core.models.common.metrics, dcdi_core.models.olf.spec
from dcdi_core.psf.olf import OmniLensField
from dcdi_core.optics.lens import load_lens
p = OmniLensField.load({str(path)!r}).psf(load_lens("mos-s1"), [0.0, 0.7], 3.0)
assert p.shape[:2] == (2, 3) and abs(p.sum(axis=(-1, -2)) - 1).max() < 1e-5
from dcdi_core.cli import main
assert main(["olf", "info", {str(path)!r}]) == 0
try:
    import dcdi_core.models.olf.arch
except dcdi_core.models.TorchMissingError as e:
    assert "pip install torch==2.13.0" in str(e), e
else:
    raise AssertionError("no TorchMissingError")
assert main(["olf", "train", "--lens", "mos-s1", "-o", "x.npz"]) == 2     # the named error, not a traceback
print("ok")
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT,
                         env=dict(os.environ, PYTHONPATH=str(ROOT)))
    assert out.returncode == 0 and out.stdout.strip().endswith("ok"), out.stderr
    assert "pip install torch==2.13.0" in out.stderr
    # and a plain import of the runtime does not load torch either
    code = "import sys, dcdi_core.psf.olf, dcdi_core.models.common.metrics; print('torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT,
                         env=dict(os.environ, PYTHONPATH=str(ROOT)))
    assert out.stdout.strip() == "False", out.stderr


def test_focus_is_an_input_of_the_radial_olf(cache, tmp_path):
    from dcdi_core.models.olf.export import export_olf
    from dcdi_core.models.olf.train import train
    from dcdi_core.optics.paraxial import prescribed_focus_diopters
    config = _config(iters=2)
    config = replace(config, data=replace(config.data, focus_lenses=("mos-s1",), focus_range_m=(0.8, math.inf),
                                          focus_bins=2, held_out=16))
    # inf survives the config's JSON round trip
    assert type(config).from_json(config.to_json()) == config
    result = train(config, tmp_path / "run", cache_dir=cache)
    ls = result.data.lenses[0]
    lens = load_lens("mos-s1")
    dp = prescribed_focus_diopters(lens)
    assert result.spec.focus and result.spec.n_inputs == 4
    assert [l.settings.focus_distance_m for l in ls.libraries] == [None, 0.8, math.inf]
    # the prescribed library is encoded at its equivalent diopters, the bins at 1 / focus
    n = len(ls.grid_x) // 3
    scale = result.spec.diopter_scale
    assert np.allclose(ls.grid_x[:n, 2] * scale, dp) and np.allclose(ls.grid_x[n:2 * n, 2] * scale, 1 / 0.8)
    assert np.allclose(ls.grid_x[2 * n:, 2], 0.0)
    assert np.allclose(ls.grid_x[:n, :2], ls.grid_x[n:2 * n, :2])
    assert np.abs(ls.grid_y[n:2 * n] - ls.grid_y[2 * n:]).max() > 0.01      # refocused: another PSF
    fm = ls.val_coords["focus_m"]
    assert np.isnan(fm).any() and ((fm[~np.isnan(fm)] >= 0.8)).all()          # prescribed and random focus
    export_olf(result, tmp_path / "f.npz")
    olf = OmniLensField.load(tmp_path / "f.npz")                              # inf survives the metadata
    entry = olf.lens_entry("mos-s1")
    assert entry["focus_range_m"] == [0.8, math.inf] and entry["prescribed_focus_diopters"] == pytest.approx(dp)
    assert olf.psf(lens, 0.3, 2.0, focus_m=[1.0, 4.0, math.inf]).shape[:1] == (3,)
    # focus None: served at the prescribed focus's equivalent diopters, not at any other focus
    x = encode_radial(olf.spec, 0, 0.3, 0.5, dp)
    assert np.allclose(olf.psf(lens, 0.3, 2.0), olf.forward(x, 0)[0], atol=1e-7)
    assert np.abs(olf.psf(lens, 0.3, 2.0) - olf.psf(lens, 0.3, 2.0, focus_m=math.inf)).max() > 0
    with pytest.raises(OutsideTrainedRangeError, match=r"focus_m = 0.5.*\[0.8, inf\] m"):
        olf.psf(lens, 0.3, 2.0, focus_m=0.5)
    with pytest.raises(InputRangeError, match="focus_m"):
        olf.psf(lens, 0.3, 2.0, focus_m=-1.0)
    # the held-out figures per focus band, prescribed included
    bands = olf.meta["held_out"]["focus"]["mos-s1"]
    assert "prescribed" in bands and sum(b["n"] for b in bands.values()) == len(ls.val_x)
    # as a PSF source: focus None (the prescribed focus) and inf served, 0.5 m traced with the reason
    from dcdi_core.psf.sources import psf_source
    assert psf_source(lens, olf_file=tmp_path / "f.npz").kind == "olf"
    assert psf_source(lens, olf_file=tmp_path / "f.npz", focus_m=math.inf).kind == "olf"
    src = psf_source(lens, olf_file=tmp_path / "f.npz", focus_m=0.5)
    assert src.kind == "trace" and "outside the learned 0.8 m to inf m" in src.message
    # the report's comparison re-encodes the held-out coordinates through psf(): the same figures as
    # the file's own (the encoded inputs), per band, so the trainer's and the runtime's encodings agree
    from lab.olf_report import held_out_comparison
    rows = {r["band"]: r for r in held_out_comparison([tmp_path / "f.npz"], tmp_path / "run" / "points.npz")}
    assert set(rows) == set(bands)
    for band, hb in bands.items():
        assert rows[band]["n"] == hb["n"] and rows[band]["rel_l1"] == pytest.approx(hb["rel_l1"], rel=1e-4)


def test_focus_bands_cut_the_diopter_range_in_thirds():
    from dcdi_core.models.olf.export import focus_bands
    got = focus_bands([np.nan, math.inf, 3.0, 1.5, 1.0, 0.7], (0.0, 1 / 0.7))
    assert got.tolist() == ["prescribed", "far", "far", "mid", "near", "near"]


def test_prescribed_focus_is_equivalent_to_a_paraxial_focus():
    """Refocusing at the prescribed sensor's equivalent diopters gives back the
    prescribed last thickness; the 6P is focused near 6 m, the double Gauss
    just inside infinity (negative diopters)."""
    from dcdi_core.optics.paraxial import image_distance_mm, prescribed_focus_diopters, refocused, \
        refocused_at_diopters
    for lid in ("mos-s1", "mos-s2", "double-gauss", "6p"):
        lens = load_lens(lid)
        d = prescribed_focus_diopters(lens)
        q = lens.surfaces[-1].thickness_mm
        assert abs(refocused_at_diopters(lens, d).surfaces[-1].thickness_mm - q) < 1e-9, lid
        if d > 0:      # the same through the distance form
            assert abs(float(image_distance_mm(lens, 1.0 / d)) - q) < 1e-9
        assert refocused_at_diopters(lens, d + 0.5).surfaces[-1].thickness_mm != pytest.approx(q, abs=1e-6)
    assert 0.1 < prescribed_focus_diopters(load_lens("6p")) < 0.3
    assert -0.5 < prescribed_focus_diopters(load_lens("double-gauss")) < 0
    lens = load_lens("6p")
    assert refocused(lens, math.inf).surfaces[-1].thickness_mm == pytest.approx(
        refocused_at_diopters(lens, 0.0).surfaces[-1].thickness_mm, abs=1e-12)


# -------------------------------------------------------------- training
def _state(result):
    return {**{"model." + k: v for k, v in result.model.state_dict().items()},
            **{"ema." + k: v for k, v in result.ema.state_dict().items()}}


def test_kill_and_resume_ends_where_an_uninterrupted_run_does(cache, tmp_path):
    from dcdi_core.models.olf.train import train
    config = _config(iters=6, checkpoint_every=3)
    straight = train(config, tmp_path / "a", cache_dir=cache)
    # killed after step 4: the work after the checkpoint at 3 is lost and redone
    with pytest.raises(Killed):
        train(config, tmp_path / "b", cache_dir=cache, on_step=kill_at(4))
    resumed = train(config, tmp_path / "b", cache_dir=cache)
    a, b = _state(straight), _state(resumed)
    assert resumed.step == 6 and a.keys() == b.keys()
    assert all(torch.equal(a[k], b[k]) for k in a)
    # same seed, same weights; another seed, others
    other = train(replace(config, seed=1), tmp_path / "c", cache_dir=cache)
    assert not torch.equal(_state(other)["model.trunk.0.weight"], a["model.trunk.0.weight"])
    # a finished run resumed: nothing more to do, the same weights
    again = train(config, tmp_path / "a", cache_dir=cache)
    assert again.step == 6 and all(torch.equal(_state(again)[k], a[k]) for k in a)


def test_resume_with_other_settings_is_refused(cache, tmp_path):
    from dcdi_core.models.olf.train import train
    config = _config(iters=2)
    train(config, tmp_path / "run", cache_dir=cache)
    other = replace(config, lr=1e-4, batch=8)
    with pytest.raises(CheckpointMismatchError, match=r"batch: checkpoint 16, now 8.*lr: checkpoint 0.003") as e:
        train(other, tmp_path / "run", cache_dir=cache)
    assert "checkpoint.pt" in str(e.value)
    with pytest.raises(CheckpointMismatchError, match="data.n_fields"):
        train(replace(config, data=replace(config.data, n_fields=4)), tmp_path / "run", cache_dir=cache)
    # how often to checkpoint decides nothing: resumed
    assert train(replace(config, checkpoint_every=7), tmp_path / "run", cache_dir=cache).step == 2


def test_tiny_olf_overfits_a_handful_of_psfs(cache, tmp_path):
    from dcdi_core.models.olf.train import train
    config = _config(iters=300, lr_min=3e-5)
    config = replace(config, data=replace(config.data, offgrid=0))     # the library's 9 PSFs alone
    losses = []
    train(config, tmp_path / "run", cache_dir=cache, progress=lambda s, n, loss: losses.append(loss))
    assert np.mean(losses[:5]) / np.mean(losses[-5:]) >= 10


def test_cli_train_and_info(cache, tmp_path, monkeypatch, capsys):
    from dcdi_core.cli import main
    monkeypatch.setenv("DCDI_CACHE_DIR", str(cache))
    out = tmp_path / "olf.npz"
    argv = ["olf", "train", "--lens", "mos-s1", "--variant", "radial", "--size", "tiny", "--iters", "3",
            "--batch", "8", "--seed", "2", "--threads", "1", "-o", str(out), "--rays", "16", "--wavelengths", "3",
            "--fields", "3", "--depths", "2", "--offgrid", "4", "--held-out", "4"]
    assert main(argv) == 0
    text = capsys.readouterr().out
    assert f"wrote {out}" in text and "held-out (ema): PSNR" in text
    assert (tmp_path / "olf.npz.run" / "checkpoint.pt").exists()
    assert main(["olf", "info", str(out), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["variant"] == "radial" and info["lenses"][0]["id"] == "mos-s1"
    assert info["lenses"][0]["prescription"] == "current" and info["bytes"] == out.stat().st_size
    assert info["training"]["iterations"] == 3
    assert main(argv[:-2] + ["--held-out", "5"]) == 2       # the run folder holds other settings
    assert "held_out" in capsys.readouterr().err


def test_float16_file_matches_torch_with_its_rounded_weights(exported, tmp_path):
    import copy
    from dcdi_core.models.olf.export import export_olf
    result, _ = exported["radial"]
    meta = export_olf(result, tmp_path / "h.npz", dtype="float16")
    olf = OmniLensField.load(tmp_path / "h.npz")
    assert meta["dtype"] == "float16" and all(a.dtype == np.float16 for a in olf._trunk[0])
    assert (tmp_path / "h.npz").stat().st_size < 0.6 * exported["radial"][1].stat().st_size
    rounded = copy.deepcopy(result.ema)
    with torch.no_grad():
        for p in rounded.parameters():
            p.copy_(p.half().double())
    rng = np.random.default_rng(1)
    x = encode_radial(olf.spec, 0, rng.uniform(0, 1, 32), rng.uniform(0, 1 / 0.7, 32))
    with torch.no_grad():
        ref = rounded.double()(torch.tensor(x, dtype=torch.float64), 0).numpy()
        full = result.ema.double()(torch.tensor(x, dtype=torch.float64), 0).numpy()
        result.ema.float()
    got = olf.forward(x, 0, np.float64)
    assert np.abs(got - ref).max() < 1e-5                       # the runtime: torch's forward on the stored weights
    assert np.abs(got - full).max() < 1e-2 * full.max()          # what float16 storage itself changes
    # the figures recorded are the stored file's (the runtime's), torch's beside them
    assert meta["held_out"]["mean"]["psnr_8bit"] == pytest.approx(meta["held_out_torch"]["mean"]["psnr_8bit"], abs=0.5)
