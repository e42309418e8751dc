"""JSON read from files is bounded before it is parsed (io.jsontext): a few
kilobytes nested deep are a refusal naming the file, never a RecursionError."""
import json

import pytest

from dcdi_core.errors import DatasetError, DcdiError
from dcdi_core.io.jsontext import MAX_DEPTH, JsonTextError, loads, nesting

DEEP = "[" * 100_000 + "]" * 100_000


def test_nesting_counts_brackets_outside_strings():
    assert nesting('{"a": [1, {"b": "[[[[["}], "c": "\\"["}') == 3
    assert nesting("[]") == 1 and nesting('"[["') == 0


def test_loads_refuses_deep_json_naming_where_it_came_from():
    with pytest.raises(JsonTextError, match=r"x\.json: JSON nested more than 64 levels"):
        loads(DEEP, "x.json")
    assert loads("[" * MAX_DEPTH + "]" * MAX_DEPTH, "ok") is not None


def test_the_planted_bug_plain_json_recurses():
    """What the bound is for: plain json on the same text is not a refusal."""
    with pytest.raises(RecursionError):
        json.loads(DEEP)


@pytest.mark.parametrize("text", ["{", "\xff\xfe", b"\xff\xfe", "[1,]"])
def test_damaged_json_is_one_project_error(text):
    with pytest.raises(JsonTextError) as caught:
        loads(text, "f.json")
    assert isinstance(caught.value, (DcdiError, ValueError)) and "\n" not in str(caught.value)


def test_a_manifest_line_nested_deep_counts_as_torn(tmp_path):
    from dcdi_core.dataset.factory_folder import read_manifest
    (tmp_path / "manifest.jsonl").write_text('{"id": "room-000001"}\n' + DEEP + "\n")
    records, _ = read_manifest(tmp_path / "manifest.jsonl")
    assert [r["id"] for r in records] == ["room-000001"]


def test_deep_settings_split_and_configs_are_refused(tmp_path):
    from dcdi_core.dataset.factory_folder import read_settings
    from dcdi_core.models.common.split import Split
    from dcdi_core.models.dacn.config import DACNTrainConfig
    from dcdi_core.errors import ModelFileError
    (tmp_path / "dataset.json").write_text(DEEP)
    with pytest.raises(DatasetError, match="nested"):
        read_settings(tmp_path)
    (tmp_path / "split.json").write_text(DEEP)
    with pytest.raises(ModelFileError, match="nested"):
        Split.load(tmp_path / "split.json")
    with pytest.raises(JsonTextError):
        DACNTrainConfig.from_json(DEEP)


@pytest.mark.parametrize("record, said", [({"id": "p~0", "scene": "s"}, "field 'frame' is missing"),
                                          ({"id": "p~0", "frame": 3, "scene": "s"}, "not a non-empty string"),
                                          ({"id": "p~0", "frame": "../../x", "scene": "s"}, "not a name")])
def test_a_pair_record_without_what_training_reads_is_refused(tmp_path, record, said):
    from dcdi_core.models.dacn.data import finished_pairs
    (tmp_path / "pairs.jsonl").write_text(json.dumps(record) + "\n")
    with pytest.raises(DatasetError, match=said):
        finished_pairs(tmp_path)
