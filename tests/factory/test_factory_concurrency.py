"""The factory under concurrency and kills: shard processes and a duplicate
of one of them on the same folder, killed (SIGKILL) at random points and
resumed, then merged: the dataset equals a single-process run byte for
byte, and no run ever removed another's data. The numpy recipe (no
Blender), tiny frames; one round in `python build.py test`, more rounds
(other kill points) in `test-slow`."""
import json
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from blender_addon.factory import batch

ROOT = Path(__file__).resolve().parents[2]
ARGS = ["--recipe", "leaves", "--lens", "mos-s1", "--seed", "3", "--resolution", "24", "32", "--psf-rays", "12",
        "--psf-wavelengths", "3", "--count", "6"]
SHARDS = 2


def _start(out: Path, shard: int, env) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "blender_addon.factory", *ARGS, "--shard", f"{shard}/{SHARDS}",
                             "--out", str(out)], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            env=env, cwd=ROOT)


def _files(folder: Path) -> dict:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*.exr"))}


def one_round(tmp: Path, seed: int, reference: Path) -> None:
    """Shards 0..SHARDS-1 and a duplicate of shard 0, all started at once,
    each SIGKILLed at a random moment (or left to finish); then every shard
    resumed to the end, merged and compared with ``reference``."""
    rng = random.Random(seed)
    env = dict(os.environ, DCDI_CACHE_DIR=str(tmp.parent / "psf-cache"))
    folders = [tmp / f"s{i}" for i in range(SHARDS)]
    procs = [(_start(folders[i], i, env), rng.uniform(0.2, 3.0)) for i in range(SHARDS)]
    procs.append((_start(folders[0], 0, env), rng.uniform(0.2, 3.0)))          # the duplicate
    t0 = time.perf_counter()
    for p, at in sorted(procs, key=lambda x: x[1]):
        time.sleep(max(0.0, at - (time.perf_counter() - t0)))
        if p.poll() is None:
            p.send_signal(signal.SIGKILL)
    for p, _ in procs:
        p.wait(timeout=120)
        err = p.stderr.read()
        p.stderr.close()
        # finished, killed, or refused because another run held the folder: nothing else
        assert p.returncode in (0, -signal.SIGKILL) or (p.returncode == 2 and "another factory run" in err), err
        print("round", seed, "exit", p.returncode)
    for i, folder in enumerate(folders):                 # resume each shard to the end, as a user would
        assert batch.run([*ARGS, "--shard", f"{i}/{SHARDS}", "--out", str(folder)]) == 0
    merged = tmp / "merged"
    assert batch.run(["merge", *map(str, folders), "--count", "6", "--out", str(merged)]) == 0
    want, got = _files(reference), _files(merged)
    assert sorted(got) == sorted(want) and len(want) == 6 * 5          # aif, depth and three lens images
    assert [k for k in want if want[k] != got[k]] == []
    assert json.loads((merged / "dataset.json").read_text()) == json.loads((reference / "dataset.json").read_text())
    ids = [json.loads(x)["id"] for x in (merged / "manifest.jsonl").read_text().splitlines()]
    assert ids == [json.loads(x)["id"] for x in (reference / "manifest.jsonl").read_text().splitlines()]
    assert not list(merged.rglob(".*.tmp*"))


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    out = tmp_path_factory.mktemp("one") / "one"
    os.environ.setdefault("DCDI_CACHE_DIR", str(tmp_path_factory.mktemp("psf-cache")))
    assert batch.run([*ARGS, "--out", str(out)]) == 0
    return out


def test_shards_and_a_duplicate_killed_at_random_then_resumed_equal_one_run(tmp_path, reference):
    one_round(tmp_path, 0, reference)


@pytest.mark.slow
@pytest.mark.parametrize("seed", range(1, 6))
def test_more_kill_points(tmp_path, reference, seed):
    one_round(tmp_path, seed, reference)


def test_the_comparison_finds_a_planted_bug(tmp_path, reference):
    """A merged folder with one sample's frame changed is not the reference."""
    import shutil
    bad = tmp_path / "bad"
    shutil.copytree(reference, bad)
    frame = next(bad.rglob("aif/*.exr"))
    data = bytearray(frame.read_bytes())
    data[-5] ^= 0xFF
    frame.write_bytes(bytes(data))
    want, got = _files(reference), _files(bad)
    assert [k for k in want if want[k] != got[k]] == [frame.relative_to(bad).as_posix()]
