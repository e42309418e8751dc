"""The factory's folder format (dcdi_core.dataset.factory_folder): ids,
paths, the manifest's torn records, the settings record, and a folder
written with the format's own helpers read back by the RGB-D reader
(no Blender needed)."""
import json

import numpy as np
import pytest

from dcdi_core.dataset import factory_folder as ff
from dcdi_core.dataset.rgbd import FactoryFolder, open_source
from dcdi_core.errors import DatasetError, ModelError, OutputError


def test_sample_ids_are_written_and_parsed_alike():
    assert ff.sample_id("room", 42) == "room-000042"
    assert ff.sample_id("street", 1234567) == "street-1234567"           # more than 6 digits when needed
    assert ff.parse_sample_id("room-000042") == ("room", 42)
    assert ff.parse_sample_id("street-1234567") == ("street", 1234567)
    for bad in ("room-42", "room-0000042", "Room-000001", "room000001", "-000001", "room-00000a", None):
        with pytest.raises(ValueError, match="sample id"):
            ff.parse_sample_id(bad)
    for recipe, index in (("Room", 0), ("room-x", 0), ("", 0), ("room", -1), ("room", 1.0)):
        with pytest.raises(ValueError):
            ff.sample_id(recipe, index)


def test_the_layout_names_every_file_of_a_sample(tmp_path):
    layout = ff.FolderLayout(tmp_path)
    sid = "room-000003"
    assert layout.manifest == tmp_path / "manifest.jsonl" and layout.settings == tmp_path / "dataset.json"
    assert layout.aif(sid) == tmp_path / "aif" / "room-000003.exr"
    assert layout.depth(sid) == tmp_path / "depth" / "room-000003.exr"
    assert layout.lens_image("mos-s1", "sharp", sid) == tmp_path / "mos-s1" / "sharp" / "room-000003.exr"
    with pytest.raises(ValueError, match="aberrated, baseline, sharp"):
        layout.lens_image("mos-s1", "blurred", sid)
    rels = [p.as_posix() for p in ff.sample_files(sid, ["a", "b"])]
    assert rels == ["aif/room-000003.exr", "depth/room-000003.exr",
                    "a/aberrated/room-000003.exr", "a/baseline/room-000003.exr", "a/sharp/room-000003.exr",
                    "b/aberrated/room-000003.exr", "b/baseline/room-000003.exr", "b/sharp/room-000003.exr"]
    assert layout.files(sid, ["a"])[0] == tmp_path / "aif" / "room-000003.exr"
    assert layout.render_handover(sid).name == ".room-000003.render.exr"
    assert ff.is_render_handover(".room-000003.render.exr") and ff.is_render_handover(".street-1234567.render.exr")
    assert not ff.is_render_handover(".room-3.render.exr") and not ff.is_render_handover("room-000003.render.exr")


def test_a_torn_last_record_does_not_count_and_is_repaired(tmp_path):
    manifest = tmp_path / "manifest.jsonl"
    assert ff.read_manifest(manifest) == ([], []) and ff.finished_ids(manifest) == set()
    a, b = {"id": "room-000000", "index": 0}, {"id": "room-000001", "index": 1}
    ff.append_record(manifest, a)
    manifest.write_text(manifest.read_text() + ff.record_line(b)[:12])      # killed while appending b
    recs, notes = ff.read_manifest(manifest)
    assert recs == [a] and "torn last record" in notes[0]
    assert manifest.read_text().endswith('{"id": "room')                   # read only: not repaired
    assert ff.finished_samples(tmp_path) == {"room-000000": a}
    assert ff.read_manifest(manifest, repair=True)[0] == [a]
    assert manifest.read_text() == json.dumps(a) + "\n"


def test_a_torn_record_with_the_next_glued_to_it_keeps_the_glued_one(tmp_path):
    manifest = tmp_path / "manifest.jsonl"
    a, b, c = ({"id": f"room-00000{i}", "index": i} for i in range(3))
    manifest.write_text(json.dumps(a) + "\n" + json.dumps(b)[:9] + json.dumps(c) + "\n")
    recs, notes = ff.read_manifest(manifest, repair=True)
    assert [r["id"] for r in recs] == ["room-000000", "room-000002"] and "kept room-000002" in notes[0]
    assert manifest.read_text() == json.dumps(a) + "\n" + json.dumps(c) + "\n"
    assert ff.read_manifest(manifest, repair=True) == (recs, [])     # repaired once, clean after


def test_records_are_written_id_first_and_a_record_without_an_id_is_not_one(tmp_path):
    line = ff.record_line({"index": 4, "id": "room-000004"})
    assert line.startswith('{"id": "room-000004", "index": 4}') and line.endswith("\n")
    manifest = tmp_path / "manifest.jsonl"
    manifest.write_text('{"index": 1}\n{"id": 7}\n[1, 2]\n' + line)
    assert [r["id"] for r in ff.read_manifest(manifest)[0]] == ["room-000004"]


def test_appending_into_a_missing_folder_names_the_file(tmp_path):
    with pytest.raises(OutputError, match="manifest.jsonl"):
        ff.append_record(tmp_path / "nowhere" / "manifest.jsonl", {"id": "room-000000"})


def _settings(**over):
    s = ff.settings_record(recipe="room", seed=3, shard="0/1", resolution=(4, 6), lenses=["mos-s1"],
                           lens_fingerprints={"mos-s1": "fp"}, baseline_depth_m=2.0,
                           render={"samples": 8, "denoise": True}, psf_settings={"pupil_samples": 12})
    s.update(over)
    return s


def test_the_settings_record_round_trips_and_flattens(tmp_path):
    s = _settings()
    assert list(s)[:2] == ["format", "recipe"] and s["format"] == ff.SETTINGS_FORMAT and s["resolution"] == [4, 6]
    assert ff.read_settings(tmp_path) is None
    ff.write_settings(tmp_path, s)
    assert ff.read_settings(tmp_path) == s
    assert (tmp_path / "dataset.json").read_text() == json.dumps(s, indent=2) + "\n"
    flat = ff.flat_settings(s)
    assert flat["render.samples"] == 8 and flat["psf_settings.pupil_samples"] == 12
    assert flat["lens_fingerprints"] == {"mos-s1": "fp"}                  # one value: compared per lens
    (tmp_path / "dataset.json").write_text("{edited")
    with pytest.raises(DatasetError, match=r"dataset.json: unreadable settings record .*; restore it"):
        ff.read_settings(tmp_path, advice="restore it")


def test_a_folder_from_before_the_settings_record_tells_them_by_its_manifest():
    rec = {"id": "room-000000", "recipe": "room", "dataset_seed": 0, "resolution": [480, 640],
           "render": {"engine": "CYCLES", "samples": 8, "seconds": 3.2}, "psf_settings": {"pupil_samples": 64},
           "lenses": {"mos-s1": {"baseline_depth_m": 2.0}}}
    assert ff.settings_from_manifest(rec) == {"recipe": "room", "seed": 0, "resolution": [480, 640],
                                              "lenses": ["mos-s1"], "render": {"samples": 8},
                                              "psf_settings": {"pupil_samples": 64}, "baseline_depth_m": 2.0}


def _image(h, w, k):
    rng = np.random.default_rng(k)
    return rng.uniform(0.0, 2.0, (h, w, 3)).astype(np.float32)          # linear HDR: above 1 survives


def test_a_folder_written_with_the_format_is_read_back_by_the_reader(tmp_path):
    """The writer's helpers (as the factory uses them) and the reader agree
    on every file: the pixels come back bit for bit; a sample without its
    manifest record is not finished."""
    layout = ff.FolderLayout(tmp_path / "ds")
    lenses = ["mos-s1", "6p"]
    ff.write_settings(layout.root, _settings(lenses=lenses))
    written = {}
    for i in range(3):
        sid = ff.sample_id("room", i)
        img = _image(4, 6, i)
        depth = np.linspace(0.5, 9.0, 24, dtype=np.float32).reshape(4, 6)
        depth[0, 0] = np.inf                                               # background
        ff.write_rgbd(layout, sid, img, depth)
        sims = {lens: {kind: _image(4, 6, 10 * i + j + 3 * n) for j, kind in enumerate(ff.LENS_KINDS)}
                for n, lens in enumerate(lenses)}
        for lens, kinds in sims.items():
            ff.write_lens_images(layout, lens, sid, **kinds)
        written[sid] = (img, depth, sims)
        if i < 2:                                                          # the third: killed before its record
            ff.append_record(layout.manifest, {"id": sid, "index": i, "recipe": "room"})
    assert all(p.is_file() for sid in written for p in layout.files(sid, lenses))
    assert not list(layout.root.rglob(".*"))                               # every file renamed into place

    src = open_source(layout.root)
    assert isinstance(src, FactoryFolder) and src.ids() == ["room-000000", "room-000001"]
    for sid in src.ids():
        img, depth, sims = written[sid]
        frame = src.load(sid)
        assert frame.id == sid and frame.scene == sid and frame.meta["manifest"]["index"] == int(sid[-1])
        np.testing.assert_array_equal(frame.image, img)
        np.testing.assert_array_equal(frame.depth, depth)
        for lens in lenses:
            got = src.pair(sid, lens)
            assert set(got) == set(ff.LENS_KINDS)
            for kind in ff.LENS_KINDS:
                np.testing.assert_array_equal(got[kind], sims[lens][kind])
    assert ff.read_settings(layout.root)["lenses"] == lenses
    assert ff.finished_ids(layout.manifest) == set(src.ids())


def test_a_folder_without_a_manifest_is_not_a_factory_folder(tmp_path):
    (tmp_path / "aif").mkdir()
    assert not ff.is_factory_folder(tmp_path)
    with pytest.raises(ModelError, match="manifest.jsonl: not found"):
        FactoryFolder(tmp_path)
