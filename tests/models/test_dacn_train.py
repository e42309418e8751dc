"""DACN training (seeded, kill-and-resume equals uninterrupted, the test
split never read), tiled correction, and the commands."""
import json
from dataclasses import replace

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from conftest import Frames, Killed, dacn_config, kill_at  # noqa: E402


def test_kill_and_resume_gives_the_uninterrupted_weights(pairs, tmp_path):
    from dcdi_core.models.dacn.train import train_dacn
    full = train_dacn(dacn_config(pairs), tmp_path / "full")
    with pytest.raises(Killed):             # after the checkpoint at 3, before the one at 6
        train_dacn(dacn_config(pairs), tmp_path / "killed", on_step=kill_at(4))
    resumed = train_dacn(dacn_config(pairs), tmp_path / "killed")
    for a, b in ((full.model, resumed.model), (full.ema, resumed.ema)):
        for (k, va), vb in zip(a.state_dict().items(), b.state_dict().values()):
            assert torch.equal(va, vb), k
    assert resumed.step == 6 and "psnr" in full.validation["ema"]["mean"]
    lines = [json.loads(s) for s in (tmp_path / "full" / "log.jsonl").read_text().splitlines()]
    assert lines[-1]["final"] and lines[-1]["val_ema"]["psnr_input"] > 10
    # another setting is refused, naming it
    from dcdi_core.models import CheckpointMismatchError
    with pytest.raises(CheckpointMismatchError, match="lr"):
        train_dacn(dacn_config(pairs, lr=5e-4), tmp_path / "full")
    from dcdi_core.models.dacn.config import DACNTrainConfig
    assert DACNTrainConfig.from_json(dacn_config(pairs).to_json()) == dacn_config(pairs)
    steps = dacn_config(pairs, iters=100, schedule="steps")
    assert [steps.lr_at(s) for s in (0, 49, 50, 80, 95)] == [1e-3, 1e-3, 5e-4, 2.5e-4, 6.25e-5]
    # cosine: linear warm-up over 10 % of the iterations, lr at its end, lr / 100 at the last
    cos = dacn_config(pairs, iters=100, warmup=0.1)
    assert cos.lr_at(0) == pytest.approx(1e-4) and cos.lr_at(9) == pytest.approx(1e-3)
    assert cos.lr_at(10) == pytest.approx(1e-3) and cos.lr_at(100) == pytest.approx(1e-5)
    assert cos.lr_at(55) == pytest.approx(1e-3 * (0.01 + 0.99 * 0.5))
    # a config written before the schedule existed trained with the steps
    old = {k: v for k, v in steps.as_dict().items() if k not in ("schedule", "warmup", "loss", "crop_choice")}
    assert DACNTrainConfig.from_dict(old) == replace(steps, loss="l1", crop_choice=1, warmup=0.0)


def test_the_test_split_never_meets_training(pairs, tmp_path, monkeypatch):
    import dcdi_core.models.dacn.data as da2t
    from dcdi_core.models.dacn import train as dacn_loop
    read = []
    real = da2t.load_pair

    def spy(path, record=None):
        read.append(str(path))
        return real(path, record)
    monkeypatch.setattr(da2t, "load_pair", spy)
    monkeypatch.setattr(dacn_loop, "load_pair", spy)
    result = dacn_loop.train_dacn(dacn_config(pairs, iters=4, checkpoint_every=4), tmp_path / "run")
    split = json.loads((tmp_path / "run" / "split.json").read_text())
    test_scenes = {s for s, p in split["scenes"].items() if p == "test"}
    assert len(test_scenes) == 2 and len(result.data.val) == 1 and len(result.data.train) == 3
    assert read and not any(s + "~" in p for s in test_scenes for p in read)       # never even opened
    assert {split["ids"][p.split("~")[0]] for p in result.data.train}.isdisjoint(test_scenes)
    assert (pairs / "split.json").exists()                                         # recorded beside the data


def test_tiled_correction_equals_the_whole_image_and_leaves_no_seams(pairs, tmp_path):
    from dcdi_core.models.dacn.correct import correct, load_dacn
    from dcdi_core.models.runtime.depth_encoding import encode_depth
    from dcdi_core.models.dacn.train import train_dacn
    train_dacn(dacn_config(pairs, iters=3, checkpoint_every=3), tmp_path / "run")
    model, info = load_dacn(tmp_path / "run")
    assert info["step"] == 3 and info["da2t"]["lens"] == "mos-s2"
    with torch.no_grad():                        # a network far from the identity
        torch.manual_seed(0)
        for p in model.parameters():
            p.add_(0.1 * torch.randn_like(p))
    rng = np.random.default_rng(1)
    img = rng.uniform(0, 1, (40, 56, 3)).astype(np.float32)
    dep = rng.uniform(0.7, 8.0, (40, 56))
    with torch.no_grad():
        whole = model(torch.from_numpy(img.transpose(2, 0, 1).copy())[None],
                      torch.from_numpy(encode_depth(dep, "minmax"))[None, None])[0].numpy().transpose(1, 2, 0)
    np.testing.assert_array_equal(correct(model, img, dep, tile=64), whole)
    tiles = []
    out = correct(model, img, dep, tile=24, overlap=8, progress=lambda d, t: tiles.append((d, t)))
    assert tiles[-1] == (6, 6) and out.shape == img.shape and np.isfinite(out).all()
    # the cross-fade weights sum to one everywhere: an identity network comes back exactly
    from dcdi_core.models.dacn.arch import DACN
    ident = DACN(model.spec).eval()
    np.testing.assert_allclose(correct(ident, img, dep, tile=24, overlap=8), img, atol=1e-6)


def test_commands(pairs, tmp_path, capsys):
    from dcdi_core.cli import main
    from dcdi_core.io.images import read_image, write_depth, write_image
    run = tmp_path / "run"
    assert main(["dacn", "train", "--data", str(pairs), "--config", "tiny", "--iters", "2", "-o", str(run),
                 "--crop", "16", "--batch", "1", "--channels", "8", "--groups", "1", "--blocks", "1",
                 "--no-rdicab"]) == 0
    assert "trained" in capsys.readouterr().out
    cfg = json.loads((run / "config.json").read_text())
    assert cfg["arch"] == {"rdicab": False, "channels": 8, "groups": 1, "blocks": 1}
    img = np.random.default_rng(0).uniform(0, 1, (20, 30, 3)).astype(np.float32)
    write_image(tmp_path / "cap.exr", img)
    write_depth(tmp_path / "d.exr", np.full((20, 30), 2.0, np.float32))
    assert main(["correct", "--image", str(tmp_path / "cap.exr"), "--model", str(run), "-o",
                 str(tmp_path / "out.exr")]) == 2
    assert "--depth DEPTH" in capsys.readouterr().err
    assert main(["correct", "--image", str(tmp_path / "cap.exr"), "--depth", str(tmp_path / "d.exr"), "--model",
                 str(run), "--lens", "mos-s1", "-o", str(tmp_path / "out.exr")]) == 2
    assert "trained for lens mos-s2" in capsys.readouterr().err
    assert main(["correct", "--image", str(tmp_path / "cap.exr"), "--depth", str(tmp_path / "d.exr"), "--model",
                 str(run), "--lens", "mos-s2", "-o", str(tmp_path / "out.exr")]) == 0
    assert read_image(tmp_path / "out.exr").shape == (20, 30, 3)
    # dcdi dacn pairs on a generic RGB-D folder
    f = Frames().load("scene1")
    write_image(tmp_path / "src" / "images" / "a.exr", f.image)
    (tmp_path / "src" / "depth").mkdir()
    np.save(tmp_path / "src" / "depth" / "a.npy", f.depth)
    assert main(["dacn", "pairs", str(tmp_path / "src"), "--lens", "mos-s1", "-o", str(tmp_path / "p"), "--rays", "8",
                 "--wavelengths", "3", "--fields", "6", "--depths", "3", "--lens-pool", "1"]) == 0
    assert "1 DA2T pairs of folder (1 frames) for mos-s1" in capsys.readouterr().out
    assert json.loads((tmp_path / "p" / "da2t.json").read_text())["lens_pool"] == 1
