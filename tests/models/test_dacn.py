"""DACN: parameter counts of the named configurations, the ablation switches,
shapes for any size, determinism, a tiny model overfits one pair."""
import pytest

torch = pytest.importorskip("torch")
F = torch.nn.functional

from dcdi_core.models.dacn.spec import CONFIGS, DACNSpec, named  # noqa: E402
from dcdi_core.errors import InputRangeError  # noqa: E402


@pytest.fixture(autouse=True)
def _one_thread():
    torch.set_num_threads(1)


def _model(spec, seed=0):
    from dcdi_core.models.dacn.arch import DACN
    torch.manual_seed(seed)
    return DACN(spec)


def _count(spec):
    from dcdi_core.models.dacn.arch import count_parameters
    return count_parameters(_model(spec))


def test_named_configs_and_the_papers_parameter_count():
    assert list(CONFIGS) == ["tiny", "tiny-rb", "refine", "demo", "paper"]
    # the released configuration (C = 180, 6 x 6 RSTB, SwinIR's tail): 14.7 M
    assert _count(CONFIGS["paper"]) == 14_664_265
    assert _count(CONFIGS["demo"]) == 1_515_331                # the demo's 1.5 M
    assert _count(CONFIGS["tiny"]) == 285_538
    with pytest.raises(InputRangeError, match="racm"):
        DACNSpec(racm="transformer")
    with pytest.raises(InputRangeError, match="DACN config"):
        named("huge")


@pytest.mark.parametrize("racm", ["rb", "rstb"])
def test_each_switch_changes_the_parameter_count_as_expected(racm):
    c, g = 12, 2
    base = DACNSpec(channels=c, groups=g, blocks=1, racm=racm, rdicab=False, d2cb=False)
    n0 = _count(base)
    # RDICAB: two channel LayerNorms, Q K V and the projection (1x1, no bias),
    # a temperature per head (4), the MLP's LayerNorm, C -> 2C -> C
    rdicab = 2 * 2 * c + 4 * c * c + 4 + 2 * c + (c * 2 * c + 2 * c) + (2 * c * c + c)
    # D2CB per group: offset net 2 x (1x1 C -> C), the deformable conv's
    # weights and bias, its offset/mask conv 3x3 C -> 27
    d2cb = g * (2 * (c * c + c) + 9 * c * c + c + 27 * 9 * c + 27)
    assert _count(DACNSpec(**{**base.as_dict(), "rdicab": True})) == n0 + rdicab
    assert _count(DACNSpec(**{**base.as_dict(), "d2cb": True})) == n0 + d2cb
    assert _count(DACNSpec(**{**base.as_dict(), "rdicab": True, "d2cb": True})) == n0 + rdicab + d2cb
    # the paper's tail: C -> 64, 2 x (64 -> 256), 64 -> 3 instead of C -> 48
    paper_tail = (9 * c * 64 + 64) + 2 * (9 * 64 * 256 + 256) + (9 * 64 * 3 + 3) - (9 * c * 48 + 48)
    assert _count(DACNSpec(**{**base.as_dict(), "tail": "paper"})) == n0 + paper_tail


@pytest.mark.parametrize("racm", ["rb", "rstb"])
def test_any_size_in_and_out_and_the_untrained_network_returns_its_input(racm):
    spec = DACNSpec(channels=12, groups=1, blocks=2, racm=racm, window=4)
    m = _model(spec)
    for h, w in [(1, 1), (13, 7), (33, 50)]:
        img, dep = torch.rand(2, 3, h, w), torch.rand(2, 1, h, w)
        out = m(img, dep)
        assert out.shape == (2, 3, h, w) and torch.isfinite(out).all()
        torch.testing.assert_close(out, img)              # zero-initialised last conv + global residual
    with pytest.raises(ValueError, match="expected"):
        m(torch.rand(1, 3, 8, 8), torch.rand(1, 1, 8, 9))


def test_same_seed_same_weights_and_outputs():
    spec = DACNSpec(channels=12, groups=2, blocks=2, window=4)
    a, b, c = _model(spec, 3), _model(spec, 3), _model(spec, 4)
    for (ka, va), (kb, vb) in zip(a.state_dict().items(), b.state_dict().items()):
        assert ka == kb and torch.equal(va, vb)
    assert any(not torch.equal(va, vc) for va, vc in zip(a.state_dict().values(), c.state_dict().values()))
    with torch.no_grad():                                  # make the output depend on every layer
        for m in (a, b):
            torch.manual_seed(9)
            for p in m.parameters():
                p.add_(0.05 * torch.randn_like(p))
    img, dep = torch.rand(1, 3, 21, 19), torch.rand(1, 1, 21, 19)
    ya = a(img, dep)
    assert torch.equal(ya, b(img, dep)) and not torch.allclose(ya, img)


def test_a_tiny_model_overfits_one_pair():
    """L1 falls tenfold (from the capture's own error) on one 32 x 32 crop."""
    g = torch.Generator().manual_seed(0)
    sharp = F.avg_pool2d(torch.rand(1, 3, 34, 34, generator=g), 3, 1)       # (1, 3, 32, 32)
    k = torch.tensor([1.0, 4, 6, 4, 1])
    k = (k[:, None] * k[None]) / 256
    blur = F.conv2d(F.pad(sharp, (2, 2, 2, 2), mode="reflect"), k.expand(3, 1, 5, 5), groups=3)
    depth = torch.linspace(0, 1, 32).view(1, 1, 1, 32).expand(1, 1, 32, 32)
    m = _model(named("tiny", channels=16))
    opt = torch.optim.Adam(m.parameters(), 2e-3, betas=(0.9, 0.99))
    l0 = (blur - sharp).abs().mean().item()
    for _ in range(220):
        loss = (m(blur, depth) - sharp).abs().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    with torch.no_grad():
        final = (m(blur, depth) - sharp).abs().mean().item()
    assert final < 0.1 * l0, (final, l0)
