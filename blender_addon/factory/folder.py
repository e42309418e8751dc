"""The output folder made ready before the first sample: the run's settings
recorded, or compared with the folder's (``prepare_folder``); a torn
manifest line repaired; a killed run's temporaries and the files of
samples without a manifest line removed; the sample folders made and
probed for writing (``check_sample_folders``). Called with the folder's
lock held (``batch``)."""
from __future__ import annotations

import os
from pathlib import Path

from dcdi_core.dataset import factory_folder as ff
from dcdi_core.dataset.factory_folder import MANIFEST, SETTINGS_FILE, read_manifest, settings_from_manifest

from .settings import settings_differences


def prepare_folder(out: Path, settings: dict, add_lens: bool = False) -> tuple[list[dict], list[str], list[str]]:
    """Record the run's settings before the first sample, or compare them with
    the folder's (refusing a mismatch by name); repair a torn manifest
    record; remove stale temporaries and the files of samples without a
    manifest line. Returns (finished records, notes, the
    lenses to add to the finished samples: only with ``add_lens``, when the
    run's lenses are the folder's followed by new ones and nothing else
    differs; the settings record is then rewritten once they are added)."""
    from dcdi_core.errors import DatasetError
    path = out / SETTINGS_FILE
    records, notes = read_manifest(out / MANIFEST)
    have = ff.read_settings(out, advice="it is written atomically, so it was edited: restore it or use another "
                                        "--out")
    if have is None and records:
        have = settings_from_manifest(records[0])
    added = []
    if have is not None:
        diffs = settings_differences(have, settings)
        old, new = list(have.get("lenses", [])), list(settings["lenses"])
        only_more = (len(new) > len(old) and new[:len(old)] == old
                     and settings_differences({k: v for k, v in have.items() if k != "lenses"},
                                              {k: v for k, v in settings.items() if k != "lenses"}) == [])
        if diffs and add_lens and only_more:
            added = new[len(old):]
        elif diffs:
            hint = (" (to add lenses to its samples: --add-lens, the folder's lenses first)" if only_more else
                    " (--add-lens adds lenses listed after the folder's own, when nothing else differs)"
                    if add_lens else "")
            raise DatasetError(f"--out {out} holds samples made with other settings: " + "; ".join(diffs)
                               + f". Rerun with the folder's settings to resume it{hint}, or use another --out")
    if not path.exists() and not added:
        ff.write_settings(out, settings)
    records, notes = read_manifest(out / MANIFEST, repair=True)
    gone = remove_stale_files(out)
    if gone:
        notes.append(f"removed {len(gone)} stale temporary file(s) of a killed run")
    unfinished = remove_unfinished_files(out, {r["id"] for r in records})
    if unfinished:
        notes.append(f"removed {len(unfinished)} file(s) of {len({p.stem for p in unfinished})} sample(s) without "
                     "a manifest line (a killed run's): they are done again")
    return records, notes, added


def remove_stale_files(out: Path) -> list[Path]:
    """This run's own leftovers of a killed run: the hidden temporaries of
    atomic writes (.<name>.<random>.tmp<ext>, dcdi_core.atomic) and Blender's
    hand-over renders (.<id>.render.exr). Only called with the folder's lock
    held, so no live run's temporaries are touched."""
    from dcdi_core.atomic import remove_stale_temporaries
    return remove_stale_temporaries(out) + _removed(p for p in out.glob(".*" + ff.RENDER_HANDOVER_SUFFIX)
                                                    if ff.is_render_handover(p.name))



def remove_unfinished_files(out: Path, finished: set[str]) -> list[Path]:
    """Remove the sample files (aif/, depth/, <lens>/<kind>/<id>.exr) whose
    sample has no manifest line: a run killed between renaming a sample's
    files and appending its line left them. Only names of the sample-id
    form are touched; called with the folder's lock held. Returns them."""
    folders = [out / ff.AIF_DIR, out / ff.DEPTH_DIR] + [d for d in out.glob("*/*")
                                                        if d.name in ff.LENS_KINDS and d.is_dir()]
    return _removed([p for folder in folders for p in folder.glob("*" + ff.IMAGE_EXT)
                     if p.stem not in finished and _is_sample_id(p.stem)])


def _removed(paths) -> list[Path]:
    """Remove each of ``paths`` that can be removed; returns those removed."""
    gone = []
    for p in paths:
        try:
            p.unlink()
            gone.append(p)
        except OSError:
            pass
    return gone


def _is_sample_id(name: str) -> bool:
    try:
        ff.parse_sample_id(name)
        return True
    except ValueError:
        return False


def check_sample_folders(layout, lenses: list[str]) -> None:
    """Make the folders a sample's files go to and write (then remove) a
    4 KiB probe file in each, before any render: an --out whose subfolders
    cannot be written (read-only, a file in a folder's place, a read-only
    file system, a disk already full) is refused now (OutputError naming
    the folder), not after the first sample's render."""
    import tempfile

    from dcdi_core.errors import output_error
    for folder in sorted({p.parent for p in layout.files(ff.sample_id("probe", 0), lenses)}):
        try:
            folder.mkdir(parents=True, exist_ok=True)
            fd, name = tempfile.mkstemp(prefix=".probe.", suffix=".tmp", dir=folder)   # a temporary's form
            try:
                os.write(fd, bytes(4096))
                os.fsync(fd)
            finally:
                os.close(fd)
                os.unlink(name)
        except OSError as e:
            raise output_error(folder, e, "--out: a sample's files cannot be written here") from None
