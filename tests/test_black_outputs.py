"""No lens yields black without a word: a result black wherever the scene
is lit is refused whatever the PSFs' source (nothing written), and a
result black over part of the lit frame is said with its share."""
import re

import numpy as np
import pytest

from support.build import ROOT
from support.cli import run_cli

from dcdi_core.app.render import check_light
from dcdi_core.errors import RenderError
from dcdi_core.io.images import write_depth, write_image


@pytest.fixture(scope="module")
def blind(tmp_path_factory):
    """MOS-S1 with its last clear aperture a micrometre: no ray passes."""
    d = tmp_path_factory.mktemp("blind")
    text = (ROOT / "lenses" / "mos-s1.toml").read_text()
    parts = text.split("[[surface]]")
    parts[-1] = re.sub(r"^semi_diameter_mm = [0-9.]+", "semi_diameter_mm = 0.000001", parts[-1], count=1,
                       flags=re.M)
    (d / "blind.toml").write_text("[[surface]]".join(parts).replace('id = "mos-s1"', 'id = "blind"'))
    write_image(d / "aif.exr", np.full((48, 64, 3), 0.5, np.float32))
    write_depth(d / "depth.exr", np.full((48, 64), 2.0, np.float32))
    return d


@pytest.mark.parametrize("verb", [["simulate"], ["bokeh", "--keep", "0.7", "0.8"]])
def test_a_lens_that_passes_no_ray_is_refused_not_black(blind, verb, capsys):
    code, out, err = run_cli(capsys, verb[0], "--image", blind / "aif.exr", "--depth", blind / "depth.exr", "--lens",
                             blind / "blind.toml", *verb[1:], "-o", blind / "out.exr")
    assert code == 2 and "no light" in err and "blind" in err, err
    assert not (blind / "out.exr").exists()


def test_a_partly_black_result_is_said_with_its_share():
    scene = np.full((40, 40, 3), 0.5, np.float32)
    result = scene.copy()
    result[:, :10] = 0.0                                   # a quarter of the frame: no ray reached it
    note = check_light(scene, result, None, "the image x")
    assert note is not None and note.startswith("25.0% of the image x's lit pixels are black")
    # a scene black there itself: nothing to say; a result barely dark: none either
    dark_scene = scene.copy()
    dark_scene[:, :10] = 0.0
    assert check_light(dark_scene, result, None, "x") is None
    assert check_light(scene, np.full_like(scene, 1e-5), None, "x") is None
    with pytest.raises(RenderError, match="no light"):
        check_light(scene, np.zeros_like(scene), None, "x")


def test_a_ray_map_kernel_that_clips_warns_as_a_traced_one(capsys):
    """`dcdi psf` of the Sonnar at 0.7 m in a 41-px kernel: from its ray map
    the same warning as traced (it clips 98.7 %: once rescaled to 1 in
    silence)."""
    from dcdi_core.cli import main
    texts = {}
    for source in ("raymap", "trace"):
        assert main(["psf", "zeiss-sonnar-50mm-f1-5", "--field", "0", "--depth", "0.7", "--kernel", "41",
                     "--psf-source", source]) == 0
        err = capsys.readouterr().err
        texts[source] = [line for line in err.splitlines() if "kernel clips" in line]
    assert len(texts["raymap"]) == 1 and texts["raymap"] == texts["trace"], texts


def test_a_large_blur_whose_coarse_kernels_clip_says_so():
    """The Mamiya 150 mm focused far, a light at 0.5 m, 3 um pixels: the
    blur passes even 8 x the 129-px kernel; the note says it is still
    clipped (it once said "their blur whole, not clipped")."""
    import warnings
    from dcdi_core.app.render import BokehRequest, bokeh
    from dcdi_core.optics.lens import load_lens
    from dcdi_core.psf.compute import PSFSettings
    from dcdi_core.render.request import RenderRequest
    lens = load_lens("mamiya-sekor-sf-150mm-f4")
    img = np.full((24, 32, 3), 0.5, np.float32)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        r = bokeh(BokehRequest(img, np.full((24, 32), 0.5, np.float32), lens, focus_m=100.0,
                               render=RenderRequest(lens, psf=PSFSettings(pixel_pitch_mm=0.003))))
    assert r.info["large_blur_factor"] == 8 and "kernel clips" in r.info["clipped"]
    note = next(n for n in r.notes if "1/8 of the resolution" in n)
    assert "still clipped" in note and "not clipped" not in note
