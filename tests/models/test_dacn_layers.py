"""DACN's building blocks: the plain-torch modulated deformable convolution
(against F.conv2d and a per-pixel reference, gradients), RDICAB, D2CB, the
Swin and EDSR blocks."""
import math

import numpy as np
import pytest

torch = pytest.importorskip("torch")
F = torch.nn.functional

from dcdi_core.models.dacn.layers.deform_conv import (D2CB, ModulatedDeformConv3x3,  # noqa: E402
                                                 modulated_deform_conv3x3)


@pytest.fixture(autouse=True)
def _one_thread():
    torch.set_num_threads(1)


def _bilinear(img, y, x):
    """img (C, H, W) at real (y, x), zero outside: the four corners written out."""
    c, h, w = img.shape
    y0, x0 = math.floor(y), math.floor(x)
    out = np.zeros(c)
    for yy, wy in ((y0, 1 - (y - y0)), (y0 + 1, y - y0)):
        for xx, wx in ((x0, 1 - (x - x0)), (x0 + 1, x - x0)):
            if 0 <= yy < h and 0 <= xx < w:
                out += wy * wx * img[:, yy, xx]
    return out


def _reference(x, offset, mask, weight, bias):
    """DCNv2 3x3 (stride 1, padding 1) pixel by pixel, tap by tap (float64 numpy)."""
    n, c, h, w = x.shape
    o = weight.shape[0]
    out = np.zeros((n, o, h, w))
    for b in range(n):
        for r in range(h):
            for q in range(w):
                acc = bias.copy()
                for i in range(3):
                    for j in range(3):
                        k = 3 * i + j
                        v = _bilinear(x[b], r + i - 1 + offset[b, 2 * k, r, q], q + j - 1 + offset[b, 2 * k + 1, r, q])
                        acc += mask[b, k, r, q] * weight[:, :, i, j] @ v
                out[b, :, r, q] = acc
    return out


def test_deform_conv_is_conv2d_at_zero_offsets_and_unit_masks():
    g = torch.Generator().manual_seed(0)
    x = torch.randn(2, 5, 9, 7, generator=g)
    w = torch.randn(4, 5, 3, 3, generator=g)
    b = torch.randn(4, generator=g)
    got = modulated_deform_conv3x3(x, torch.zeros(2, 18, 9, 7), torch.ones(2, 9, 9, 7), w, b)
    torch.testing.assert_close(got, F.conv2d(x, w, b, padding=1), atol=1e-5, rtol=1e-5)


def test_deform_conv_equals_a_per_pixel_reference():
    rng = np.random.default_rng(1)
    n, c, o, h, w = 2, 3, 2, 5, 6
    x = rng.normal(size=(n, c, h, w))
    off = rng.uniform(-2.5, 2.5, size=(n, 18, h, w))      # reaches outside the input too
    mask = rng.uniform(0, 1, size=(n, 9, h, w))
    wt = rng.normal(size=(o, c, 3, 3))
    bias = rng.normal(size=o)
    want = _reference(x, off, mask, wt, bias)
    t = lambda a: torch.from_numpy(a).float()              # noqa: E731
    got = modulated_deform_conv3x3(t(x), t(off), t(mask), t(wt), t(bias)).double().numpy()
    np.testing.assert_allclose(got, want, atol=1e-5, rtol=0)
    got64 = modulated_deform_conv3x3(*(torch.from_numpy(a) for a in (x, off, mask, wt, bias))).numpy()
    np.testing.assert_allclose(got64, want, atol=1e-10, rtol=0)


def test_deform_conv_gradients():
    g = torch.Generator().manual_seed(2)
    x = torch.randn(1, 2, 4, 4, dtype=torch.float64, generator=g, requires_grad=True)
    # away from integer positions, where bilinear sampling has kinks
    off = (torch.rand(1, 18, 4, 4, dtype=torch.float64, generator=g) * 0.8 + 0.1).requires_grad_()
    mask = torch.rand(1, 9, 4, 4, dtype=torch.float64, generator=g, requires_grad=True)
    w = torch.randn(2, 2, 3, 3, dtype=torch.float64, generator=g, requires_grad=True)
    b = torch.randn(2, dtype=torch.float64, generator=g, requires_grad=True)
    assert torch.autograd.gradcheck(modulated_deform_conv3x3, (x, off, mask, w, b), eps=1e-6, atol=1e-6)


def test_deform_conv_module_starts_as_half_a_conv_and_learns_offsets():
    torch.manual_seed(0)
    m = ModulatedDeformConv3x3(4, 3, guide_channels=2)
    x, guide = torch.randn(1, 4, 6, 6), torch.randn(1, 2, 6, 6)
    # zero-initialised offset conv: zero offsets, sigmoid(0) = 0.5 masks
    torch.testing.assert_close(m(x, guide), F.conv2d(x, 0.5 * m.weight, m.bias, padding=1), atol=1e-5, rtol=1e-5)
    m(x, guide).square().sum().backward()
    assert m.conv_offset.weight.grad.abs().sum() > 0 and m.weight.grad.abs().sum() > 0
    d = D2CB(8)
    y = d(torch.randn(2, 8, 5, 7), torch.randn(2, 8, 5, 7))
    assert y.shape == (2, 8, 5, 7)


# --------------------------------------------------------------- attention
def test_rdicab_is_image_twice_at_zero_projections_and_depth_steers_it():
    from dcdi_core.models.dacn.layers.attention import RDICAB, heads_dividing
    assert [heads_dividing(c, 6) for c in (32, 48, 60, 180, 7)] == [4, 6, 6, 6, 1]
    torch.manual_seed(0)
    m = RDICAB(16, heads=4)
    img, dep = torch.randn(2, 16, 5, 6), torch.randn(2, 16, 5, 6)
    out = m(img, dep)
    assert out.shape == img.shape
    assert not torch.allclose(m(img, dep), m(img, torch.randn_like(dep)))      # K, V come from the depth
    with torch.no_grad():
        m.attn.proj.weight.zero_()
        m.mlp.fc2.weight.zero_()
        m.mlp.fc2.bias.zero_()
    torch.testing.assert_close(m(img, dep), 2 * img)                          # the residual and the long skip
    assert m.attn.temperature.shape == (4, 1, 1)


def test_channel_attention_is_linear_in_pixels_and_normalised():
    from dcdi_core.models.dacn.layers.attention import ChannelCrossAttention
    torch.manual_seed(1)
    a = ChannelCrossAttention(8, heads=2)
    x, y = torch.randn(1, 8, 4, 4), torch.randn(1, 8, 4, 4)
    # L2-normalised Q and K: scaling the inputs leaves the attention weights alone, V scales
    torch.testing.assert_close(a(x * 5.0, y * 3.0), 3.0 * a(x, y), atol=1e-5, rtol=1e-5)


# -------------------------------------------------------------------- swin
def _swinir_mask(h, w, ws, s):
    """The shifted-window mask as SwinIR builds it (three slices per axis)."""
    from dcdi_core.models.dacn.layers.swin import window_partition
    img = torch.zeros(1, h, w, 1)
    cnt = 0
    for hs in (slice(0, -ws), slice(-ws, -s), slice(-s, None)):
        for wsl in (slice(0, -ws), slice(-ws, -s), slice(-s, None)):
            img[:, hs, wsl, :] = cnt
            cnt += 1
    mw = window_partition(img, ws).squeeze(-1)
    m = mw[:, None, :] - mw[:, :, None]
    return m.masked_fill(m != 0, -100.0).masked_fill(m == 0, 0.0)


def test_swin_mask_is_swinirs_and_never_lets_a_pixel_attend_to_padding():
    from dcdi_core.models.dacn.layers.swin import attention_mask
    torch.testing.assert_close(attention_mask(16, 24, 8, 4), _swinir_mask(16, 24, 8, 4))
    assert attention_mask(16, 24, 8, 0) is None
    h, w, ws, s = 6, 11, 4, 2
    m = attention_mask(h, w, ws, s)
    hp, wp = 8, 12
    src_r = (torch.arange(hp) + s) % hp
    src_c = (torch.arange(wp) + s) % wp
    pad = (src_r[:, None] >= h) | (src_c[None, :] >= w)                  # rolled grid position holds padding
    from dcdi_core.models.dacn.layers.swin import window_partition
    pw = window_partition(pad.view(1, hp, wp, 1).float(), ws).squeeze(-1).bool()     # (windows, n)
    real_to_pad = (~pw)[:, :, None] & pw[:, None, :]
    assert real_to_pad.any() and (m[real_to_pad] == -100.0).all()


def test_swin_block_on_a_partial_window_sees_only_its_real_pixels():
    from dcdi_core.models.dacn.layers.swin import SwinBlock
    torch.manual_seed(0)
    blk = SwinBlock(12, heads=3, window=4, shift=0)
    x = torch.randn(1, 6, 7, 12)
    y = blk(x)
    # the bottom-right window holds rows 4-5, columns 4-6: alone, it gives the same
    torch.testing.assert_close(y[:, 4:, 4:], blk(x[:, 4:, 4:].contiguous()), atol=1e-5, rtol=1e-5)
    shifted = SwinBlock(12, heads=3, window=4, shift=2)
    assert shifted(x).shape == x.shape and torch.isfinite(shifted(x)).all()
