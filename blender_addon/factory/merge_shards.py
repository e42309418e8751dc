"""One dataset from the shard folders of a job array (the step after it).

    python -m blender_addon.factory merge SHARD_DIR... --count N --out DIR [--copy]

Each shard folder is what ``factory --shard I/N`` wrote (a job array on a
cluster with node-local scratch writes one folder per task). Refused before
anything is written, naming what to change (``DatasetError``): a folder
without the factory's settings record or manifest; shards made with
different settings (every differing setting named by its option; only the
shard itself may differ); an index in two shards; an index outside 0 ..
N-1; a missing index (the first few listed, and which shard of the array
lacks them); a sample whose manifest line is there but a file is not.

Then the sample files are hard-linked into ``DIR`` (copied where a link
cannot be made, e.g. across file systems, or with ``--copy``), each under a
temporary name renamed into place; ``dataset.json`` is the shards' settings
with shard 0/1 (so ``DIR`` is the folder one unsharded run would have made,
and the factory can resume it with ``--shard 0/1`` to grow ``--count``);
``merge.json`` records the shards; ``manifest.jsonl``, sorted by index, is
written last, atomically: a merge killed before it leaves no manifest and
the same command starts it again.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
from pathlib import Path

if __package__ in (None, ""):
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from blender_addon.factory.settings import OPTION_OF  # noqa: E402
from dcdi_core.dataset import factory_folder as ff  # noqa: E402
from dcdi_core.dataset.factory_folder import MANIFEST, SETTINGS_FILE, read_manifest  # noqa: E402

SHOWN = 5                     # how many indices or files a refusal lists
# what may differ between the shards of one dataset (why undenoised frames are: their flag is compared)
NOT_COMPARED = ("shard", "render.no_denoise_reason")


def parse(argv):
    p = argparse.ArgumentParser(prog="factory merge", description=__doc__.split("\n\n")[0])
    p.add_argument("shards", nargs="+", metavar="SHARD_DIR", help="the shard folders (factory --out of each task)")
    p.add_argument("--count", type=int, required=True, metavar="N",
                   help="the job array's --count: indices 0 .. N-1 must each be in exactly one shard")
    p.add_argument("--out", required=True, help="the merged dataset folder (new, or one a killed merge left)")
    p.add_argument("--copy", action="store_true", help="copy the files (default: hard links where possible)")
    return p.parse_args(argv)


def main(argv=None) -> int:
    """Exit 0 when merged, 2 with one line ("factory: error: ...") for any
    refusal (nothing written then)."""
    from dcdi_core.errors import DcdiError
    a = parse(sys.argv[1:] if argv is None else argv)
    try:
        summary = merge([Path(s) for s in a.shards], Path(a.out), a.count, copy=a.copy)
    except DcdiError as e:
        print(f"factory: error: {' '.join(str(e).split())}", file=sys.stderr, flush=True)
        return 2
    print(f"factory: merged {summary['samples']} samples of {len(summary['shards'])} shards into {a.out} "
          f"({summary['linked']} files linked, {summary['copied']} copied)", flush=True)
    return 0


def merge(shards: list[Path], out: Path, count: int, *, copy: bool = False) -> dict:
    """Merge ``shards`` into ``out`` (see the module); returns a summary
    (shards, samples, linked, copied)."""
    settings, records = check_shards(shards, out, count)
    jobs = sample_files(records, settings["lenses"])
    linked = copied = 0
    for src, rel in jobs:
        if place(src, out / rel, copy=copy):
            linked += 1
        else:
            copied += 1
    write_dataset(out, settings, [rec for _, rec in records], shards, count)
    return {"shards": [str(s) for s in shards], "samples": len(records), "linked": linked, "copied": copied}


def check_shards(shards: list[Path], out: Path, count: int) -> tuple[dict, list]:
    """Everything refused before a file is written: (the settings, [(shard,
    record)] sorted by index)."""
    from dcdi_core.errors import DatasetError, InputRangeError, check_writable_folder
    if count < 1:
        raise InputRangeError("--count", count, "an integer >= 1 (the job array's --count)")
    out_r = out.resolve()
    if any(s.resolve() == out_r for s in shards):
        raise DatasetError(f"--out {out} is one of the shards: merge into a new folder")
    if (out / MANIFEST).exists():
        raise DatasetError(f"--out {out} already holds a dataset ({MANIFEST}): use a new folder")
    if out.exists() and not out.is_dir():
        raise DatasetError(f"--out {out} is a file, not a folder")
    check_writable_folder(out, "--out")
    found = [(s, read_settings(s)) for s in shards]
    check_same_settings(found)
    records = [(s, rec) for s in shards for rec in read_manifest(s / MANIFEST)[0]]
    check_indices(records, count, found[0][1]["recipe"], shard_counts(found))
    return found[0][1], sorted(records, key=lambda sr: sr[1]["index"])


def read_settings(shard: Path) -> dict:
    """A shard folder's settings record (refused when missing or unreadable)."""
    from dcdi_core.errors import DatasetError
    path = shard / SETTINGS_FILE
    if not shard.is_dir():
        raise DatasetError(f"shard {shard}: not a folder")
    if not path.exists() or not (shard / MANIFEST).exists():
        raise DatasetError(f"shard {shard}: no {SETTINGS_FILE} and {MANIFEST}: not a factory folder (or one made "
                           "before the factory recorded its settings: its settings cannot be checked)")
    return ff.read_settings(shard)


def setting_differences(a: dict, b: dict) -> list[str]:
    """'--option: A vs B' for every setting (the shard excepted) that differs,
    settings recorded by one side only included."""
    fa, fb = ff.flat_settings(a), ff.flat_settings(b)
    out = []
    for key in sorted(set(fa) | set(fb)):
        if key in NOT_COMPARED or fa.get(key) == fb.get(key):
            continue
        if key == "lens_fingerprints":
            ga, gb = fa.get(key) or {}, fb.get(key) or {}
            changed = sorted(x for x in set(ga) | set(gb) if ga.get(x) != gb.get(x))
            out.append(f"the optics of lens {', '.join(changed)} (the lens file changed between the shards)")
            continue
        name = OPTION_OF.get(key, key)
        out.append(f"{name}: {_show(fa.get(key, 'not recorded'))} vs {_show(fb.get(key, 'not recorded'))}")
    return out


def _show(v) -> str:
    return " ".join(map(str, v)) if isinstance(v, list) else str(v)


def check_same_settings(found: list[tuple[Path, dict]]) -> None:
    from dcdi_core.errors import DatasetError
    first, ref = found[0]
    bad = [f"shard {s} against {first}: " + "; ".join(d) for s, st in found[1:]
           for d in [setting_differences(ref, st)] if d]
    if bad:
        raise DatasetError("shards made with different settings, not merged: " + " | ".join(bad)
                           + ". Remake those shards with the others' settings")


def shard_counts(found: list[tuple[Path, dict]]) -> set:
    """The shard counts N the folders record (their --shard I/N)."""
    out = set()
    for _, st in found:
        try:
            out.add(int(str(st.get("shard", "0/1")).split("/")[1]))
        except (IndexError, ValueError):
            pass
    return out


def check_indices(records: list, count: int, recipe: str, counts: set) -> None:
    """Each index 0 .. count-1 in exactly one shard; the id its index's."""
    from dcdi_core.errors import DatasetError
    where, doubled, outside, bad_id = {}, [], [], []
    for shard, rec in records:
        i = rec.get("index")
        if not isinstance(i, int) or rec["id"] != _id_of(recipe, i):
            bad_id.append(f"{rec['id']} (index {i!r}) in {shard}")
            continue
        if not 0 <= i < count:
            outside.append(f"{i} in {shard}")
        elif i in where:
            doubled.append(f"{i} in {where[i]} and {shard}")
        else:
            where[i] = shard
    missing = [i for i in range(count) if i not in where]
    problems = []
    if bad_id:
        problems.append(f"records whose id is not {recipe}-<index>: {_first(bad_id)}")
    if doubled:
        problems.append(f"{len(doubled)} index(es) in two shards: {_first(doubled)} (a shard given twice, or "
                        "shards of different --shard counts?)")
    if outside:
        problems.append(f"{len(outside)} index(es) outside 0..{count - 1}: {_first(outside)} (is --count "
                        f"{count} the job array's?)")
    if missing:
        hint = ""
        if len(counts) == 1:
            n = counts.pop()
            lacking = sorted({i % n for i in missing})
            hint = f"; the shards {', '.join(f'{j}/{n}' for j in lacking[:SHOWN])} lack them (not given, or unfinished)"
        problems.append(f"{len(missing)} index(es) missing: {_first(missing)}{hint}")
    if problems:
        raise DatasetError("not merged: " + "; ".join(problems))


def _id_of(recipe: str, index: int) -> str | None:
    """The id of ``index``; None for an index no sample id can hold (negative)."""
    try:
        return ff.sample_id(recipe, index)
    except ValueError:
        return None


def _first(items) -> str:
    shown = ", ".join(map(str, items[:SHOWN]))
    return shown + (f", ... ({len(items) - SHOWN} more)" if len(items) > SHOWN else "")


def sample_files(records: list, lenses: list) -> list[tuple[Path, Path]]:
    """(source, relative destination) of every file of every sample,
    refused when one is missing."""
    from dcdi_core.errors import DatasetError
    jobs, missing = [], []
    for shard, rec in records:
        for rel in ff.sample_files(rec["id"], lenses):
            if not (shard / rel).is_file():
                missing.append(str(shard / rel))
            jobs.append((shard / rel, rel))
    if missing:
        raise DatasetError(f"not merged: {len(missing)} file(s) of finished samples missing: {_first(missing)}")
    return jobs


def place(src: Path, dest: Path, *, copy: bool = False) -> bool:
    """``src`` at ``dest`` under a temporary name renamed into place: a hard
    link (True) or, where one cannot be made or with ``copy``, a copy (False)."""
    from dcdi_core.atomic import atomic_path
    with atomic_path(dest) as tmp:
        if not copy:
            try:
                os.unlink(tmp)
                os.link(src, tmp)
                return True
            except OSError:
                pass
        shutil.copyfile(src, tmp)
        return False


def write_dataset(out: Path, settings: dict, records: list, shards: list, count: int) -> None:
    """The settings record (shard 0/1), merge.json, then the manifest last."""
    from dcdi_core.atomic import write_text
    layout = ff.FolderLayout(out)
    ff.write_settings(out, {**settings, "shard": "0/1"})
    write_text(layout.merge_record, json.dumps({"shards": [str(s) for s in shards], "count": count,
                                                "samples": len(records)}, indent=2) + "\n")
    ff.write_manifest(layout.manifest, records)


if __name__ == "__main__":
    sys.exit(main())
