"""The occlusion-aware bokeh's depth layers: where they are cut."""
import numpy as np


def test_bokeh_layers_share_out_the_depths_the_frame_holds():
    """Lights at 7 m before a wall at 9 m and an occluder at 1.5 m: each
    depth its own layer (equal widths over 0.11 to 0.67 diopters put the
    lights in the wall's layer, and they took its blur); a continuous
    range keeps equal widths."""
    from dcdi_core.render.bokeh import LAYER_BINS, _layer_edges, _layer_masks
    inv = np.full((60, 60), 1 / 9.0)
    inv[10:13, 10:13] = 1 / 7.0
    inv[:, 40:] = 1 / 1.5
    layers, idx = _layer_masks(inv, np.ones(inv.shape, bool), 12)
    assert len({int(idx[11, 11]), int(idx[30, 30]), int(idx[30, 50])}) == 3
    # the old equal widths: the lights and the wall in one layer
    assert int((1 / 7.0 - 1 / 9.0) // ((1 / 1.5 - 1 / 9.0) / 12)) == 0
    ramp = np.linspace(0.1, 0.9, 5000)
    edges = _layer_edges(ramp, 0.1, 0.9, 8)
    assert np.allclose(edges, np.linspace(0.1, 0.9, 9), atol=0.8 / LAYER_BINS * 1.01)
