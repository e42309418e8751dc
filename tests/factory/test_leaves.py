"""The dead-leaves RGB-D generator (dcdi_core.dataset.leaves): same seed same
bytes, a depth map that is exactly its layers' depths, depths in the range,
texture energy and clipping on target, the user's textures used, and bad
input refused before any work."""
import json

import numpy as np
import pytest

from dcdi_core.dataset import statistics
from dcdi_core.dataset.leaves import BACKGROUND, LeavesOptions, leaves_layers, leaves_rgbd
from dcdi_core.dataset.textures import TextureLibrary
from dcdi_core.errors import InputRangeError

H, W = 240, 320


def _index_map(layers, height, width):
    """The nearest covering layer at every pixel centre, painted far to
    near over the whole frame with Layer.covers (not the generator's
    z-buffer, boxes or batches)."""
    y = (np.arange(height) + 0.5)[:, None]
    x = (np.arange(width) + 0.5)[None, :]
    index = np.full((height, width), -1)
    for layer in reversed(layers):
        index[layer.covers(x, y)] = layer.index
    return index


def test_the_same_seed_gives_the_same_bytes_and_another_seed_another_scene():
    a = leaves_rgbd(3, H, W)
    b = leaves_rgbd(3, H, W)
    assert a[0].tobytes() == b[0].tobytes() and a[1].tobytes() == b[1].tobytes() and a[2] == b[2]
    c = leaves_rgbd(4, H, W)
    assert not np.array_equal(a[0], c[0]) and not np.array_equal(a[1], c[1])
    assert a[0].dtype == np.float32 and a[0].shape == (H, W, 3)
    assert a[1].dtype == np.float32 and a[1].shape == (H, W)
    json.dumps(a[2])


@pytest.mark.parametrize("seed, size", [(0, (H, W)), (1, (97, 131)), (2, (4, 4))])
def test_the_depth_map_matches_its_layers_depths_exactly(seed, size):
    image, depth, info = leaves_rgbd(seed, *size)
    layers = leaves_layers(seed, *size)
    assert len(layers) == info["layers"] and layers[-1].kind == BACKGROUND
    index = _index_map(layers, *size)
    assert (index >= 0).all()                                  # the background covers everything
    expected = np.array([layer.depth_m for layer in layers], dtype=np.float32)[index]
    assert depth.tobytes() == expected.tobytes()               # bit for bit: never an average
    assert len(np.unique(index)) == info["visible_layers"]
    if size == (H, W):
        assert info["visible_layers"] > 100                    # depth edges everywhere


def test_depths_lie_in_the_range_and_every_layer_was_drawn_from_it():
    options = LeavesOptions(depth_range_m=(1.5, 4.0))
    for seed in range(3):
        _, depth, info = leaves_rgbd(seed, H, W, options)
        assert depth.min() >= 1.5 and depth.max() <= 4.0
        layers = leaves_layers(seed, H, W, options)
        d = np.array([layer.depth_m for layer in layers])
        assert (d >= 1.5).all() and (d <= 4.0).all() and (np.diff(d) >= 0).all()   # nearest first
        assert layers[-1].depth_m == 4.0 and info["background_depth_m"] == 4.0
        # log-uniform: about as many shapes per octave of depth
        shapes = np.log2(d[:-1])
        assert abs(np.mean(shapes < np.log2(np.sqrt(6.0))) - 0.5) < 0.08
    _, depth, _ = leaves_rgbd(0, H, W)
    bands = statistics.depth_band_counts(depth)
    assert bands.sum() == H * W and (bands[:4] > 0).all()     # near to far, all present by default


def test_texture_energy_and_clipping_are_on_target():
    for seed in range(3):
        image, _, _ = leaves_rgbd(seed, H, W)
        hf = statistics.high_frequency_share(image)
        assert 0.10 <= hf <= 0.30, (seed, hf)
        assert statistics.clipped_fraction(image) <= 0.005
        assert np.percentile(image, 1) >= 0.0 and np.percentile(image, 99) <= 0.9
    # the measure can fail: the same frame smoothed has too little fine texture
    from scipy.ndimage import gaussian_filter
    smooth = gaussian_filter(image, sigma=(1.5, 1.5, 0))
    assert statistics.high_frequency_share(smooth) < 0.10


def test_shapes_carry_texture_inside_not_only_at_their_edges():
    from scipy.ndimage import laplace, maximum_filter, minimum_filter
    for seed in range(2):
        image, depth, _ = leaves_rgbd(seed, H, W)
        luminance = image @ statistics.LUMINANCE.astype(np.float32)
        interior = minimum_filter(depth, 5) == maximum_filter(depth, 5)   # 2 px or more from any depth edge
        assert interior.mean() > 0.2
        detail = np.abs(laplace(luminance))[interior].mean() / luminance[interior].mean()
        assert detail > 0.02, (seed, detail)     # flat-coloured shapes (shading only) give about 0.0002


def test_edges_are_anti_aliased_while_the_depth_is_not():
    image, depth, _ = leaves_rgbd(5, H, W)
    values = {d: image[depth == d].reshape(-1, 3) for d in np.unique(depth)}
    # a pixel on an edge mixes layers' colours; the depth map only holds layers' depths
    assert len(np.unique(depth)) == len(values)
    gy = np.abs(np.diff(image.mean(axis=2), axis=0))
    edge = np.diff(depth, axis=0) != 0
    assert gy[edge].mean() > 2 * gy[~edge].mean()


def test_the_users_textures_are_used(tmp_path):
    from dcdi_core.io.images import write_image
    rng = np.random.default_rng(0)
    write_image(tmp_path / "bark.png", rng.random((40, 56, 3)).astype(np.float32) * 0.5)
    write_image(tmp_path / "cloth.png", np.full((32, 32, 3), [0.6, 0.1, 0.1], np.float32))
    library = TextureLibrary.from_folder(tmp_path)
    used = set()
    for seed in range(4):
        image, _, info = leaves_rgbd(seed, 96, 128, textures=library)
        used.update(info["textures"])
        assert info["photo_layers"] > 0
    assert used == {"bark", "cloth"}
    plain = leaves_rgbd(0, 96, 128)
    textured = leaves_rgbd(0, 96, 128, textures=library)
    assert plain[1].tobytes() == textured[1].tobytes()         # textures change colour, never the layout
    assert not np.array_equal(plain[0], textured[0]) and plain[2]["textures"] == []
    none = leaves_rgbd(0, 96, 128, LeavesOptions(photo_share=0.0), textures=library)
    assert none[2]["textures"] == [] and none[2]["photo_layers"] == 0


@pytest.mark.parametrize("args", [(0, 3, 64), (0, 64, 2), (0, 0, 64), (0, 64.0, 64), (-1, 64, 64),
                                  (0, 9000, 64), (0, True, 64)])
def test_bad_sizes_and_seeds_are_refused(args):
    with pytest.raises(InputRangeError):
        leaves_rgbd(*args)


@pytest.mark.parametrize("field, value", [
    ("depth_range_m", (10.0, 0.7)), ("depth_range_m", (0.0, 10.0)), ("depth_range_m", (1.0, float("inf"))),
    ("depth_range_m", (1.0,)), ("coverage", 0.0), ("coverage", float("nan")), ("size_exponent", 1.0),
    ("min_radius_px", 0.1), ("perspective_exponent", 2.0), ("thin_share", -0.1), ("texel_per_px", (0.5, 3.0)),
    ("tile_px", 100), ("tiles", 0), ("photo_share", 1.5), ("albedo_range", (0.5, 0.2)), ("coverage", "3"),
])
def test_bad_options_are_refused_naming_the_field(field, value):
    with pytest.raises(InputRangeError, match=f"LeavesOptions.{field}"):
        LeavesOptions(**{field: value})


def test_bad_options_and_textures_objects_are_refused_before_any_work():
    with pytest.raises(InputRangeError, match="options"):
        leaves_rgbd(0, 64, 64, options={"coverage": 2})
    with pytest.raises(InputRangeError, match="textures"):
        leaves_rgbd(0, 64, 64, textures="some/folder")
