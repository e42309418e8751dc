"""The PSF library's reader on the user's own files: a damaged file is said
and kept (never deleted as the disk cache's own would be), a file declaring
more than its arrays hold is refused before any allocation, a file of
another kind (a shipped ray map) is one line, and a fuzz of byte and value
mutations gives a library or one project error."""
import io
import json
import tracemalloc
import zipfile
from pathlib import Path

import numpy as np
import pytest

from dcdi_core.cli import main
from dcdi_core.errors import DcdiError
from dcdi_core.optics.lens import load_lens
from dcdi_core.psf.compute import PSFSettings
from dcdi_core.psf.library import LibraryGrid, PSFLibrary

FAST = PSFSettings(pupil_samples=16, n_wavelengths=3, kernel_size=15)
pytestmark = pytest.mark.filterwarnings("ignore::dcdi_core.psf.compute.KernelTooSmallWarning")   # a small file
GRID = LibraryGrid(n_fields=3, n_depths=2)
RAYMAP = Path(__file__).resolve().parents[2] / "dcdi_core" / "psf" / "data" / "raymap" / "zeiss-sonnar-50mm-f1-5.npz"


@pytest.fixture(scope="module")
def library_bytes(tmp_path_factory):
    lib = PSFLibrary(load_lens("mos-s1"), FAST, GRID, None)
    lib.ensure(bins=[0, 2])
    p = tmp_path_factory.mktemp("lib") / "lib.npz"
    lib.save(p)
    return p.read_bytes()


def _rewrite(data: bytes, meta=None, arrays=None) -> bytes:
    """The library file ``data`` with its meta (a dict) or some arrays replaced."""
    with np.load(io.BytesIO(data), allow_pickle=False) as z:
        content = {k: z[k] for k in z.files}
    if meta is not None:
        content["meta"] = np.array(json.dumps(meta))
    content.update(arrays or {})
    out = io.BytesIO()
    np.savez_compressed(out, **content)
    return out.getvalue()


def _meta(data: bytes) -> dict:
    with np.load(io.BytesIO(data), allow_pickle=False) as z:
        return json.loads(str(z["meta"]))


def test_a_users_damaged_library_is_said_and_kept(library_bytes, tmp_path, capsys):
    """One PSF value changed (the checksum no longer matches): `psflib show`
    exits 2 naming the file, and the file is still there, unchanged (the
    reader once deleted it, "rebuilding" it as the cache's)."""
    with np.load(io.BytesIO(library_bytes)) as z:
        psf = z["psf"].copy()
    psf[0, 0, 0, 7, 7] += 0.25
    damaged = _rewrite(library_bytes, arrays={"psf": psf})
    f = tmp_path / "mine.npz"
    f.write_bytes(damaged)
    code = main(["psflib", "show", str(f), "--png", str(tmp_path / "grid.png")])
    err = capsys.readouterr().err
    assert code == 2 and "mine.npz" in err and "corrupt" in err and len(err.strip().splitlines()) == 1, err
    assert f.read_bytes() == damaged
    assert not (tmp_path / "grid.png").exists()


def test_a_file_declaring_a_huge_grid_is_refused_before_allocating(library_bytes, tmp_path):
    meta = _meta(library_bytes)
    meta["grid"]["n_fields"] = 2_000_000
    f = tmp_path / "huge.npz"
    f.write_bytes(_rewrite(library_bytes, meta=meta))
    assert f.stat().st_size < 100_000
    tracemalloc.start()
    try:
        with pytest.raises(DcdiError, match="huge.npz"):
            PSFLibrary.load(f)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 50e6, peak


def test_a_ray_map_given_as_a_library_is_one_line(tmp_path, capsys):
    code = main(["psflib", "show", str(RAYMAP), "--png", str(tmp_path / "grid.png")])
    err = capsys.readouterr().err
    assert code == 2 and "not a PSF library file" in err and "Traceback" not in err, err
    assert len(err.strip().splitlines()) == 1


def _mutations(data: bytes, rng):
    """Byte flips, truncations and meta values changed to the wrong type or size."""
    for _ in range(25):
        b = bytearray(data)
        for i in rng.integers(0, len(b), size=int(rng.integers(1, 8))):
            b[i] ^= int(rng.integers(1, 256))
        yield bytes(b)
    for cut in (10, len(data) // 3, len(data) - 5):
        yield data[:cut]
    meta = _meta(data)
    for path, value in ((("settings", "kernel_size"), 10 ** 9), (("settings", "kernel_size"), "x"),
                        (("settings",), None), (("grid", "n_depths"), -3), (("grid", "near_m"), float("nan")),
                        (("settings", "band_nm"), 5), (("lens_fingerprint",), None), (("settings", "bogus"), 1)):
        m = json.loads(json.dumps(meta))
        d = m
        for k in path[:-1]:
            d = d[k]
        d[path[-1]] = value
        yield _rewrite(data, meta=m)


def test_fuzzed_library_files_give_a_library_or_one_project_error(library_bytes, tmp_path):
    rng = np.random.default_rng(7)
    for i, data in enumerate(_mutations(library_bytes, rng)):
        f = tmp_path / f"fuzz-{i}.npz"
        f.write_bytes(data)
        try:
            lib = PSFLibrary.load(f)
        except DcdiError as e:
            assert f.name in str(e), e
        except zipfile.BadZipFile:
            pytest.fail(f"mutation {i}: a raw zip error")
        else:
            assert np.isfinite(lib.psf).all()
        assert f.read_bytes() == data                      # read, never changed or deleted
