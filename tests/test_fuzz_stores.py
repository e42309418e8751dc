"""Fuzzed ray maps and lens files: each mutation is read as a store that
serves finite PSFs, or refused with one project error naming the file;
never another exception, never NaN served in silence."""
import re
import warnings

import numpy as np

from support.build import ROOT

from dcdi_core.errors import DcdiError

RAYMAP = ROOT / "dcdi_core" / "psf" / "data" / "raymap" / "zeiss-jena-tessar-50mm-f2-8.npz"


def _raymap_mutations(rng):
    from dcdi_core.psf.raymap import RayMap
    rm = RayMap.load(RAYMAP)
    data = RAYMAP.read_bytes()
    for _ in range(12):                                   # bytes flipped: the checksum or the zip refuses
        b = bytearray(data)
        for i in rng.integers(0, len(b), size=int(rng.integers(1, 6))):
            b[i] ^= int(rng.integers(1, 256))
        yield "bytes", bytes(b)
    yield "truncated", data[: len(data) // 2]
    # values changed with the checksum made anew (a file written by another hand)
    for name in ("xy", "chroma", "clip", "chief", "aim", "geometry", "reference_geometry"):
        for value in (np.nan, np.inf, 1e30, -1e12, 0.0):
            a = np.array(rm.arrays[name], dtype=np.float64)
            if a.size == 0:
                continue
            flat = a.reshape(-1)
            flat[rng.integers(0, flat.size, size=3)] = value
            with np.errstate(over="ignore"):              # 1e30 in a float16 array: inf, as a file may hold
                yield f"{name}={value}", dict(rm.arrays, **{name: a.astype(rm.arrays[name].dtype)})
    for key, value in (("stop_semi_diameter_mm", -1.0), ("sensor_distance_mm", 1e300), ("far_plane_mm", 0.0),
                       ("lens_id", "../x"), ("recipe", {"n_fields": 10 ** 9})):
        yield f"meta {key}", (dict(rm.meta, **{key: value}), rm.arrays)


def _write(path, mutation):
    from dcdi_core.io.npzfile import write_format
    from dcdi_core.psf import raymap as R
    from dcdi_core.psf.raymap import RayMap
    if isinstance(mutation, bytes):
        path.write_bytes(mutation)
        return
    meta, arrays = mutation if isinstance(mutation, tuple) else (RayMap.load(RAYMAP).meta, mutation)
    write_format(path, meta, {k: np.asarray(v) for k, v in arrays.items()}, R.FORMAT, R.FORMAT_VERSION)


def test_fuzzed_ray_maps_serve_finite_psfs_or_are_refused(tmp_path):
    from dcdi_core.optics.lens import load_lens
    from dcdi_core.psf.compute import PSFSettings
    from dcdi_core.psf.raymap import RayMap, RayMapLibrary
    lens = load_lens("zeiss-jena-tessar-50mm-f2-8")
    settings = PSFSettings(pupil_samples=16, n_wavelengths=3, kernel_size=31, pixel_pitch_mm=0.02)
    rng = np.random.default_rng(3)
    for i, (what, mutation) in enumerate(_raymap_mutations(rng)):
        f = tmp_path / f"fuzz-{i}.npz"
        try:
            _write(f, mutation)
        except DcdiError:
            continue                                      # refused before it was written
        try:
            rm = RayMap.load(f)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                kern = RayMapLibrary(rm, lens, settings).kernels(np.array([0.0, 0.7]), np.array([2.0, 5.0]))
        except DcdiError as e:
            assert f.name in str(e) or "no ray" in str(e) or "lens" in str(e), (what, e)
            continue
        assert np.isfinite(kern).all(), what


def _lens_mutations(text, rng):
    numbers = [m for m in re.finditer(r"(?m)^(\w+) = (-?[0-9][0-9.e+-]*)$", text)]
    for value in ("1e300", "-1e300", "nan", "inf", "-inf", "0", "-0.0", "1e-300", "99999999999999999999", '"x"'):
        for m in rng.choice(len(numbers), size=3, replace=False):
            n = numbers[int(m)]
            yield f"{n.group(1)}={value}", text[:n.start(2)] + value + text[n.end(2):]
    lines = text.splitlines()
    for _ in range(5):
        k = int(rng.integers(0, len(lines)))
        yield f"line {k} removed", "\n".join(lines[:k] + lines[k + 1:])


def test_fuzzed_lens_files_trace_finite_psfs_or_are_refused(tmp_path):
    from dcdi_core.optics.lens import load_lens
    from dcdi_core.psf.compute import PSFSettings, psf
    text = (ROOT / "lenses" / "zeiss-jena-tessar-50mm-f2-8.toml").read_text()
    settings = PSFSettings(pupil_samples=8, n_wavelengths=3, kernel_size=15)
    rng = np.random.default_rng(5)
    for i, (what, mutated) in enumerate(_lens_mutations(text, rng)):
        f = tmp_path / f"fuzz-{i}.toml"
        f.write_text(mutated)
        try:
            lens = load_lens(f)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                r = psf(lens, depth_m=3.0, field=0.5, settings=settings)
        except DcdiError:
            continue
        assert np.isfinite(r.psf).all(), what
