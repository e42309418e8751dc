"""DACN evaluation (scores over imaged pixels, per depth band, held-out
pairs only), the shipped-weights file, and the data-size subset."""
import json
import math

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from conftest import dacn_config as _config  # noqa: E402


def test_band_scores_pool_squared_error_over_the_band_pixels():
    from dcdi_core.models.dacn.evaluate import BandSums, image_scores
    from dcdi_core.models.common.metrics import ssim_map
    rng = np.random.default_rng(0)
    tgt = rng.uniform(0.2, 0.8, (30, 40, 3))
    out = tgt + rng.normal(0, 0.05, tgt.shape)
    depth = np.where(np.arange(40)[None, :] < 15, 0.8, 3.0) * np.ones((30, 1))
    depth[:, 35:] = np.inf
    depth[:5, :] = np.nan                                  # not imaged: never scored
    out[:5] = 0.0
    sc = image_scores(out, tgt, depth)
    clipped = np.clip(out, 0, 1)
    sel = ~np.isnan(depth)
    assert math.isclose(sc["psnr"], 10 * math.log10(1 / ((clipped - tgt)[sel] ** 2).mean()), rel_tol=1e-12)
    near = sel & (depth < 1.0)
    sse, n, ssum, sn = sc["bands"]["0.7-1 m"]
    assert n == near.sum() * 3 and math.isclose(sse, ((clipped - tgt)[near] ** 2).sum())
    smap = ssim_map(clipped.transpose(2, 0, 1), tgt.transpose(2, 0, 1), 1.0).mean(0)
    inner = np.zeros_like(near)
    inner[5:-5, 5:-5] = True
    assert sn == (near & inner).sum() and math.isclose(ssum, smap[(near & inner)[5:-5, 5:-5]].sum())
    assert set(sc["bands"]) == {"0.7-1 m", "2-5 m", "> 10 m"}  # infinity is in the far band
    assert sc["bands"]["> 10 m"][1] == 25 * 5 * 3
    b = BandSums()
    b.add(*sc["bands"]["2-5 m"])
    assert b.scores()["pixels"] == ((depth >= 2) & (depth < 5)).sum()
    with pytest.raises(Exception, match="imaged"):
        image_scores(out, tgt, np.full((30, 40), np.nan))


def test_eval_scores_only_held_out_pairs_and_exports_round_trip(pairs, tmp_path, capsys):  # noqa: F811
    from dcdi_core.cli import main
    from dcdi_core.models.dacn.correct import load_dacn
    from dcdi_core.models.dacn.train import train_dacn
    train_dacn(_config(pairs, iters=3, checkpoint_every=3), tmp_path / "run")
    split = json.loads((tmp_path / "run" / "split.json").read_text())
    test_ids = sorted(i for i, s in split["ids"].items() if split["scenes"][s] == "test")
    from dcdi_core.models.common.lpips import CHANNELS, LPIPS
    torch.save({f"features.{k}": v for k, v in LPIPS().features.state_dict().items()}, tmp_path / "alex.pth")
    torch.save({f"lin{k}.model.1.weight": torch.rand(1, c, 1, 1) for k, c in enumerate(CHANNELS)}, tmp_path / "l.pth")
    assert main(["dacn", "eval", str(tmp_path / "run"), "--data", str(pairs), "--compare", f"same={tmp_path / 'run'}",
                 "--json", str(tmp_path / "ev.json"), "--pictures", str(tmp_path / "pics"),
                 "--lpips", str(tmp_path / "alex.pth"), str(tmp_path / "l.pth")]) == 0
    out = capsys.readouterr().out
    assert f"{len(test_ids)} held-out pairs" in out and "| capture |" in out and "| same |" in out
    ev = json.loads((tmp_path / "ev.json").read_text())
    assert sorted(r["id"].split("~")[0] for r in ev["pairs"]) == test_ids
    assert ev["mean"]["dacn"] == ev["mean"]["same"] and ev["mean"]["capture"]["lpips"] > 0
    assert "| LPIPS |" in out and "| deconvolution |" in out and "field band" in out and "depth band" in out
    assert ev["mean"]["deconvolution"]["psnr"] > 0 and set(ev["fields"]["dacn"]) <= {"field 0-0.3", "field 0.3-0.6",
                                                                                       "field 0.6-1"}
    assert len(list((tmp_path / "pics").glob("*.png"))) == len(test_ids)
    # the shipped form: float16 npz, read without pickle, the same network to float16 precision
    assert main(["dacn", "export", str(tmp_path / "run"), "-o", str(tmp_path / "m.npz")]) == 0
    a, _ = load_dacn(tmp_path / "run")
    b, info = load_dacn(tmp_path / "m.npz")
    assert info["da2t"]["lens"] == "mos-s2" and info["step"] == 3
    x, d = torch.rand(1, 3, 32, 32), torch.rand(1, 1, 32, 32)
    with torch.no_grad():
        assert (a(x, d) - b(x, d)).abs().max() < 5e-3
    raw = dict(np.load(tmp_path / "m.npz", allow_pickle=False))
    raw[next(k for k in raw if k != "meta")] *= 2
    np.savez(tmp_path / "bad.npz", **raw)
    with pytest.raises(Exception, match="checksum"):
        load_dacn(tmp_path / "bad.npz")


def test_train_scenes_takes_a_nested_subset(pairs, tmp_path):  # noqa: F811
    from dcdi_core.models.dacn.train import open_data
    full = open_data(_config(pairs))
    one = open_data(_config(pairs, train_scenes=1))
    two = open_data(_config(pairs, train_scenes=2))
    assert len(full.train) == 3 and len(one.train) == 1 and len(two.train) == 2
    assert set(one.train) <= set(two.train) <= set(full.train) and one.key != two.key
    with pytest.raises(Exception, match="train_scenes"):
        open_data(_config(pairs, train_scenes=4))


def test_study_trains_every_row_and_seed_at_equal_budget_and_tabulates(pairs, tmp_path):  # noqa: F811
    from lab import dacn_study
    assert dacn_study.run_flags("refine")[:2] == ["--input", "capture"]
    with pytest.raises(SystemExit, match="unknown row"):
        dacn_study.run_flags("nothing")
    out = tmp_path / "study"
    argv = [str(out), "--lens", "mos-s2", "--train", str(pairs), "--test", str(pairs), "--runs",
            "baseline,refine,refine@2m", "--seeds", "0,1", "--iters", "2", "--batch", "1", "--crop", "16", "--validate-every", "1", "--jobs", "2"]
    assert dacn_study.main(argv) == 0
    for row in ("baseline", "refine"):
        for seed in (0, 1):
            cfg = json.loads((out / "mos-s2" / f"{row}-s{seed}" / "config.json").read_text())
            assert (cfg["iters"], cfg["seed"], cfg["batch"], cfg["config"]) == (2, seed, 1, "refine")
    assert json.loads((out / "mos-s2" / "baseline-s0" / "config.json").read_text())["input"] == "baseline"
    assert json.loads((out / "mos-s2" / "baseline-s0" / "config.json").read_text())["arch"]["refine"] is False
    text = (out / "mos-s2" / "table.md").read_text()
    assert "| baseline |" in text and "| refine |" in text and "| capture |" in text and "| deconvolution |" in text
    # the depth-unaware refine: trained on the derived one-depth pairs, told 2 m, evaluated told it
    told = json.loads((out / "mos-s2" / "refine@2m-s0" / "config.json").read_text())
    assert told["data"] == str(out / "mos-s2" / "pairs-told-2m") and "| refine@2m |" in text
    ev = json.loads((out / "mos-s2" / "eval.json").read_text())
    assert ev["mean"]["refine@2m-s0"]["psnr"] != ev["mean"]["refine-s0"]["psnr"]
    assert (out / "mos-s2" / "curves.png").stat().st_size > 0 and "RMS blur" in (out / "mos-s2" / "data.md").read_text()
    mtime = (out / "mos-s2" / "refine-s1" / "checkpoint.pt").stat().st_mtime
    assert dacn_study.main(argv) == 0                       # finished runs are not trained again
    assert (out / "mos-s2" / "refine-s1" / "checkpoint.pt").stat().st_mtime == mtime


def test_bench_dacn_quick(capsys):
    from dcdi_core.cli import main
    assert main(["bench", "dacn", "--quick"]) == 0
    out = capsys.readouterr().out
    assert "tiny: 285,538 parameters" in out and "tiled / untiled" in out


def test_lpips_from_user_weights_is_zero_on_equal_images_and_refuses_other_files(tmp_path):
    from dcdi_core.models.common.lpips import CHANNELS, LPIPS, load_lpips, lpips_score
    torch.manual_seed(0)
    ref = LPIPS()
    torch.save({f"features.{k}": v for k, v in ref.features.state_dict().items()}, tmp_path / "alex.pth")
    lins = {f"lin{k}.model.1.weight": torch.rand(1, c, 1, 1) for k, c in enumerate(CHANNELS)}
    torch.save(lins, tmp_path / "lin.pth")
    m = load_lpips(tmp_path / "alex.pth", tmp_path / "lin.pth")
    rng = np.random.default_rng(0)
    a = rng.uniform(0, 1, (64, 64, 3))
    b = np.clip(a + rng.normal(0, 0.1, a.shape), 0, 1)
    assert lpips_score(m, a, a) == 0.0
    d = lpips_score(m, a, b)
    assert d > 0 and np.isclose(d, lpips_score(m, b, a), rtol=1e-5)
    assert lpips_score(m, a, np.clip(a + rng.normal(0, 0.3, a.shape), 0, 1)) > d
    mask = np.zeros((64, 64), bool)
    mask[:32] = True
    assert np.isfinite(lpips_score(m, a, b, mask))
    torch.save({"features.0.weight": torch.zeros(2)}, tmp_path / "bad.pth")
    with pytest.raises(Exception, match="bad.pth"):
        load_lpips(tmp_path / "bad.pth", tmp_path / "lin.pth")
    with pytest.raises(Exception, match="lin.pth: not AlexNet's features"):
        load_lpips(tmp_path / "lin.pth", tmp_path / "alex.pth")          # the two swapped
    with pytest.raises(Exception, match="alex.pth: no lin"):
        load_lpips(tmp_path / "alex.pth", tmp_path / "alex.pth")
