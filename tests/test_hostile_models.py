"""Model, basis and lens files read as hostile, and names read from files kept names.

Deterministic cases first (each failed on the code before the checks: an
absurd dilation loaded, NaN weights ran silently, a missing key was a
KeyError, no size limit, a manifest id ``../../x/escape`` reached outside the
folder), then property-based fuzzing (hypothesis; profiles in
tests/conftest.py: a few derandomised examples by default, many with
DCDI_HYPOTHESIS_PROFILE=long): a shipped depth-from-blur refinement, a small
Omni-Lens-Field and the shipped lens files, mutated (metadata values and
keys, array shapes, dtypes, NaN and inf, the zip cut short; lens numbers,
keys, surfaces multiplied, the text cut short), are loaded (and a loaded
refinement run) with either success or one project error (a ``DcdiError``),
never another exception, and the peak Python allocation stays below
:data:`PEAK_BYTES`. Each property also runs against a planted bug.
"""
from __future__ import annotations

import copy
import json
import shutil
import tempfile
import tomllib
import tracemalloc
import warnings
import zipfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dcdi_core.errors import DatasetError, DcdiError, InputRangeError
from dcdi_core.io import npzfile
from dcdi_core.errors import ModelFileError
from dcdi_core.models.runtime import dfd_refine
from dcdi_core.models.runtime.dfd_refine import DfdRefiner
from dcdi_core.io.model_npz import read_model_npz
from dcdi_core.psf.olf import OmniLensField, checksum
from dcdi_core.optics.errors import LensFileError, OpticsError, ZemaxImportError
from dcdi_core.optics.lens import MAX_LENS_FILE_BYTES, MAX_SURFACES, Lens, load_lens
from dcdi_core.optics.prescription_toml import dumps_prescription
from dcdi_core.psf.basis import BasisFileError, BasisStore

ROOT = Path(__file__).resolve().parents[1]
WEIGHTS = ROOT / "dcdi_core" / "models" / "weights"
REFINE = WEIGHTS / "dfd-refine-mos-s1.npz"
BASIS = ROOT / "dcdi_core" / "psf" / "data" / "basis" / "mos-s1.npz"
PEAK_BYTES = 200 * 2 ** 20
FIXTURES = [HealthCheck.function_scoped_fixture, HealthCheck.too_slow]


# ------------------------------------------------------------------ helpers
def read_trusted(path) -> tuple[dict, dict]:
    """(meta, arrays) of a file this test trusts (a shipped one), by numpy."""
    with np.load(path, allow_pickle=False) as z:
        return json.loads(str(z["meta"])), {k: z[k] for k in z.files if k != "meta"}


def write_npz(path, meta: dict, arrays: dict, *, fresh_checksum: bool = True, compressed: bool = False) -> Path:
    """``meta`` and ``arrays`` as an .npz, the checksum recomputed (what a
    hostile writer does) unless ``fresh_checksum`` is False."""
    meta = dict(meta)
    if fresh_checksum:
        meta["checksum"] = checksum(meta, arrays)
    (np.savez_compressed if compressed else np.savez)(path, meta=np.array(json.dumps(meta)), **arrays)
    return Path(path)


def refine_file(path, edit=None) -> Path:
    """The shipped MOS-S1 refinement at ``path``, ``edit(meta, arrays)`` applied, checksum recomputed."""
    meta, arrays = read_trusted(REFINE)
    if edit:
        edit(meta, arrays)
    return write_npz(path, meta, arrays)


def small_olf(path, edit=None) -> Path:
    """A small radial Omni-Lens-Field of MOS-S1 (width 8, no hidden layer,
    41 px kernels), its metadata the shipped OLF's for that lens."""
    meta, _ = read_trusted(WEIGHTS / "olf-radial.npz")
    meta = {k: meta[k] for k in ("format", "version", "dtype", "variant", "weights")}
    shipped, _ = read_trusted(WEIGHTS / "olf-radial.npz")
    entry = next(e for e in shipped["lenses"] if e["id"] == "mos-s1")
    meta["spec"] = {"variant": "radial", "lenses": ["mos-s1"], "kernel_sizes": [41], "hidden_layers": 0,
                    "width": 8, "first_width": None, "focus": False, "diopter_scale": 1 / 0.7,
                    "paper_grid": shipped["spec"]["paper_grid"]}
    meta["network"] = {"trunk": [["trunk0.weight", "trunk0.bias"], ["trunk1.weight", "trunk1.bias"]],
                       "heads": [["head0.weight", "head0.bias"]]}
    meta["lenses"] = [entry]
    rng = np.random.default_rng(0)
    arrays = {"trunk0.weight": rng.normal(size=(2, 3)), "trunk0.bias": np.zeros(2),
              "trunk1.weight": rng.normal(size=(8, 2)), "trunk1.bias": np.zeros(8),
              "head0.weight": rng.normal(size=(3 * 41 * 41, 8)), "head0.bias": np.zeros(3 * 41 * 41)}
    arrays = {k: v.astype(np.float32) for k, v in arrays.items()}
    if edit:
        edit(meta, arrays)
    return write_npz(path, meta, arrays)


def one_line(e: BaseException, *words) -> str:
    text = str(e)
    assert "\n" not in text and all(w in text for w in words), text
    return text


def peak_of(fn) -> int:
    """The peak Python allocation (bytes, tracemalloc: numpy's arrays included) while ``fn()`` runs."""
    tracemalloc.start()
    try:
        fn()
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


# ------------------------------------------------ depth-from-blur refinement
def test_an_absurd_dilation_is_refused_on_load_before_anything_is_allocated(tmp_path):
    path = refine_file(tmp_path / "r.npz", lambda m, a: m.update(dilations=[1, 1, 100_000, 1]))
    assert path.stat().st_size < 120_000                        # a 113 kB file
    with pytest.raises(ModelFileError) as e:
        DfdRefiner(path)
    one_line(e.value, "r.npz", "dilations[2]", "100000", f"[1, {dfd_refine.MAX_DILATION}]")


@pytest.mark.parametrize("field,value", [("channels", 10 ** 7), ("log_depth_channel", 28), ("tile_px", 0),
                                         ("dilations", [1] * 40), ("hypotheses_m", [0.7, -1.0])])
def test_every_size_in_the_refinements_metadata_has_a_range(tmp_path, field, value):
    path = refine_file(tmp_path / "r.npz", lambda m, a: m.update({field: value}))
    with pytest.raises(ModelFileError) as e:
        DfdRefiner(path)
    one_line(e.value, "r.npz", field, "allowed")


def test_a_layer_wider_or_larger_than_allowed_is_refused(tmp_path):
    def widen(m, a):                    # 3 x 3 kernels made 9 x 9: a 9 x 9 x dilation pad per layer
        a["w0"] = np.zeros((32, 28, 9, 9), np.float32)
    with pytest.raises(ModelFileError) as e:
        DfdRefiner(refine_file(tmp_path / "r.npz", widen))
    one_line(e.value, "w0", f"odd <= {dfd_refine.MAX_KERNEL}")


def test_nan_weights_with_a_valid_checksum_are_refused_on_load(tmp_path):
    def poison(m, a):
        a["w1"][0, 0, 1, 1] = np.nan
    with pytest.raises(ModelFileError) as e:
        DfdRefiner(refine_file(tmp_path / "r.npz", poison))
    one_line(e.value, "r.npz", "'w1'", "NaN", "finite")


def test_a_refinement_that_overflows_is_refused_instead_of_giving_the_far_limit(tmp_path):
    def huge(m, a):                     # finite weights whose sum overflows float32: inf, then NaN
        a["w3"][:] = 3e38
        a["b2"][:] = 1e30
    refiner = DfdRefiner(refine_file(tmp_path / "r.npz", huge))
    features = np.abs(np.random.default_rng(0).normal(size=(28, 3, 4))).astype(np.float32)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with pytest.raises(ModelFileError) as e:
            refiner(features)
    one_line(e.value, "r.npz", "non-finite")


@pytest.mark.parametrize("key", ["lens", "channels", "log_depth_channel", "dilations"])
def test_a_missing_metadata_key_is_one_line_naming_the_file_and_the_key(tmp_path, key):
    path = refine_file(tmp_path / "r.npz", lambda m, a: m.pop(key))
    with pytest.raises(ModelFileError) as e:
        DfdRefiner(path)
    one_line(e.value, "r.npz", f"'{key}'", "missing")


def test_dcdi_depth_estimate_refuses_a_poisoned_refinement_in_one_line(tmp_path, monkeypatch, capsys):
    """`dcdi depth estimate --refine FILE` with NaN weights (valid checksum):
    exit 2, one line naming the file and the array, not 10 m everywhere."""
    from conftest import write_rgbd_scene
    from dcdi_core.cli import main
    write_rgbd_scene(tmp_path, monkeypatch, 32, 48)

    def poison(m, a):
        a["w0"][:] = np.nan
    bad = refine_file(tmp_path / "bad.npz", poison)
    code = main(["depth", "estimate", "--image", str(tmp_path / "aif.exr"), "--camera", "mos-s1",
                 "-o", str(tmp_path / "d.exr"), "--refine", str(bad), "--rays", "16", "--wavelengths", "3",
                 "--kernel", "15", "--psf-source", "trace"])
    err = capsys.readouterr().err
    errors = [line for line in err.splitlines() if line.startswith("dcdi: error:")]
    assert code == 2 and len(errors) == 1 and "Traceback" not in err, err
    assert "bad.npz" in errors[0] and "'w0'" in errors[0] and "finite" in errors[0], err
    assert not (tmp_path / "d.exr").exists()


def test_a_missing_layer_is_one_line_naming_the_array(tmp_path):
    with pytest.raises(ModelFileError) as e:
        DfdRefiner(refine_file(tmp_path / "r.npz", lambda m, a: a.pop("b2")))
    one_line(e.value, "'b2'", "missing")


def test_a_model_file_over_the_size_limit_is_refused_before_it_is_read(tmp_path, monkeypatch):
    largest = max(p.stat().st_size for p in WEIGHTS.glob("*.npz"))
    assert npzfile.MAX_FILE_BYTES >= 50 * largest                # far above every shipped file
    monkeypatch.setattr(npzfile, "MAX_FILE_BYTES", REFINE.stat().st_size - 1)
    opened = []
    monkeypatch.setattr(zipfile, "ZipFile", lambda *a, **k: opened.append(a))
    with pytest.raises(ModelFileError) as e:
        DfdRefiner(REFINE)
    one_line(e.value, REFINE.name, "over the limit", f"at most {REFINE.stat().st_size - 1} bytes")
    assert opened == []                                          # refused before it was opened


def test_an_array_header_declaring_gigabytes_is_refused_before_its_data_is_allocated(tmp_path):
    path = refine_file(tmp_path / "r.npz")
    with zipfile.ZipFile(path, "a") as z:                        # 10^8 float32 declared, 16 bytes held
        header = "{'descr': '<f4', 'fortran_order': False, 'shape': (100000000,), }"
        header += " " * (63 - len(header)) + "\n"
        z.writestr("w9.npy", b"\x93NUMPY\x01\x00" + len(header).to_bytes(2, "little") + header.encode()
                   + bytes(16))
    caught = []
    peak = peak_of(lambda: caught.append(pytest.raises(ModelFileError, DfdRefiner, path)))
    one_line(caught[0].value, "r.npz", "'w9'", "declares")
    assert peak < 20 * 2 ** 20, peak


def test_a_small_zip_that_would_inflate_to_gigabytes_is_refused(tmp_path):
    path = tmp_path / "bomb.npz"
    zeros = np.zeros(64 * 2 ** 20, np.uint8)                     # 64 MiB of zeros: a 65 kB deflated member
    meta = {"format": "dcdi-dfd-refine", "version": 1}
    write_npz(path, meta, {"pad": zeros}, compressed=True)
    assert path.stat().st_size < 200_000
    caught = []
    peak = peak_of(lambda: caught.append(pytest.raises(ModelFileError, DfdRefiner, path)))
    one_line(caught[0].value, "bomb.npz", "uncompressed", f"{npzfile.EXPANSION} x the file's size")
    assert peak < 20 * 2 ** 20, peak


def test_pickles_stay_refused(tmp_path):
    path = tmp_path / "p.npz"
    np.savez(path, meta=np.array(json.dumps({"format": "dcdi-dfd-refine"})),
             w0=np.array([{"a": 1}], dtype=object))
    with pytest.raises(ModelFileError) as e:
        DfdRefiner(path)
    one_line(e.value, "p.npz", "pickles are refused")


# ------------------------------------------------------------------- the OLF
def test_a_small_olf_loads(tmp_path):
    olf = OmniLensField.load(small_olf(tmp_path / "o.npz"))
    assert olf.lens_ids == ["mos-s1"] and olf.kernel_size("mos-s1") == 41


def test_olf_nan_weights_are_refused_on_load(tmp_path):
    def poison(m, a):
        a["head0.weight"][5, 3] = np.inf
    with pytest.raises(ModelFileError) as e:
        OmniLensField.load(small_olf(tmp_path / "o.npz", poison))
    one_line(e.value, "o.npz", "'head0.weight'", "finite")


@pytest.mark.parametrize("where,key", [("lenses", "pixel_pitch_mm"), ("lenses", "psf_settings"),
                                       ("lenses", "depth_range_m"), ("spec", "width"), (None, "network")])
def test_an_olf_missing_a_key_is_one_line_naming_it(tmp_path, where, key):
    def drop(m, a):
        (m["lenses"][0] if where == "lenses" else m[where] if where else m).pop(key)
    with pytest.raises(ModelFileError) as e:
        OmniLensField.load(small_olf(tmp_path / "o.npz", drop))
    one_line(e.value, "o.npz", key, "missing")


@pytest.mark.parametrize("edit,field", [
    (lambda m, a: m["spec"].update(kernel_sizes=[100_001]), "spec.kernel_sizes[0]"),
    (lambda m, a: m["spec"].update(width=10 ** 9), "spec.width"),
    (lambda m, a: m["lenses"][0]["library_grid"].update(n_fields=10 ** 6), "lenses[0].library_grid.n_fields"),
    (lambda m, a: m["lenses"][0]["psf_settings"].update(colour=1), "lenses[0].psf_settings.colour"),
    (lambda m, a: m["lenses"][0].update(id="../../x"), "lenses[0].id"),
    (lambda m, a: a.update({"head0.weight": a["head0.weight"][:10]}), "head0.weight"),
])
def test_every_olf_size_and_name_is_checked_on_load(tmp_path, edit, field):
    with pytest.raises(ModelFileError) as e:
        OmniLensField.load(small_olf(tmp_path / "o.npz", edit))
    one_line(e.value, "o.npz", f"'{field}'", "allowed")


# ---------------------------------------------------- DACN and depth network
@pytest.mark.parametrize("name,fmt,edit,field", [
    ("dacn-mos-s1", "dcdi-dacn", lambda m: m["spec"].update(channels=10 ** 6), "spec.channels"),
    ("dacn-mos-s1", "dcdi-dacn", lambda m: m["spec"].update(groups=32, blocks=32), "spec"),
    ("dacn-mos-s1", "dcdi-dacn", lambda m: m["spec"].update(colour=True), "spec.colour"),
    ("dacn-mos-s1", "dcdi-dacn", lambda m: m.pop("step"), "step"),
    ("depth-mos-s1", "dcdi-depthnet", lambda m: m["spec"].update(widths=[4096, 4096]), "spec.widths[0]"),
    ("depth-mos-s1", "dcdi-depthnet", lambda m: m["spec"].update(widths=[1024, 1024]), "spec"),
])
def test_network_specs_are_checked_before_the_network_is_built(tmp_path, name, fmt, edit, field):
    meta, arrays = read_trusted(WEIGHTS / f"{name}.npz")
    edit(meta)
    path = write_npz(tmp_path / "n.npz", meta, arrays)
    with pytest.raises(ModelFileError) as e:
        read_model_npz(path, fmt, 1, "network")
    one_line(e.value, "n.npz", f"'{field}'", "allowed")


def test_the_runtimes_dacn_fields_are_the_dacn_specs():
    from dataclasses import fields

    from dcdi_core.models.dacn.spec import DACNSpec
    from dcdi_core.io import model_npz as npz
    known = set(npz.DACN_INTEGERS) | set(npz.DACN_RATIOS) | set(npz.DACN_CHOICES) | set(npz.DACN_FLAGS)
    assert known == {f.name for f in fields(DACNSpec)}


# ------------------------------------------------------------- PSF basis
@pytest.mark.parametrize("edit,field", [
    (lambda m: m["grid"].update(n_fields=10 ** 6), "grid.n_fields"),
    (lambda m: m.update(kernel_size=4001), "kernel_size"),
    (lambda m: m.update(lens_id="../../x"), "lens_id"),
    (lambda m: m.pop("psf_settings"), "psf_settings"),
])
def test_a_basis_store_is_checked_before_it_is_expanded(tmp_path, edit, field):
    meta, arrays = read_trusted(BASIS)
    edit(meta)
    path = write_npz(tmp_path / "b.npz", meta, arrays, compressed=True)
    with pytest.raises(BasisFileError) as e:
        BasisStore.load(path)
    one_line(e.value, "b.npz", f"'{field}'")


# --------------------------------------------------------------- lens files
def _surfaces_toml(n: int) -> str:
    surfs = "".join(f'[[surface]]\nradius_mm = inf\nthickness_mm = 1.0\nsemi_diameter_mm = 5.0\n'
                    f'stop = {"true" if i == 0 else "false"}\n\n' for i in range(n))
    return f'schema_version = 1\nid = "many"\n\n[sensor]\nsemi_diagonal_mm = 1.0\n\n{surfs}'


def test_a_lens_of_too_many_surfaces_is_refused_before_it_is_built(tmp_path):
    (tmp_path / "many.toml").write_text(_surfaces_toml(MAX_SURFACES + 800))
    with pytest.raises(LensFileError) as e:
        Lens.from_toml(tmp_path / "many.toml")
    one_line(e.value, "many.toml", str(MAX_SURFACES + 800), f"at most {MAX_SURFACES}")
    d = tomllib.loads(_surfaces_toml(1))
    d["surface"] = d["surface"] * 10 ** 6                       # minutes to build: refused at once
    with pytest.raises(LensFileError, match="1000000 surfaces"):
        Lens.from_dict(d)
    assert MAX_SURFACES >= 6 * max(len(tomllib.loads(p.read_text())["surface"]) for p in ROOT.glob("lenses/*.toml"))


def test_a_lens_file_over_the_size_limit_is_refused_before_it_is_read(tmp_path):
    text = (ROOT / "lenses" / "mos-s1.toml").read_text()
    big = tmp_path / "big.toml"
    big.write_text(text + "\n# " + "x" * MAX_LENS_FILE_BYTES + "\n")      # a valid lens, 1 MiB of comment
    with pytest.raises(LensFileError) as e:
        Lens.from_toml(big)
    one_line(e.value, "big.toml", "over the limit", str(MAX_LENS_FILE_BYTES))
    zmx = tmp_path / "big.zmx"
    zmx.write_bytes(b"NAME x\n" * (MAX_LENS_FILE_BYTES // 7 + 1))
    from dcdi_core.optics.zemax import read_zmx
    with pytest.raises(ZemaxImportError, match="over the limit"):
        read_zmx(zmx)


def test_a_zemax_file_of_too_many_surfaces_is_refused_while_it_is_parsed(tmp_path):
    from dcdi_core.optics.zemax import read_zmx
    surfs = "".join(f"SURF {i}\n  TYPE STANDARD\n  CURV 0\n  DISZ 1\n  DIAM 5\n" + ("  STOP\n" if i == 1 else "")
                    for i in range(MAX_SURFACES + 300))
    (tmp_path / "many.zmx").write_text("MODE SEQ\nUNIT MM\n" + surfs)
    with pytest.raises(ZemaxImportError) as e:
        read_zmx(tmp_path / "many.zmx")
    one_line(e.value, "many.zmx", f"{MAX_SURFACES} lens surfaces")


# ---------------------------------------------------------- names, not paths
VALID = ["mos-s1", "mos-s2", "6p", "double-gauss", "room-000009", "room-000009~0", "scene0", "radial",
         "leaves-000001", "Adirondack-perfect", "0000", "a_b.c"]
INVALID = ["", ".", "..", ".hidden", "../../x/escape", "a/b", "a\\b", "a\0b", "-x", "~x", "c:x", "a b",
           "x" * 129, 5, None, ["a"]]


def test_names_are_names():
    from dcdi_core.names import check_name, is_name
    assert all(is_name(v) for v in VALID)
    assert [v for v in INVALID if is_name(v)] == []
    with pytest.raises(DatasetError) as e:
        check_name("../../x/escape", "id", "m.jsonl")
    one_line(e.value, "m.jsonl", "'id'", "'../../x/escape'", "allowed")
    with pytest.raises(InputRangeError, match="lens id"):
        check_name("a/b", "lens id", error=InputRangeError)
    for lens in ROOT.glob("lenses/*.toml"):
        assert is_name(load_lens(lens).id)


def _factory_folder(root: Path, sid: str) -> Path:
    from dcdi_core.dataset import factory_folder as ff
    root.mkdir(parents=True)
    ff.append_record(root / ff.MANIFEST, {"id": "room-000000", "index": 0})
    with open(root / ff.MANIFEST, "a") as f:                    # what the factory never writes
        f.write(json.dumps({"id": sid, "index": 1}) + "\n")
    return root


def test_a_manifest_id_that_is_a_path_is_refused_before_anything_is_read_or_written(tmp_path):
    from dcdi_core.dataset.rgbd import FactoryFolder
    root = _factory_folder(tmp_path / "data" / "set", "../../x/escape")
    with pytest.raises(DatasetError) as e:
        FactoryFolder(root)
    one_line(e.value, "manifest.jsonl", "line 2", "'id'", "../../x/escape")


def test_pair_ids_that_are_paths_are_refused(tmp_path):
    from dcdi_core.dataset import factory_folder as ff
    from dcdi_core.models.dacn.data import DA2TConfig, build_pairs, finished_pairs, pair_path
    (tmp_path / "pairs.jsonl").write_text(json.dumps({"id": "../../escape~0"}) + "\n")
    with pytest.raises(DatasetError, match="pairs.jsonl, line 1"):
        finished_pairs(tmp_path)
    with pytest.raises(DatasetError, match="pair id"):
        pair_path(tmp_path, "../x~0")

    class Escape:                               # a source whose frame id is a path: nothing is built
        def ids(self):
            return ["../../escape"]

        def load(self, id):
            raise AssertionError("a frame was loaded")
    out = tmp_path / "out" / "o"
    with pytest.raises(DatasetError, match="pair id"):
        build_pairs(Escape(), out, DA2TConfig(lens="mos-s2"))
    assert not (tmp_path / "escape~0.npy").exists()
    layout = ff.FolderLayout(tmp_path)
    for call in (lambda: layout.aif("../x"), lambda: layout.lens_image("../l", "sharp", "room-000000"),
                 lambda: ff.sample_files("room-000000", ["a/b"])):
        with pytest.raises(DatasetError):
            call()
    (tmp_path / ff.SETTINGS_FILE).write_text(json.dumps({"lenses": ["mos-s1", "../../x"]}))
    with pytest.raises(DatasetError, match=r"lenses\[1\]"):
        ff.read_settings(tmp_path)


def test_lens_ids_and_model_keys_that_are_paths_are_refused(tmp_path, monkeypatch):
    from dcdi_core.shipped import network
    from dcdi_core.psf.basis import shipped_store
    (tmp_path / "lenses").mkdir()
    shutil.copy(ROOT / "lenses" / "mos-s1.toml", tmp_path / "outside.toml")
    monkeypatch.setenv("DCDI_LENS_PATH", str(tmp_path / "lenses"))
    with pytest.raises(OpticsError, match="not a lens id"):
        load_lens("../outside")                 # would read the file outside the lens folders
    with pytest.raises(InputRangeError):
        network("dacn").shipped_file("../../../x")
    with pytest.raises(InputRangeError):
        shipped_store("../x")
    d = tomllib.loads((ROOT / "lenses" / "mos-s1.toml").read_text())
    with pytest.raises(LensFileError, match="'id'"):
        Lens.from_dict(dict(d, id="a" * 129))
    assert network("dacn").shipped_file("mos-s1") is not None


# ------------------------------------------------------------ fuzz: models
JSON_VALUES = st.recursive(
    st.none() | st.booleans() | st.integers(-2 ** 70, 2 ** 70) | st.sampled_from([0, 1, -1, 10 ** 9, 2 ** 63])
    | st.floats(allow_nan=True, allow_infinity=True) | st.sampled_from(["", "../../x", "mos-s1", "x" * 300]),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=3),
    max_leaves=8)


def _paths(value, prefix=()):
    """Every key path into a JSON value (dict keys and list indices)."""
    out = [prefix] if prefix else []
    if isinstance(value, dict):
        for k, v in value.items():
            out += _paths(v, prefix + (k,))
    elif isinstance(value, list):
        for i, v in enumerate(value[:6]):
            out += _paths(v, prefix + (i,))
    return out


@st.composite
def mutated_model(draw, meta: dict, arrays: dict):
    """(bytes of an .npz) from ``meta`` and ``arrays`` with a few changes."""
    meta, arrays = copy.deepcopy(meta), {k: v.copy() for k, v in arrays.items()}
    for _ in range(draw(st.integers(1, 3))):
        how = draw(st.sampled_from(["value", "drop", "add", "shape", "dtype", "nan", "drop-array"]))
        if how in ("value", "drop", "add"):
            path = draw(st.sampled_from(_paths(meta)))
            parent = meta
            for k in path[:-1]:
                parent = parent[k]
            if how == "value":
                parent[path[-1]] = draw(JSON_VALUES)
            elif how == "drop" and isinstance(parent, dict):
                parent.pop(path[-1])
            elif isinstance(parent, dict):
                parent[draw(st.text(max_size=6))] = draw(JSON_VALUES)
            continue
        name = draw(st.sampled_from(sorted(arrays)))
        a = arrays[name]
        if how == "shape":
            shape = tuple(draw(st.lists(st.integers(0, 64), min_size=0, max_size=3)))     # <= 262,144 values
            arrays[name] = np.resize(a, shape).astype(a.dtype)
        elif how == "dtype":
            dtype = draw(st.sampled_from(["float16", "float64", "int8", "int64", "bool", "complex64", "<U3"]))
            with warnings.catch_warnings(), np.errstate(all="ignore"):
                warnings.simplefilter("ignore")
                try:
                    arrays[name] = a.astype(dtype)
                except ValueError:          # text made by an earlier change that is no number: kept
                    pass
        elif how == "nan" and a.size and a.dtype.kind in "fc":
            flat = a.reshape(-1).copy()
            with np.errstate(all="ignore"):             # 1e30 is inf in float16: fine too
                flat[draw(st.integers(0, a.size - 1))] = draw(st.sampled_from([np.nan, np.inf, -np.inf, 1e30]))
            arrays[name] = flat.reshape(a.shape)
        elif how == "drop-array":
            arrays.pop(name)
    with tempfile.TemporaryDirectory() as d:
        path = write_npz(Path(d) / "m.npz", meta, arrays, fresh_checksum=draw(st.booleans()),
                         compressed=draw(st.booleans()))
        data = path.read_bytes()
    if draw(st.booleans()):
        data = data[:draw(st.integers(0, len(data)))]
    return data


def load_and_run(kind: str, data: bytes, bound: int = PEAK_BYTES) -> None:
    """Load a model file of ``kind`` ('refine' or 'olf') from ``data`` (and run
    a loaded refinement on finite features): success or one DcdiError, the
    peak allocation below ``bound``."""
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "m.npz"
        path.write_bytes(data)

        def load():
            try:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    if kind == "olf":
                        OmniLensField.load(path)
                        return
                    r = DfdRefiner(path)
                    r(np.ones((r.meta["channels"], 3, 4), np.float32))
            except DcdiError as e:
                assert "\n" not in str(e)
        peak = peak_of(load)
    assert peak < bound, f"peak allocation {peak} bytes"


_SOURCES: dict = {}


def _sources() -> dict:
    if not _SOURCES:
        with tempfile.TemporaryDirectory() as d:
            _SOURCES["refine"] = read_trusted(REFINE)
            _SOURCES["olf"] = read_trusted(small_olf(Path(d) / "o.npz"))
    return _SOURCES


@pytest.mark.property
@given(data=st.data(), kind=st.sampled_from(["refine", "olf"]))
@settings(suppress_health_check=FIXTURES)
def test_a_mutated_model_file_loads_or_is_refused_with_a_project_error(data, kind):
    meta, arrays = _sources()[kind]
    load_and_run(kind, data.draw(mutated_model(meta, arrays)))


def test_the_model_fuzz_property_finds_a_planted_bug(tmp_path, monkeypatch):
    """With the refinement's metadata unchecked, a dilation the checks refuse
    passes the load and its padding exceeds the bound."""
    path = refine_file(tmp_path / "r.npz", lambda m, a: m.update(dilations=[1, 1, 400, 1]))
    load_and_run("refine", path.read_bytes(), bound=50 * 2 ** 20)       # checked: refused on load
    monkeypatch.setattr(dfd_refine, "check_refinement", lambda *a: None)
    with pytest.raises(AssertionError, match="peak allocation"):
        load_and_run("refine", path.read_bytes(), bound=50 * 2 ** 20)


# ------------------------------------------------------------- fuzz: lenses
LENS_FILES = sorted(p.name for p in (ROOT / "lenses").glob("*.toml"))


def _numbers(value, prefix=()):
    """Key paths of every number (and boolean) inside a prescription dict."""
    if isinstance(value, dict):
        return [p for k, v in value.items() for p in _numbers(v, prefix + (k,))]
    if isinstance(value, list):
        return [p for i, v in enumerate(value) for p in _numbers(v, prefix + (i,))]
    return [prefix] if isinstance(value, (int, float)) else []


TOML_VALUES = (st.floats(allow_nan=True, allow_infinity=True) | st.integers(-2 ** 63, 2 ** 63 - 1)
               | st.sampled_from([0, 0.0, -0.0, 1e-300, 1e300, -1.0, True, "x", "../../x"])
               | st.lists(st.floats(-1e6, 1e6), max_size=40))


@st.composite
def mutated_lens(draw) -> bytes:
    d = tomllib.loads((ROOT / "lenses" / draw(st.sampled_from(LENS_FILES))).read_text())
    for _ in range(draw(st.integers(1, 3))):
        how = draw(st.sampled_from(["number", "drop", "surfaces", "surface-key"]))
        if how == "number":
            path = draw(st.sampled_from(_numbers(d)))
            parent = d
            for k in path[:-1]:
                parent = parent[k]
            parent[path[-1]] = draw(TOML_VALUES)
        elif how == "drop":
            d.pop(draw(st.sampled_from(sorted(d))))
        elif how == "surfaces" and isinstance(d.get("surface"), list):
            d["surface"] = d["surface"] * draw(st.sampled_from([0, 2, 16, MAX_SURFACES // 2, 400]))
        elif how == "surface-key" and d.get("surface"):
            s = d["surface"][draw(st.integers(0, len(d["surface"]) - 1))]
            key = draw(st.sampled_from(sorted(s)))
            if draw(st.booleans()):
                s.pop(key)
            else:
                s[key] = draw(TOML_VALUES)
    try:
        text = dumps_prescription(d).encode()
    except TypeError:
        text = b""
    if draw(st.booleans()):
        text = text[:draw(st.integers(0, len(text)))]
    return text


def load_lens_bytes(data: bytes, bound: int = PEAK_BYTES) -> None:
    """Load a lens file from ``data``: success or one DcdiError, the peak allocation below ``bound``."""
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "l.toml"
        path.write_bytes(data)

        def load():
            try:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    Lens.from_toml(path)
            except DcdiError as e:
                assert "\n" not in str(e)
        peak = peak_of(load)
    assert peak < bound, f"peak allocation {peak} bytes"


@pytest.mark.property
@given(data=mutated_lens())
@settings(suppress_health_check=FIXTURES)
def test_a_mutated_lens_file_loads_or_is_refused_with_a_project_error(data):
    load_lens_bytes(data)


def test_the_lens_fuzz_property_finds_a_planted_bug(monkeypatch):
    """With a lens reader that lets a KeyError out (the old missing-key
    failure), the property's check fails."""
    d = tomllib.loads((ROOT / "lenses" / "mos-s1.toml").read_text())
    load_lens_bytes(dumps_prescription(d).encode())

    def careless(cls, d, path="<dict>", content_hash=""):
        return d["no-such-key"]
    monkeypatch.setattr(Lens, "from_dict", classmethod(careless))
    with pytest.raises(KeyError):
        load_lens_bytes(dumps_prescription(d).encode())

