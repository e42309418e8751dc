"""`dcdi dof`: the pipeline end to end with each depth backend, and with a
sharp input, --camera none and the true depth, exactly `dcdi bokeh`."""
import numpy as np
import pytest

torch = pytest.importorskip("torch")

from conftest import write_rgbd_scene  # noqa: E402
from conftest import dacn_config as _config  # noqa: E402

from dcdi_core.cli import main  # noqa: E402
from dcdi_core.io.images import read_image  # noqa: E402

FAST = ["--rays", "16", "--wavelengths", "3", "--kernel", "15", "--psf-source", "trace"]


@pytest.fixture
def scene(tmp_path, monkeypatch):
    write_rgbd_scene(tmp_path, monkeypatch, 48, 64)
    return tmp_path


@pytest.fixture(scope="module")
def networks(pairs, tmp_path_factory):  # noqa: F811
    """A tiny DACN and depth network of mos-s2 (a few steps), exported as shipped."""
    from dcdi_core.models.dacn.export import export_dacn
    from dcdi_core.models.depth.export import export_depthnet
    from dcdi_core.models.dacn.train import train_dacn
    from dcdi_core.models.depth.config import DepthTrainConfig
    from dcdi_core.models.depth.train import train_depth
    d = tmp_path_factory.mktemp("nets")
    train_dacn(_config(pairs, iters=2, checkpoint_every=2), d / "dacn")
    train_depth(DepthTrainConfig(data=str(pairs), widths=(4, 8), iters=2, batch=1, crop=16, val_fraction=1 / 6,
                                 test_fraction=2 / 6), d / "depth")
    export_dacn(d / "dacn", d / "dacn.npz")
    export_depthnet(d / "depth", d / "depth.npz")
    return d


def _args(d, *extra):
    return ["--image", str(d / "aif.exr"), "--lens", "mos-s1", "--keep", "0.7", "1.5", *FAST, *extra]


def test_sharp_input_camera_none_true_depth_equals_bokeh(scene, capsys):
    d = scene
    assert main(["bokeh", *_args(d, "--depth", str(d / "depth.exr"), "-o", str(d / "b.exr"))]) == 0
    assert main(["dof", *_args(d, "--depth", str(d / "depth.exr"), "--camera", "none", "-o", str(d / "p.exr"))]) == 0
    out = capsys.readouterr().out
    assert "camera none, depth given, PSFs trace" in out
    np.testing.assert_array_equal(read_image(d / "p.exr"), read_image(d / "b.exr"))


def test_end_to_end_with_the_dcdi_depth_network(scene, networks, capsys):
    d = scene
    assert main(["dof", *_args(d, "--camera", "mos-s2", "--dacn", str(networks / "dacn.npz"), "--depth-checkpoint",
                               str(networks / "depth.npz"), "-o", str(d / "p.exr"), "--save-intermediates",
                               str(d / "mid"), "--side-by-side", str(d / "s.png"))]) == 0
    out = capsys.readouterr().out
    assert "depth dcdi" in out and "correction" in out and "depth " in out
    res, cor = read_image(d / "p.exr"), read_image(d / "mid" / "corrected.exr")
    assert res.shape == cor.shape == (48, 64, 3) and np.isfinite(res).all() and (d / "s.png").exists()


@pytest.mark.parametrize("backend", ["depth-anything-v2", "unidepth", "depth-pro"])
def test_end_to_end_with_each_public_estimator_through_a_stand_in(scene, networks, monkeypatch, capsys, backend):
    from support.depth_stand_ins import install_stand_ins

    from dcdi_core.io.images import read_depth
    from dcdi_core.models.depth.estimators import srgb_uint8
    d = scene
    ck = install_stand_ins(monkeypatch, d)[backend]
    assert main(["dof", *_args(d, "--camera", "mos-s2", "--dacn", str(networks / "dacn.npz"), "--depth-backend",
                               backend, "--depth-checkpoint", str(ck), "-o", str(d / "p.exr"),
                               "--save-intermediates", str(d / "mid"))]) == 0
    assert f"depth {backend}" in capsys.readouterr().out
    expected = 1 + 4 * srgb_uint8(read_image(d / "aif.exr")).mean(axis=2) / 255
    np.testing.assert_allclose(read_depth(d / "mid" / "depth.exr"), expected, rtol=1e-5)
    assert np.isfinite(read_image(d / "p.exr")).all()


def test_what_is_missing_is_said_before_any_work(scene, networks, capsys):
    d = scene
    cases = [(["--camera", "6p", "--depth", str(d / "depth.exr")], "no shipped DACN for 6p"),
             (["--camera", "none"], "no depth map"),
             (["--camera", "mos-s1", "--dacn", str(networks / "dacn.npz"), "--depth", str(d / "depth.exr")],
              "trained for lens mos-s2")]
    for extra, says in cases:
        assert main(["dof", *_args(d, *extra, "-o", str(d / "p.exr"))]) != 0
        assert says in capsys.readouterr().err
    assert not (d / "p.exr").exists()


def test_pipeline_and_depth_reports_on_held_out_pairs(pairs, networks, tmp_path, capsys):  # noqa: F811
    dacn, dep = f"mos-s2={networks / 'dacn.npz'}", f"mos-s2={networks / 'depth.npz'}"
    assert main(["report", "pipeline", "--pairs", f"mos-s2={pairs}", "--dacn", dacn, "--depth-model", dep,
                 "--baseline", dacn, "--target", "mos-s1", "--count", "1", "--quick", "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    for row in ("no correction", "corrected, true depth", "corrected, estimated depth", "depth-unaware model"):
        assert f"| {row} |" in out
    assert list((tmp_path / "pictures").glob("mos-s2-*.png"))
    assert main(["report", "depth", "--pairs", f"mos-s2={pairs}", "--depth-model", dep, "--count", "2",
                 "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "| mos-s2 | 2 | capture |" in out and "| mos-s2 | 2 | sharp |" in out
