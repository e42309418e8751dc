"""DACN's data: the RGB-D readers on tiny files in each format, depth
encodings, the split by scene, the DA2T degradation and its pre-built pairs."""
import json

import numpy as np
import pytest

from dcdi_core.io.images import linear_to_srgb, write_depth, write_image
from dcdi_core.models.runtime.depth_encoding import encode_depth
from dcdi_core.dataset.rgbd import (FactoryFolder, Middlebury2014, NYUv2Labeled, RGBDFolder,
                                        middlebury_depth_m, open_source, read_pfm)
from dcdi_core.models.common.split import Split, split_by_scene, split_source
from dcdi_core.errors import ModelError


def _img(h, w, seed=0):
    return np.random.default_rng(seed).uniform(0.05, 0.95, (h, w, 3)).astype(np.float32)


def _write_png16(path, values):
    import OpenImageIO as oiio
    v = np.ascontiguousarray(values, dtype=np.uint16)
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), oiio.ImageSpec(v.shape[1], v.shape[0], 1, oiio.UINT16))
    assert out.write_image(v[..., None])
    out.close()


# ------------------------------------------------------------------ readers
def test_generic_folder_reads_exr_png_npy_and_mm_png(tmp_path):
    (tmp_path / "images").mkdir()
    (tmp_path / "depth").mkdir()
    a, b, c = _img(5, 6, 1), _img(5, 6, 2), _img(5, 6, 3)
    write_image(tmp_path / "images" / "a.exr", a)
    write_image(tmp_path / "images" / "b.png", b, bit_depth=16)
    write_image(tmp_path / "images" / "c.exr", c)
    da = np.full((5, 6), 2.5, np.float32)
    write_depth(tmp_path / "depth" / "a.exr", da)
    mm = np.arange(30, dtype=np.uint16).reshape(5, 6) * 100        # 0 mm: invalid
    _write_png16(tmp_path / "depth" / "b.png", mm)
    np.save(tmp_path / "depth" / "c.npy", np.full((5, 6), 7.0, np.float32))
    (tmp_path / "scenes.json").write_text(json.dumps({"a": "room1", "b": "room1"}))
    src = open_source(tmp_path)
    assert isinstance(src, RGBDFolder) and src.ids() == ["a", "b", "c"]
    assert [src.scene(i) for i in src.ids()] == ["room1", "room1", "c"]
    fa, fb, fc = (src.load(i) for i in src.ids())
    np.testing.assert_array_equal(fa.image, a)
    np.testing.assert_array_equal(fa.depth, da)
    np.testing.assert_allclose(fb.image, b, atol=2e-4)                  # 16-bit sRGB round trip
    assert np.isnan(fb.depth[0, 0])
    np.testing.assert_allclose(fb.depth.ravel()[1:], mm.ravel()[1:] / 1000.0, rtol=1e-6)
    assert (fc.depth == 7.0).all()


def test_factory_folder_lists_finished_samples_only(tmp_path):
    for sid in ("room-000000", "room-000001"):
        write_image(tmp_path / "aif" / f"{sid}.exr", _img(4, 6))
        write_depth(tmp_path / "depth" / f"{sid}.exr", np.full((4, 6), np.inf, np.float32))
        for k in ("aberrated", "baseline", "sharp"):
            write_image(tmp_path / "mos-s1" / k / f"{sid}.exr", _img(4, 6, 5))
    (tmp_path / "manifest.jsonl").write_text(json.dumps({"id": "room-000000", "recipe": "room"}) + "\n"
                                             + '{"id": "room-000001", "rec')            # torn: not finished
    src = open_source(tmp_path)
    assert isinstance(src, FactoryFolder) and src.ids() == ["room-000000"]
    f = src.load("room-000000")
    assert f.image.shape == (4, 6, 3) and np.isinf(f.depth).all() and f.meta["manifest"]["recipe"] == "room"
    assert set(src.pair("room-000000", "mos-s1")) == {"aberrated", "baseline", "sharp"}


def test_pair_records_torn_by_a_kill_do_not_count(tmp_path):
    from dcdi_core.models.dacn.data import finished_pairs
    a, b, c = ({"id": f"room-00000{i}~0", "frame": f"room-00000{i}", "scene": "room"} for i in range(3))
    # b torn while appended, c appended after it by the resumed build, then a torn last line
    (tmp_path / "pairs.jsonl").write_text(json.dumps(a) + "\n" + json.dumps(b)[:10] + json.dumps(c) + "\n"
                                          + '{"id": "room-000003~0", "sce')
    assert sorted(finished_pairs(tmp_path)) == ["room-000000~0", "room-000002~0"]
    assert finished_pairs(tmp_path / "none") == {}


def _write_nyu_mat(path, images, depths, scenes):
    """A MATLAB v7.3 file as NYUv2's labeled set is laid out (HDF5 with a
    512-byte MATLAB header; arrays transposed; scenes a cell array of
    uint16 char arrays)."""
    import h5py
    with h5py.File(path, "w", userblock_size=512) as f:
        f["images"] = np.stack([im.transpose(2, 1, 0) for im in images])       # (N, 3, W, H)
        f["depths"] = np.stack([d.T for d in depths])                          # (N, W, H)
        refs = f.create_group("#refs#")
        ds = []
        for k, s in enumerate(scenes):
            refs[f"s{k}"] = np.array([[ord(ch)] for ch in s], dtype=np.uint16)
            ds.append(refs[f"s{k}"].ref)
        f.create_dataset("scenes", data=np.array([ds], dtype=h5py.ref_dtype))
    with open(path, "r+b") as fh:
        fh.write(b"MATLAB 7.3 MAT-file, Platform: GLNXA64, Created on: Mon Jan 1 00:00:00 2024 HDF5 schema 1.00 .")


def test_nyuv2_labeled_mat(tmp_path):
    pytest.importorskip("h5py")
    rng = np.random.default_rng(0)
    images = [rng.integers(0, 256, (4, 7, 3), dtype=np.uint8) for _ in range(3)]
    depths = [rng.uniform(0.5, 9.0, (4, 7)).astype(np.float32) for _ in range(3)]
    depths[1][0, 0] = 0.0                                            # missing depth
    _write_nyu_mat(tmp_path / "nyu.mat", images, depths, ["kitchen_0004", "kitchen_0004", "office_0012"])
    src = open_source(tmp_path / "nyu.mat")
    assert isinstance(src, NYUv2Labeled) and src.ids() == ["0000", "0001", "0002"]
    assert [src.scene(i) for i in src.ids()] == ["kitchen_0004", "kitchen_0004", "office_0012"]
    f = src.load("0001")
    assert f.image.shape == (4, 7, 3) and f.depth.shape == (4, 7)
    np.testing.assert_allclose(linear_to_srgb(f.image.astype(np.float64)) * 255, images[1], atol=1e-3)
    assert np.isnan(f.depth[0, 0])
    np.testing.assert_array_equal(f.depth.ravel()[1:], depths[1].ravel()[1:])


def _write_pfm(path, a):
    h, w = a.shape
    with open(path, "wb") as f:
        f.write(f"Pf\n{w} {h}\n-1.0\n".encode())
        f.write(np.ascontiguousarray(a[::-1], dtype="<f4").tobytes())     # bottom row first


def test_middlebury_2014_disparity_to_metric_depth(tmp_path):
    calib = ("cam0=[3997.684 0 1176.728; 0 3997.684 1011.728; 0 0 1]\n"
             "cam1=[3997.684 0 1307.839; 0 3997.684 1011.728; 0 0 1]\n"
             "doffs=131.111\nbaseline=193.001\nwidth=5\nheight=3\nndisp=280\n")
    disp = np.array([[100.0, 150.0, np.inf, 200.0, 250.0]] * 3, np.float32)
    disp[2] *= 0.5
    for name in ("Adirondack-perfect", "Adirondack-imperfect", "Piano-perfect"):
        d = tmp_path / name
        d.mkdir()
        (d / "calib.txt").write_text(calib)
        write_image(d / "im0.png", _img(3, 5))
        _write_pfm(d / "disp0.pfm", disp)
    np.testing.assert_array_equal(np.nan_to_num(read_pfm(tmp_path / "Piano-perfect" / "disp0.pfm"), posinf=-1),
                                  np.nan_to_num(disp, posinf=-1))
    src = open_source(tmp_path)
    assert isinstance(src, Middlebury2014)
    assert [src.scene(i) for i in src.ids()] == ["Adirondack", "Adirondack", "Piano"]
    f = src.load("Piano-perfect")
    want = 193.001 * 3997.684 / (disp.astype(np.float64) + 131.111) / 1000.0
    assert np.isnan(f.depth[:, 2]).all()
    np.testing.assert_allclose(f.depth[:, [0, 1, 3, 4]], want[:, [0, 1, 3, 4]], rtol=1e-6)
    assert f.depth[0, 0] == pytest.approx(3.3385, abs=1e-4)           # 193 mm x 3998 px / 231.1 px
    assert np.isnan(middlebury_depth_m(np.array([-200.0]), f.meta["calib"])).all()
    with pytest.raises(ModelError, match="not an RGB-D source"):
        open_source(tmp_path / "Piano-perfect")


# ------------------------------------------------------------------ depth
def test_depth_encodings():
    d = np.array([[0.05, 1.0, 5.5], [10.0, 50.0, np.nan]], np.float32)
    mm = encode_depth(d, "minmax")
    np.testing.assert_allclose(mm, [[0, 0.9 / 9.9, 5.4 / 9.9], [1, 1, 1]], rtol=1e-6)   # clamped to [0.1, 10]
    assert (encode_depth(np.full((3, 3), 4.0), "minmax") == 0).all()                    # one depth: 0
    np.testing.assert_allclose(encode_depth(d, "minmax", stats=(0.1, 20.0)).max(), 9.9 / 19.9, rtol=1e-6)
    di = encode_depth(np.array([0.05, 0.7, 7.0, np.inf, np.nan]), "diopter")
    np.testing.assert_allclose(di, [7.0, 1.0, 0.1, 0.0, 0.0], rtol=1e-6)


# ------------------------------------------------------------------ split
def test_split_by_scene_never_puts_a_test_scene_in_training(tmp_path):
    ids = {f"{s}-{v}": s for s in (f"scene{k:02d}" for k in range(40)) for v in ("perfect", "imperfect", "x")}
    sp = split_by_scene(ids, val=0.1, test=0.2, seed=3)
    train, val, test = (set(sp.of(p)) for p in ("train", "val", "test"))
    assert len(train) + len(val) + len(test) == len(ids)
    assert {ids[i] for i in test} & {ids[i] for i in train | val} == set()
    assert {ids[i] for i in val} & {ids[i] for i in train} == set()
    assert len({ids[i] for i in test}) == 8 and len({ids[i] for i in val}) == 4
    # the reader's order does not matter; the seed does; the record reads back
    assert split_by_scene(dict(reversed(list(ids.items()))), val=0.1, test=0.2, seed=3).scenes == sp.scenes
    assert split_by_scene(ids, val=0.1, test=0.2, seed=4).scenes != sp.scenes
    sp.save(tmp_path / "split.json")
    back = Split.load(tmp_path / "split.json")
    assert back.scenes == sp.scenes and back.of("test") == sp.of("test")


# ------------------------------------------------------------------ DA2T
FAST = dict(pupil_samples=8, n_wavelengths=3, n_fields=6, n_depths=3)


def _frame(h=48, w=64, depth=None, fid="f0", scene="s0"):
    from dcdi_core.dataset.rgbd import RGBDFrame
    rng = np.random.default_rng(7)
    img = np.clip(np.kron(rng.uniform(0.1, 0.9, (h // 4, w // 4, 3)), np.ones((4, 4, 1))), 0, 1).astype(np.float32)
    if depth is None:
        depth = np.where(np.arange(w)[None, :] < w // 2, 1.0, 6.0) * np.ones((h, 1))
    return RGBDFrame(fid, scene, img, depth.astype(np.float32), "test")


def test_da2t_degradation_is_seeded_recorded_and_its_baseline_shares_the_frame():
    from dcdi_core.models.dacn.data import DA2TConfig, degrade
    cfg = DA2TConfig(lens="mos-s2", **FAST)
    a, b = degrade(_frame(), cfg, 0), degrade(_frame(), cfg, 0)
    for k in ("capture", "target", "baseline", "depth"):
        np.testing.assert_array_equal(getattr(a, k), getattr(b, k))          # same seed, same bytes
    assert a.record == b.record and a.id == "f0~0"
    rec = a.record["perturbation"]
    assert rec["fraction"] == 0.10 and rec["changes"]
    assert all(abs(c["to"] / c["from"] - 1) <= 0.10 + 1e-12 for c in rec["changes"])
    assert a.record["noise"]["seed"] != a.record["noise"]["baseline_seed"]
    c = degrade(_frame(), cfg, 1)                                              # another variant: another lens
    assert c.record["perturbation"]["seed"] != rec["seed"] and not np.array_equal(c.capture, a.capture)
    assert a.capture.shape == a.target.shape == a.baseline.shape == (48, 64, 3) and a.depth.shape == (48, 64)
    # without noise, a frame all at the baseline's depth gives the baseline exactly
    quiet = DA2TConfig(lens="mos-s2", noise=None, perturb_fraction=0.0, baseline_depth_m=2.0, **FAST)
    flat = degrade(_frame(depth=np.full((48, 64), 2.0)), quiet)
    np.testing.assert_allclose(flat.baseline, flat.capture, atol=1e-6)
    near = degrade(_frame(depth=np.full((48, 64), 0.8)), quiet)
    assert np.abs(near.baseline - near.capture).max() > 1e-3                # the baseline ignores depth


def test_da2t_saturates_as_a_sensor_does():
    from dcdi_core.models.dacn.data import DA2TConfig, degrade
    f = _frame()
    f.image[:, 20:30] *= 3.0                                                  # an HDR highlight
    quiet = dict(noise=None, perturb_fraction=0.0, **FAST)
    clipped = degrade(f, DA2TConfig(lens="mos-s2", **quiet))
    raw = degrade(f, DA2TConfig(lens="mos-s2", saturate=False, **quiet))
    assert raw.target.max() > 2 and raw.capture.max() > 1.2
    for k in ("capture", "target", "baseline"):
        a, b = getattr(clipped, k), getattr(raw, k)
        assert a.min() >= 0 and a.max() <= 1
        np.testing.assert_array_equal(a, np.clip(b, 0, 1))                    # blurred first, then clipped


def test_prebuilt_pairs_resume_and_crops_stay_aligned(tmp_path):
    from dcdi_core.models.dacn.data import (DA2TConfig, PairCrops, build_pairs, crop_position, load_pair,
                                            pair_path)
    from dcdi_core.dataset.rgbd import RGBDSource

    class Frames(RGBDSource):
        def __init__(self):
            self.f = {i: _frame(fid=i, scene=i[:2]) for i in ("aa1", "aa2", "bb1")}

        def ids(self):
            return sorted(self.f)

        def scene(self, id):
            return id[:2]

        def load(self, id):
            return self.f[id]

    cfg = DA2TConfig(lens="mos-s2", **FAST)
    src = Frames()
    split = split_source(src, val=0.0, test=0.5, seed=0)
    assert {src.scene(i) for i in split.of("test")}.isdisjoint({src.scene(i) for i in split.of("train")})
    build_pairs(src, tmp_path, cfg, ids=["aa1"])
    first = pair_path(tmp_path, "aa1~0").stat().st_mtime_ns
    logs = []
    done = build_pairs(src, tmp_path, cfg, log=logs.append)                # the rest only
    assert "2 pairs to build (1 done)" in logs[0] and set(done) == {"aa1~0", "aa2~0", "bb1~0"}
    assert pair_path(tmp_path, "aa1~0").stat().st_mtime_ns == first
    with pytest.raises(ModelError, match="other DA2T settings"):
        build_pairs(src, tmp_path, DA2TConfig(lens="mos-s1", **FAST))
    crops = PairCrops([pair_path(tmp_path, i) for i in done], "minmax", augment=False)
    p = load_pair(pair_path(tmp_path, "aa1~0"))
    rng = np.random.default_rng(0)
    x, y, d = crops.crop(p, 16, np.random.default_rng(5))
    r, c = crop_position(~np.isnan(p.depth), 16, np.random.default_rng(5))
    np.testing.assert_array_equal(x, p.capture[r:r + 16, c:c + 16])
    np.testing.assert_array_equal(y, p.target[r:r + 16, c:c + 16])
    np.testing.assert_array_equal(d, encode_depth(p.depth[r:r + 16, c:c + 16], "minmax"))
    assert not np.isnan(p.depth[r:r + 16, c:c + 16]).any()
    xb, yb, db = PairCrops(crops.paths, "diopter").sample(rng, 3, 16)
    assert xb.shape == yb.shape == (3, 3, 16, 16) and db.shape == (3, 1, 16, 16) and xb.dtype == np.float32


def test_a_lens_pool_reuses_a_few_perturbed_lenses():
    from dcdi_core.models.dacn.data import DA2TConfig, degrade
    cfg = DA2TConfig(lens="mos-s2", lens_pool=2, **FAST)
    sims = {}
    recs = [degrade(_frame(fid=f"f{k}"), cfg, 0, simulators=sims).record for k in range(5)]
    seeds = {r["perturbation"]["seed"] for r in recs}
    # two lenses, each library made once, and the nominal lens's (the deconvolution's)
    assert len(seeds) == 2 and len(sims) == 3 and sum(k[0] == "nominal" for k in sims) == 1
    again = degrade(_frame(fid="f3"), cfg, 0)                      # the same draw without the shared dict
    assert again.record == recs[3]
