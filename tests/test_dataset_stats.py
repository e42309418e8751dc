"""`dcdi dataset stats` on a tiny factory folder written here: two
recipes of two 96 x 128 frames, a flat one and a white-noise one, with
depths and clipped pixels laid out by hand, so that every measure has a
known answer."""
import json
import math

import numpy as np
import pytest

from dcdi_core.cli import main
from dcdi_core.dataset import factory_folder as ff
from dcdi_core.errors import DatasetError, InputRangeError
from dcdi_core.app import dataset_stats as dr

H, W = 96, 128
CROP = 16            # 128 px crops do not fit a 96 x 128 frame: the function's option, the CLI keeps 128
CLIPPED_ROWS = 6     # rows of the second noise frame set above 1.0


def _band_depth() -> np.ndarray:
    """Rows in each report band, one row below 0.7 m, one with no depth."""
    d = np.empty((H, W), np.float32)
    d[0:15], d[15:30], d[30:60], d[60:75], d[75:84], d[84:94] = 0.8, 1.5, 3.0, 7.0, 20.0, np.inf
    d[94], d[95] = 0.5, np.nan
    return d


# {recipe: [(image, depth)]}; the flat frames use the band depths, the noise ones 1.5 m
def _frames():
    rng = np.random.default_rng(3)
    flat = np.full((H, W, 3), 0.4, np.float32)
    noise = [rng.random((H, W, 3), dtype=np.float32) for _ in range(2)]
    noise[1][:CLIPPED_ROWS] = 1.5
    return {"flat": [(flat, _band_depth()), (flat.copy(), _band_depth())],
            "noise": [(n, np.full((H, W), 1.5, np.float32)) for n in noise]}


def _write_folder(root, frames: dict) -> None:
    layout = ff.FolderLayout(root)
    for recipe, items in frames.items():
        for k, (image, depth) in enumerate(items):
            sid = ff.sample_id(recipe, k)
            ff.write_rgbd(layout, sid, image, depth)
            ff.append_record(layout.manifest, {"id": sid, "recipe": recipe, "resolution": [H, W]})


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    root = tmp_path_factory.mktemp("factory")
    _write_folder(root, _frames())
    return root


@pytest.fixture(scope="module")
def report(folder, tmp_path_factory):
    out = tmp_path_factory.mktemp("dataset-report")
    options = dr.DatasetReportOptions(crop_px=CROP, seed=5)
    return dr.run_report([folder], options, out, log=lambda t: None), out


def test_high_frequency_share_of_flat_and_white_noise(report):
    res = report[0]["recipes"]
    assert res["flat"]["hf_share"]["max"] < 1e-3 and res["flat"]["hf_share"]["pooled"] < 1e-3
    # white noise: all but the disc of radius 0.1 of the unit square of frequencies, 1 - pi / 100
    first = res["noise"]["frame_rows"][0]
    assert first["hf_share"] == pytest.approx(1 - math.pi / 100, abs=0.015)
    assert 0.9 < res["noise"]["hf_share"]["pooled"] < 0.99


def test_depth_band_shares_are_the_rows_written(report):
    r = report[0]["recipes"]["flat"]
    want = {"0.7-1 m": 15, "1-2 m": 15, "2-5 m": 30, "5-10 m": 15, "> 10 m": 19}
    assert r["depth_shares"] == pytest.approx({k: v / H for k, v in want.items()})
    assert r["depth_below_first_band"] == pytest.approx(1 / H)
    assert r["depth_invalid"] == pytest.approx(1 / H)
    assert r["depth_1_5_m"] == pytest.approx(45 / H)
    assert report[0]["recipes"]["noise"]["depth_shares"]["1-2 m"] == 1.0


def test_clipped_fraction_is_the_share_set_above_one(report):
    r = report[0]["recipes"]["noise"]
    assert [f["clipped_fraction"] for f in r["frame_rows"]] == [0.0, pytest.approx(CLIPPED_ROWS / H)]
    assert r["clipped"]["worst"] == pytest.approx(CLIPPED_ROWS / H)
    assert r["clipped"]["worst_frame"].endswith("noise-000001")
    assert r["clipped"]["pooled"] == pytest.approx(CLIPPED_ROWS / (2 * H))
    assert report[0]["recipes"]["flat"]["clipped"]["pooled"] == 0.0


def test_crops_above_40_db_flat_all_noise_none(report):
    res = report[0]["recipes"]
    for lens in ("mos-s1", "mos-s2"):
        flat, noise = res["flat"]["crops_above"][lens], res["noise"]["crops_above"][lens]
        assert flat["crops"] > 0 and flat["share_above"] == 1.0, lens
        assert noise["crops"] > 0 and noise["share_above"] == 0.0, lens
        assert flat["median_psnr_db"] == "inf" or flat["median_psnr_db"] > 60, lens
        assert 5 < noise["median_psnr_db"] < 30, lens


def test_writes_table_json_and_pictures(report):
    results, out = report
    assert json.loads((out / "results.json").read_text()) == json.loads(json.dumps(results))
    text = (out / "report.md").read_text()
    assert "| flat | 2 |" in text and "| noise | 2 |" in text and "crops > 40 dB, mos-s2 %" in text
    for recipe in ("flat", "noise"):
        assert f"]({recipe}.jpg)" in text
        assert 0 < (out / f"{recipe}.jpg").stat().st_size < dr.PICTURE_MAX_BYTES


def test_sensor_positions_are_seeded_and_within_the_sensor():
    a = [dr.sensor_position(480, 640, 0, f"f/room-{k:06d}") for k in range(50)]
    assert a == [dr.sensor_position(480, 640, 0, f"f/room-{k:06d}") for k in range(50)]
    assert a != [dr.sensor_position(480, 640, 1, f"f/room-{k:06d}") for k in range(50)]
    rows, cols = zip(*a)
    assert min(rows) >= 0 and max(rows) <= 1280 - 480 and min(cols) >= 0 and max(cols) <= 1920 - 640
    # spread over the sensor: both halves, both ways
    assert min(rows) < 200 < 600 < max(rows) and min(cols) < 300 < 900 < max(cols)


def test_crop_psnr_grid_and_skips():
    sharp = np.full((40, 50, 3), 0.5, np.float32)
    capture = sharp.copy()
    usable = np.ones((40, 50), bool)
    usable[:, :3] = False                           # a dark strip on the left: the grid starts after it
    assert dr.crop_grid(usable, 16) == (4, 3 + 15 // 2, 2, 2)     # 47 usable columns: 2 crops, 15 to spare
    capture[4:20, 10:26] += 0.01                     # 40 dB exactly in the first crop
    capture[:4] = capture[:, :10] = 0.0              # outside the grid: not measured
    psnr, skipped = dr.crop_psnr(capture, sharp, usable, 16)
    assert skipped == 0 and psnr.shape == (4,)
    assert psnr[0] == pytest.approx(40.0, abs=1e-3) and np.isinf(psnr[1:]).all()
    usable[30, 30] = False
    psnr, skipped = dr.crop_psnr(capture, sharp, usable, 16)
    assert skipped == 1 and psnr.shape == (3,)
    assert dr.crop_psnr(capture, sharp, np.zeros((40, 50), bool), 16)[0].size == 0


def test_near_reaches_a_square():
    m = np.zeros((9, 9), bool)
    m[4, 4] = True
    want = np.zeros((9, 9), bool)
    want[2:7, 2:7] = True
    assert (dr.near(m, 2) == want).all()


def test_evenly_spreads_and_keeps_short_lists():
    assert dr.evenly(list(range(10)), 4) == [0, 3, 6, 9]
    assert dr.evenly([1, 2], 5) == [1, 2] and dr.evenly([1, 2, 3], None) == [1, 2, 3]


def test_frame_larger_than_the_sensor_is_skipped_and_named(tmp_path):
    root = tmp_path / "tall"
    _write_folder(root, {"tall": [(np.full((1290, 8, 3), 0.3, np.float32), np.full((1290, 8), 2.0, np.float32))]})
    res = dr.run_report([root], dr.DatasetReportOptions(lenses=("mos-s1",), pictures=0), tmp_path / "out",
                        log=lambda t: None)["recipes"]["tall"]
    assert res["frames_too_large_for_sensor"] == ["tall/tall-000000"]
    assert res["crops_above"]["mos-s1"]["crops"] == 0 and res["crops_above"]["mos-s1"]["share_above"] is None
    assert "larger than the sensor" in (tmp_path / "out" / "report.md").read_text()


def test_options_are_checked():
    for bad in ({"lenses": ()}, {"frames": 0}, {"crop_px": 1}, {"seed": 1.5}, {"psnr_db": math.nan}):
        with pytest.raises(InputRangeError):
            dr.DatasetReportOptions(**bad)


@pytest.mark.parametrize("case", ["missing", "no manifest", "empty manifest", "twice"])
def test_cli_refuses_a_bad_folder_in_one_line_before_any_work(folder, tmp_path, capsys, case):
    bad = tmp_path / "bad"
    args = [str(bad)]
    if case != "missing":
        bad.mkdir()
    if case == "empty manifest":
        (bad / ff.MANIFEST).write_text("")
    if case == "twice":
        args = [str(folder), str(folder) + "/"]
    out = tmp_path / "out"
    code = main(["dataset", "stats", *args, "--out", str(out)])
    err = capsys.readouterr().err.strip()
    assert code == 2 and err.startswith("dcdi: error: ") and "\n" not in err, err
    assert ("bad" in err) if case != "twice" else ("twice" in err)
    assert not out.exists()


def test_cli_runs_with_its_128_px_crops(folder, tmp_path, capsys):
    out = tmp_path / "out"
    code = main(["dataset", "stats", str(folder), "--lens", "mos-s1", "--frames", "1", "--out", str(out)])
    captured = capsys.readouterr()
    assert code == 0 and "| flat | 1 |" in captured.out and "flat 1/1" in captured.err
    res = json.loads((out / "results.json").read_text())
    assert res["options"]["crop_px"] == 128 and res["options"]["lenses"] == ["mos-s1"]
    # a 64 x 96 frame holds no 128 px crop: no share, shown as such
    assert res["recipes"]["noise"]["crops_above"]["mos-s1"] == {
        "crops": 0, "crops_above": 0, "share_above": None, "median_psnr_db": None, "skipped_crops": 0}


def test_missing_image_of_a_finished_frame_is_refused(tmp_path):
    root = tmp_path / "f"
    _write_folder(root, {"room": [(np.zeros((8, 8, 3), np.float32), np.ones((8, 8), np.float32))]})
    ff.FolderLayout(root).aif("room-000000").unlink()
    with pytest.raises(DatasetError, match="room-000000"):
        dr.recipe_frames([root], None)
