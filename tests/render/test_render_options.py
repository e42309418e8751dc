"""ConvolveOptions and BokehOptions: a bad value is refused when the options
are made, naming its field and the allowed range, before an image is touched."""
import dataclasses

import numpy as np
import pytest

from dcdi_core.errors import InputRangeError
from dcdi_core.psf.compute import PSFSettings
from dcdi_core.render.convolve import ConvolveOptions, patch_convolve
from dcdi_core.render.multires import DEFAULT_MAX_LEVEL
from dcdi_core.render.bokeh import BokehOptions


@pytest.mark.parametrize("fields, says", [
    (dict(method="svd"), "convolution method = 'svd'.*windows, lowrank, fast"),
    (dict(blend=0), "blend = 0.*>= 1 px"),
    (dict(blend=2.5), "blend = 2.5"),
    (dict(support_eps=0.5), r"support_eps = 0.5.*\[0, 0.5\)"),
    (dict(rank_eps=-0.1), r"rank_eps = -0.1.*\[0, 0.5\)"),
    (dict(tile=0), "tile = 0.*>= 1"),
    (dict(chunk=True), "chunk = True"),
    (dict(accelerator="cuda", method="fast"), "accelerator = 'cuda'"),
    (dict(accelerator="torch"), "accelerator = 'torch'.*method 'fast'"),
])
def test_convolve_options_refuse_bad_values(fields, says):
    with pytest.raises(InputRangeError, match=says):
        ConvolveOptions(**fields)


def test_convolve_blend_beyond_half_the_patch_is_refused_with_the_range():
    img = np.zeros((16, 16, 3), np.float32)
    kern = np.zeros((2, 2, 3, 3, 3), np.float32)
    kern[..., 1, 1] = 1.0
    with pytest.raises(InputRangeError, match=r"blend = 5.*\[1, 4\] px"):
        patch_convolve(img, kern, 8, ConvolveOptions(blend=5))
    with pytest.raises(InputRangeError, match="patch size = 7"):
        patch_convolve(img, kern, 7)
    with pytest.raises(InputRangeError, match="options"):
        patch_convolve(img, kern, 8, {"method": "fast"})
    assert np.array_equal(patch_convolve(img + 0.25, kern, 8, ConvolveOptions(blend=4)), img + 0.25)


def test_options_are_frozen():
    with pytest.raises(dataclasses.FrozenInstanceError):
        ConvolveOptions().method = "fast"
    with pytest.raises(dataclasses.FrozenInstanceError):
        BokehOptions(focus_m=2.0).patch = 8


@pytest.mark.parametrize("fields, says", [
    (dict(), "keep / focus.*a keep range"),
    (dict(keep=(2.0, 1.0)), "keep.*0 < near <= far"),
    (dict(keep=3.0), "keep"),
    (dict(focus_m=-1.0), "focus = -1.0.*> 0"),
    (dict(focus_m="nearby"), "focus = 'nearby'.*'prescribed'"),
    (dict(focus_m=2.0, settings=PSFSettings(focus_distance_m=3.0)), "settings' own focus_distance_m 3.0"),
    (dict(focus_m=2.0, patch=15), "patch = 15.*even"),
    (dict(focus_m=2.0, n_layers=0), r"n_layers = 0.*\[1, 256\]"),
    (dict(focus_m=2.0, occlusion=1), "occlusion = 1.*True or False"),
    (dict(focus_m=2.0, interpolation="sinc"), "interpolation = 'sinc'"),
    (dict(focus_m=2.0, convolution="svd"), "convolution = 'svd'"),
    (dict(focus_m=2.0, rank_eps=0.7), "rank_eps = 0.7"),
    (dict(focus_m=2.0, multires=-1.0), "multires"),
    (dict(focus_m=2.0, max_level=9), "max_level = 9"),
    (dict(focus_m=2.0, multires=2.0, convolution="lowrank"), "multires with convolution"),
    (dict(focus_m=2.0, geometry=(480, 640)), "geometry"),
])
def test_bokeh_options_refuse_bad_values(fields, says):
    with pytest.raises(InputRangeError, match=says):
        BokehOptions(**fields)


def test_bokeh_options_defaults_and_derived_options():
    o = BokehOptions(keep=[1.1, 1.3])
    assert o.keep == (1.1, 1.3) and o.max_level == DEFAULT_MAX_LEVEL and o.focus_distance_m is None
    assert o.convolve_options() == ConvolveOptions(method="fast", rank_eps=2e-2)
    assert o.library_settings() == PSFSettings()
    f = BokehOptions(focus_m=2, settings=PSFSettings(kernel_size=21))
    assert f.focus_distance_m == 2.0 and f.library_settings() == PSFSettings(kernel_size=21, focus_distance_m=2.0)
    assert BokehOptions(focus_m="prescribed").library_settings().focus_distance_m is None
    assert dataclasses.replace(o, convolution="lowrank").convolve_options().method == "lowrank"
