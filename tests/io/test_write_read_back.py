"""A writer that reports success yet leaves a broken file (a full disk
under a library that does not say so) is an error, and nothing is left at
the output path: each image is read back whole before it is renamed into
place."""
import numpy as np
import pytest

from dcdi_core.io import images
from dcdi_core.io.image_file import ImageFileError


class _Truncating:
    """OpenImageIO with a writer whose file loses its second half on close,
    as a full disk can leave it while the library reports success."""

    def __init__(self, oiio):
        self._oiio = oiio
        outer = self

        class ImageOutput:
            @staticmethod
            def create(fmt):
                return _Out(outer._oiio.ImageOutput.create(fmt))
        self.ImageOutput = ImageOutput

    def __getattr__(self, name):
        return getattr(self._oiio, name)


class _Out:
    def __init__(self, real):
        self._real, self._path = real, None

    def open(self, path, spec):
        self._path = path
        return self._real.open(path, spec)

    def close(self):
        ok = self._real.close()
        with open(self._path, "r+b") as f:
            f.truncate(max(f.seek(0, 2) // 2, 1))
        return ok

    def __getattr__(self, name):
        return getattr(self._real, name)


@pytest.mark.parametrize("name", ["out.png", "out.exr", "out.jpg"])
def test_a_silently_truncated_write_is_an_error_and_leaves_nothing(tmp_path, monkeypatch, name):
    oiio = images._oiio()
    if oiio is None:
        pytest.skip("OpenImageIO is not installed: the numpy EXR writer checks its size instead")
    monkeypatch.setattr(images, "_oiio", lambda: _Truncating(oiio))
    out = tmp_path / name
    with pytest.raises(ImageFileError, match="cannot be read back"):
        images.write_image(out, np.full((64, 96, 3), 0.4, np.float32))
    assert not out.exists() and not list(tmp_path.glob("*.tmp*"))


def test_an_intact_write_reads_back(tmp_path):
    img = np.random.default_rng(0).random((40, 60, 3), dtype=np.float32)
    images.write_image(tmp_path / "ok.exr", img)
    assert np.array_equal(images.read_image(tmp_path / "ok.exr"), img)


def test_a_zip_write_that_fails_closes_its_zip_quietly(tmp_path):
    """A write that fails inside an .npz (the disk full at the second array)
    raises one error, leaves nothing, and prints no "Exception ignored"
    afterwards (numpy's savez left its zip for the collector to close onto
    the closed file)."""
    import subprocess
    import sys
    script = f"""
import errno, gc, numpy as np
from dcdi_core.io import npzfile
real = np.lib.format.write_array
calls = []
def full(fid, a, **k):
    calls.append(1)
    if len(calls) == 2:
        raise OSError(errno.ENOSPC, "No space left on device")
    return real(fid, a, **k)
np.lib.format.write_array = full
try:
    npzfile.write_format({str(tmp_path / 'x.npz')!r}, {{}}, {{"a": np.zeros(1000), "b": np.ones(1000)}}, "t", 1)
except OSError as e:
    print("raised", e.errno)
gc.collect()
"""
    p = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True)
    assert p.stdout.strip().startswith("raised"), p.stdout + p.stderr
    assert "Exception ignored" not in p.stderr and "Traceback" not in p.stderr, p.stderr
    assert list(tmp_path.iterdir()) == []


def test_a_picture_that_cannot_be_read_back_is_an_error(tmp_path, monkeypatch):
    """matplotlib reporting success on a full disk (the PNG cut short):
    save_figure refuses it and leaves nothing; the figure is closed."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from dcdi_core.atomic import save_figure
    from dcdi_core.errors import OutputError
    fig = plt.figure()
    real = fig.savefig

    def cut_short(path, **k):
        real(path, **k)
        with open(path, "r+b") as f:
            f.truncate(100)
    monkeypatch.setattr(fig, "savefig", cut_short)
    with pytest.raises(OutputError, match="cannot be read back"):
        save_figure(fig, tmp_path / "p.png")
    assert list(tmp_path.iterdir()) == [] and not plt.fignum_exists(fig.number)
