"""Textures with photographs' statistics (dcdi_core.dataset.natural): the
drawn spectrum slope is the texture's, colours stay in range, the same seed
gives the same bytes, the folder for --textures is never overwritten, and
bad options are refused in one line before any file."""
from __future__ import annotations

import json

import numpy as np
import pytest

from dcdi_core.cli import main
from dcdi_core.dataset.natural import NaturalTextureOptions, natural_texture, power_law_noise, write_textures
from dcdi_core.dataset.textures import TextureLibrary
from dcdi_core.errors import InputRangeError


def _slope(x: np.ndarray) -> float:
    """The power spectrum's log-log slope over 4-64 cycles per texture."""
    n = x.shape[0]
    p = np.abs(np.fft.fft2(x - x.mean())) ** 2
    f = np.hypot(*np.meshgrid(np.fft.fftfreq(n), np.fft.fftfreq(n), indexing="ij")) * n
    ring = (f >= 4) & (f <= 64)
    return -np.polyfit(np.log(f[ring]), np.log(p[ring]), 1)[0]


@pytest.mark.parametrize("slope", [1.6, 2.0, 2.8])
def test_the_noise_has_the_asked_spectrum(slope):
    x = power_law_noise(np.random.default_rng(0), 256, slope)
    assert abs(_slope(x) - slope) < 0.15
    assert abs(x.mean()) < 1e-9 and abs(x.std() - 1.0) < 1e-9


def test_a_texture_without_edges_keeps_its_drawn_slope_and_range():
    options = NaturalTextureOptions(slope_range=(2.4, 2.4), edge_share_range=(0.0, 0.0), contrast_range=(0.2, 0.2))
    img = natural_texture(np.random.default_rng(3), 256, options)
    assert img.shape == (256, 256, 3) and img.dtype == np.float32
    assert np.isfinite(img).all() and img.min() >= 0.0 and img.max() <= 1.0
    assert abs(_slope(np.log(img.mean(-1))) - 2.4) < 0.2


def test_textures_differ_and_repeat_by_seed():
    a = natural_texture(np.random.default_rng([0, 1]), 64)
    b = natural_texture(np.random.default_rng([0, 1]), 64)
    c = natural_texture(np.random.default_rng([0, 2]), 64)
    assert np.array_equal(a, b) and not np.array_equal(a, c)


def test_write_textures_makes_a_texture_library_and_never_overwrites(tmp_path):
    paths = write_textures(tmp_path / "t", 3, seed=5, size=32)
    assert [p.name for p in paths] == ["natural-0000.png", "natural-0001.png", "natural-0002.png"]
    assert len(TextureLibrary.from_folder(tmp_path / "t").sets) == 3
    before = paths[0].read_bytes()
    with pytest.raises(InputRangeError, match="seed 5"):            # other settings: never mixed into the folder
        write_textures(tmp_path / "t", 1, seed=9, size=32)
    assert paths[0].read_bytes() == before
    (tmp_path / "t" / "textures.json").unlink()                      # textures of unknown making: not touched
    with pytest.raises(InputRangeError, match="nothing is overwritten"):
        write_textures(tmp_path / "t", 3, seed=5, size=32)


def test_a_stopped_run_resumes_with_the_same_settings(tmp_path):
    """A run stopped after some textures (here: one removed) is resumed by
    the same command: the files there are kept, the missing one made as the
    whole run would have made it, and a larger --count extends the set."""
    whole = [p.read_bytes() for p in write_textures(tmp_path / "a", 3, seed=2, size=32)]
    write_textures(tmp_path / "b", 3, seed=2, size=32)
    (tmp_path / "b" / "natural-0001.png").unlink()
    kept = (tmp_path / "b" / "natural-0000.png").stat().st_mtime_ns
    paths = write_textures(tmp_path / "b", 4, seed=2, size=32)
    assert [p.read_bytes() for p in paths[:3]] == whole and paths[3].exists()
    assert (tmp_path / "b" / "natural-0000.png").stat().st_mtime_ns == kept


def test_textures_are_checked_before_any_work(tmp_path, monkeypatch):
    """The memory a texture takes (stated: 160 bytes a pixel) and the PNG
    writer are checked before a texture is made or a folder created."""
    from dcdi_core import memory
    from dcdi_core.dataset import natural
    from dcdi_core.errors import MemoryLimitError
    from dcdi_core.io import image_checks
    made = []
    monkeypatch.setattr(natural, "natural_texture", lambda *a, **k: made.append(1) or np.zeros((8, 8, 3)))
    monkeypatch.setattr(memory, "available_bytes", lambda: 4 << 30)
    with pytest.raises(MemoryLimitError, match="--size 8192"):
        write_textures(tmp_path / "big", 1, size=8192)
    monkeypatch.setattr(image_checks, "_oiio", lambda: None)
    with pytest.raises(Exception, match="OpenImageIO"):
        write_textures(tmp_path / "nooiio", 1, size=32)
    assert made == [] and not (tmp_path / "big").exists() and not (tmp_path / "nooiio").exists()


@pytest.mark.parametrize("kw, field", [({"slope_range": (3.0, 2.0)}, "slope_range"),
                                       ({"contrast_range": (0.0, 1.0)}, "contrast_range"),
                                       ({"patches": -1}, "patches"), ({"saturated_share": 2.0}, "saturated_share"),
                                       ({"chroma_share": "x"}, "chroma_share")])
def test_bad_options_are_refused_naming_the_field(kw, field):
    with pytest.raises(InputRangeError, match=field):
        NaturalTextureOptions(**kw)


def test_cli_writes_the_folder_and_refuses_bad_input_in_one_line(tmp_path, capsys):
    assert main(["dataset", "textures", "-o", str(tmp_path / "t"), "--count", "2", "--size", "32"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["textures"] == 2 and len(list((tmp_path / "t").glob("natural-*.png"))) == 2
    assert main(["dataset", "textures", "-o", str(tmp_path / "u"), "--count", "2", "--size", "8"]) != 0
    err = capsys.readouterr().err.strip()
    assert "--size" in err and len(err.splitlines()) == 1 and not (tmp_path / "u").exists()
