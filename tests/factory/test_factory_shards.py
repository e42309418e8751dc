"""The factory on a scheduler: --shard auto from a Slurm array or a
Kubernetes indexed Job, and the merge of the shards' folders (refusing
other settings, doubled, missing and out-of-range indices); the cluster
scripts of docs/scaling-out.md, checked as far as this machine allows."""
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from blender_addon.factory import merge_shards
from blender_addon.factory.options import shard_from_environment
from dcdi_core.errors import DatasetError, InputRangeError

ROOT = Path(__file__).resolve().parents[2]
CLUSTER = ROOT / "blender_addon" / "factory" / "cluster"
LENSES = ["mos-s1", "mos-s2"]


# ------------------------------------------------------------------ --shard auto
@pytest.mark.parametrize("env, text, want", [
    ({"SLURM_ARRAY_TASK_ID": "3", "SLURM_ARRAY_TASK_MIN": "0", "SLURM_ARRAY_TASK_MAX": "7",
      "SLURM_ARRAY_TASK_COUNT": "8"}, "auto", (3, 8)),
    ({"SLURM_ARRAY_TASK_ID": "5", "SLURM_ARRAY_TASK_MIN": "1", "SLURM_ARRAY_TASK_MAX": "8",
      "SLURM_ARRAY_TASK_COUNT": "8"}, "auto/8", (4, 8)),                 # --array=1-8
    ({"SLURM_ARRAY_TASK_ID": "6", "SLURM_ARRAY_TASK_MIN": "0", "SLURM_ARRAY_TASK_MAX": "14",
      "SLURM_ARRAY_TASK_STEP": "2", "SLURM_ARRAY_TASK_COUNT": "8"}, "auto", (3, 8)),   # --array=0-14:2
    ({"JOB_COMPLETION_INDEX": "0", "DCDI_SHARD_COUNT": "4"}, "auto", (0, 4)),
    ({"JOB_COMPLETION_INDEX": "2"}, "AUTO/3", (2, 3)),
])
def test_shard_auto_takes_the_job_arrays_index_and_count(env, text, want):
    assert shard_from_environment(text, env) == want


@pytest.mark.parametrize("env, text, says", [
    ({}, "auto", "a job array's environment"),
    ({"JOB_COMPLETION_INDEX": "1"}, "auto", "--shard auto/N or DCDI_SHARD_COUNT"),
    ({"JOB_COMPLETION_INDEX": "4", "DCDI_SHARD_COUNT": "4"}, "auto", "0 <= I < N"),
    ({"SLURM_ARRAY_TASK_ID": "3", "SLURM_ARRAY_TASK_MIN": "1", "SLURM_ARRAY_TASK_MAX": "7",
      "SLURM_ARRAY_TASK_COUNT": "3"}, "auto", "evenly spaced array"),             # --array=1,3,7
    ({"SLURM_ARRAY_TASK_ID": "0", "SLURM_ARRAY_TASK_MIN": "0", "SLURM_ARRAY_TASK_MAX": "7",
      "SLURM_ARRAY_TASK_COUNT": "8"}, "auto/4", "the job array has 8 tasks"),
    ({"JOB_COMPLETION_INDEX": "x", "DCDI_SHARD_COUNT": "4"}, "auto", "JOB_COMPLETION_INDEX"),
    ({}, "autox", "I/N, auto or auto/N"),
])
def test_shard_auto_without_a_usable_array_is_refused_by_name(env, text, says):
    with pytest.raises(InputRangeError, match="--shard") as e:
        shard_from_environment(text, env)
    assert says in str(e.value)


def test_the_factory_records_the_resolved_shard(monkeypatch):
    pytest.importorskip("bpy")
    from blender_addon.factory.options import check_arguments, parse
    monkeypatch.setenv("JOB_COMPLETION_INDEX", "1")
    monkeypatch.setenv("DCDI_SHARD_COUNT", "3")
    a = check_arguments(parse(["--recipe", "room", "--count", "4", "--out", "x", "--shard", "auto",
                               "--resolution", "24", "32"]))
    assert (a.shard, a.shard_index, a.shard_count) == ("1/3", 1, 3)


# ------------------------------------------------------------------ the merge
def _settings(shard="0/1", **kw):
    s = {"format": 1, "recipe": "room", "seed": 0, "shard": shard, "resolution": [24, 32], "lenses": LENSES,
         "lens_fingerprints": {x: f"fp-{x}" for x in LENSES}, "baseline_depth_m": 2.0,
         "render": {"samples": 8, "denoise": True, "denoising_quality": "HIGH"},
         "psf_settings": {"pupil_samples": 64, "n_wavelengths": 31}}
    s.update(kw)
    return s


def _files(sid):
    return [f"aif/{sid}.exr", f"depth/{sid}.exr"] + [f"{x}/{k}/{sid}.exr" for x in LENSES
                                                     for k in ("aberrated", "baseline", "sharp")]


def _shard(root: Path, i: int, n: int, count: int, *, indices=None, **settings) -> Path:
    """A shard folder as `factory --shard i/n` leaves it (files hold their own names)."""
    d = root / f"shard-{i}"
    d.mkdir(parents=True)
    (d / "dataset.json").write_text(json.dumps(_settings(f"{i}/{n}", **settings)))
    lines = []
    for k in (indices if indices is not None else range(i, count, n)):
        sid = f"room-{k:06d}"
        for rel in _files(sid):
            (d / rel).parent.mkdir(parents=True, exist_ok=True)
            (d / rel).write_text(f"{rel} of shard {i}")
        lines.append(json.dumps({"id": sid, "index": k, "seed": k}) + "\n")
    (d / "manifest.jsonl").write_text("".join(lines[::-1]))        # in any order
    return d


def test_a_complete_set_of_shards_merges_into_one_dataset(tmp_path):
    shards = [_shard(tmp_path, i, 3, 7) for i in range(3)]
    out = tmp_path / "merged"
    assert merge_shards.main([*map(str, shards), "--count", "7", "--out", str(out)]) == 0
    recs = [json.loads(x) for x in (out / "manifest.jsonl").read_text().splitlines()]
    assert [r["index"] for r in recs] == list(range(7))
    for r in recs:
        for rel in _files(r["id"]):
            assert (out / rel).read_text() == f"{rel} of shard {r['index'] % 3}"
            assert os.path.samefile(out / rel, shards[r["index"] % 3] / rel)        # hard-linked
    settings = json.loads((out / "dataset.json").read_text())
    assert settings == _settings("0/1")                 # what one unsharded run records
    assert json.loads((out / "merge.json").read_text())["samples"] == 7
    assert not list(out.rglob(".*"))                    # no temporary left
    copied = merge_shards.merge(shards, tmp_path / "copied", 7, copy=True)
    assert copied["copied"] == 7 * 8 and not os.path.samefile(tmp_path / "copied" / "aif" / "room-000000.exr",
                                                              shards[0] / "aif" / "room-000000.exr")


def test_the_factory_command_runs_the_merge(tmp_path):
    shards = [_shard(tmp_path, i, 2, 3) for i in range(2)]
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    p = subprocess.run([sys.executable, "-m", "blender_addon.factory", "merge", *map(str, shards),
                        "--count", "3", "--out", str(tmp_path / "m")], cwd=ROOT, env=env, capture_output=True,
                       text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    assert "merged 3 samples of 2 shards" in p.stdout


@pytest.mark.parametrize("case, says", [
    ("settings", r"shards made with different settings.*--psf-rays: 64 vs 32; --resolution: 24 32 vs 48 64"),
    ("lens", r"the optics of lens mos-s2"),
    ("doubled", r"1 index\(es\) in two shards: 2 in .*shard-0 and .*shard-1"),
    ("missing", r"3 index\(es\) missing: 1, 3, 5; the shards 1/2 lack them"),
    ("outside", r"1 index\(es\) outside 0..5: 9 in .*shard-1 \(is --count 6"),
    ("file", r"1 file\(s\) of finished samples missing: .*mos-s2/sharp/room-000004.exr"),
    ("twice", r"in two shards"),
])
def test_a_bad_set_of_shards_is_refused_by_name_and_nothing_written(tmp_path, case, says):
    count = 6
    a = _shard(tmp_path, 0, 2, count)
    if case == "settings":
        b = _shard(tmp_path, 1, 2, count, resolution=[48, 64], psf_settings={"pupil_samples": 32,
                                                                             "n_wavelengths": 31})
    elif case == "lens":
        b = _shard(tmp_path, 1, 2, count, lens_fingerprints={"mos-s1": "fp-mos-s1", "mos-s2": "changed"})
    elif case == "doubled":
        b = _shard(tmp_path, 1, 2, count, indices=[1, 2, 3, 5])
    elif case == "missing":
        b = None
    elif case == "outside":
        b = _shard(tmp_path, 1, 2, count, indices=[1, 3, 5, 9])
    elif case == "file":
        b = _shard(tmp_path, 1, 2, count)
        (a / "mos-s2" / "sharp" / "room-000004.exr").unlink()
    else:
        b = a
    out = tmp_path / "merged"
    with pytest.raises(DatasetError, match=says):
        merge_shards.merge([a] if b is None else [a, b], out, count)
    assert not out.exists()


def test_the_merge_refuses_a_finished_out_or_a_folder_without_settings(tmp_path):
    a = _shard(tmp_path, 0, 1, 2)
    with pytest.raises(DatasetError, match="is one of the shards"):
        merge_shards.merge([a], a, 2)
    (tmp_path / "done").mkdir()
    (tmp_path / "done" / "manifest.jsonl").write_text("")
    with pytest.raises(DatasetError, match="already holds a dataset"):
        merge_shards.merge([a], tmp_path / "done", 2)
    (tmp_path / "bare").mkdir()
    with pytest.raises(DatasetError, match="no dataset.json and manifest.jsonl"):
        merge_shards.merge([a, tmp_path / "bare"], tmp_path / "m", 2)
    with pytest.raises(InputRangeError, match="--count"):
        merge_shards.merge([a], tmp_path / "m", 0)


def test_a_merge_killed_before_its_manifest_is_done_again(tmp_path, monkeypatch):
    shards = [_shard(tmp_path, i, 2, 4) for i in range(2)]
    out = tmp_path / "m"
    real = merge_shards.write_dataset

    def killed(*a, **k):
        raise KeyboardInterrupt
    monkeypatch.setattr(merge_shards, "write_dataset", killed)
    with pytest.raises(KeyboardInterrupt):
        merge_shards.merge(shards, out, 4)
    assert not (out / "manifest.jsonl").exists()
    monkeypatch.setattr(merge_shards, "write_dataset", real)
    assert merge_shards.merge(shards, out, 4)["samples"] == 4
    assert len((out / "manifest.jsonl").read_text().splitlines()) == 4


def test_shards_of_a_real_factory_run_merge_into_the_unsharded_dataset(tmp_path, monkeypatch):
    """Two factory shards (one by --shard auto from an indexed Job's
    environment), merged: the same files, byte for byte, and the same
    samples as one unsharded run."""
    pytest.importorskip("bpy")
    from blender_addon.factory import batch as factory
    monkeypatch.setenv("DCDI_CACHE_DIR", str(tmp_path / "psf-cache"))
    small = ["--recipe", "tabletop", "--count", "3", "--lens", "mos-s1", "--seed", "5", "--resolution", "24", "32",
             "--cycles-samples", "2", "--psf-rays", "12", "--psf-wavelengths", "3"]
    assert factory.run([*small, "--out", str(tmp_path / "one")]) == 0
    assert factory.run([*small, "--out", str(tmp_path / "s0"), "--shard", "0/2"]) == 0
    monkeypatch.setenv("JOB_COMPLETION_INDEX", "1")
    assert factory.run([*small, "--out", str(tmp_path / "s1"), "--shard", "auto/2"]) == 0
    assert json.loads((tmp_path / "s1" / "dataset.json").read_text())["shard"] == "1/2"
    assert factory.run(["merge", str(tmp_path / "s1"), str(tmp_path / "s0"), "--count", "3",
                        "--out", str(tmp_path / "merged")]) == 0
    one, merged = tmp_path / "one", tmp_path / "merged"
    files = sorted(p.relative_to(one) for p in one.rglob("*.exr"))
    assert files == sorted(p.relative_to(merged) for p in merged.rglob("*.exr")) and len(files) == 15
    assert all((one / f).read_bytes() == (merged / f).read_bytes() for f in files)
    assert json.loads((merged / "dataset.json").read_text()) == json.loads((one / "dataset.json").read_text())
    ids = [json.loads(x)["id"] for x in (merged / "manifest.jsonl").read_text().splitlines()]
    assert ids == [f"tabletop-{i:06d}" for i in range(3)]
    # the merged folder is a factory folder: the unsharded command resumes it (nothing left to do)
    assert factory.run([*small, "--out", str(merged)]) == 0


# ------------------------------------------------------------------ the cluster scripts
def test_the_slurm_array_script_parses_and_runs_as_two_tasks_then_merges(tmp_path):
    """bash -n, then the script itself as tasks 0 and 1 of a 2-task array
    (the variables Slurm sets, a tiny data set), then the merge."""
    script = CLUSTER / "factory-array.sbatch"
    assert subprocess.run(["bash", "-n", str(script)]).returncode == 0
    text = script.read_text()
    assert re.search(r"^#SBATCH --array=0-7$", text, re.M) and "--shard auto" in text
    pytest.importorskip("bpy")
    env = {**os.environ, "PYTHONPATH": str(ROOT), "DCDI_REPO": str(ROOT), "DCDI_PYTHON": sys.executable,
           "DCDI_SHARDS": str(tmp_path / "shards"), "DCDI_COUNT": "3", "DCDI_RECIPE": "tabletop",
           "DCDI_CACHE_DIR": str(tmp_path / "cache"),
           "DCDI_FACTORY_ARGS": "--resolution 24 32 --cycles-samples 2 --psf-rays 12 --psf-wavelengths 3",
           "SLURM_ARRAY_TASK_MIN": "0", "SLURM_ARRAY_TASK_MAX": "1", "SLURM_ARRAY_TASK_COUNT": "2",
           "SLURM_CPUS_PER_TASK": "1"}
    for task in ("0", "1"):
        p = subprocess.run(["bash", str(script)], env={**env, "SLURM_ARRAY_TASK_ID": task}, capture_output=True,
                           text=True, timeout=300)
        assert p.returncode == 0, p.stdout + p.stderr
        assert f"in shard {task}/2" in p.stdout
    shards = sorted((tmp_path / "shards").glob("shard-*"))
    assert merge_shards.main([*map(str, shards), "--count", "3", "--out", str(tmp_path / "merged")]) == 0
    assert len((tmp_path / "merged" / "manifest.jsonl").read_text().splitlines()) == 3


def _yaml_value(text: str, key: str) -> str:
    values = re.findall(rf"^\s*{key}:\s*(\S.*)$", text, re.M)
    assert len(values) == 1, (key, values)
    return values[0].strip().strip('"')


def test_the_kubernetes_indexed_job_is_consistent_and_its_command_parses():
    """Without PyYAML (not a dependency): the layout (spaces, two-space
    indents), the Job's fields, DCDI_SHARD_COUNT = completions, and its
    shell command through bash -n."""
    text = (CLUSTER / "factory-indexed-job.yaml").read_text()
    body = [ln for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    assert "\t" not in text and all((len(ln) - len(ln.lstrip())) % 2 == 0 for ln in body)
    assert _yaml_value(text, "apiVersion") == "batch/v1" and _yaml_value(text, "kind") == "Job"
    assert _yaml_value(text, "completionMode") == "Indexed" and _yaml_value(text, "restartPolicy") == "Never"
    n = _yaml_value(text, "completions")
    assert n == _yaml_value(text, "parallelism")
    assert re.search(rf'- name: DCDI_SHARD_COUNT\n\s+value: "{n}"\n', text)
    block = re.search(r"args:\n(\s+)- \|\n((?:\1  .*\n)+)", text)
    script = "\n".join(ln[len(block.group(1)) + 2:] for ln in block.group(2).splitlines())
    assert "--shard auto" in script and "$JOB_COMPLETION_INDEX" in script
    assert subprocess.run(["bash", "-n"], input=script, text=True).returncode == 0


def test_the_kubernetes_indexed_job_parses_as_yaml():
    yaml = pytest.importorskip("yaml", reason="PyYAML is not a dependency; the test above checks the layout")
    job = yaml.safe_load((CLUSTER / "factory-indexed-job.yaml").read_text())
    spec = job["spec"]
    c = spec["template"]["spec"]["containers"][0]
    env = {e["name"]: e["value"] for e in c["env"]}
    assert spec["completionMode"] == "Indexed" and int(env["DCDI_SHARD_COUNT"]) == spec["completions"]
    assert "--shard auto" in c["args"][0]
