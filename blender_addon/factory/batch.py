"""The dataset factory: seeded scenes rendered all-in-focus with metric depth,
then passed through the depth-aware simulation of each requested lens.

    blender --background --python blender_addon/factory/batch.py -- --recipe room --count 10 \\
        --lens mos-s1 --out DIR --seed 0 [--shard I/N]
    python -m blender_addon.factory --recipe room --count 10 --lens mos-s1 --out DIR --seed 0

DIR is a factory folder, its format defined in
dcdi_core.dataset.factory_folder: dataset.json (the run's settings,
compared on every resume: a mismatch is refused), manifest.jsonl (one JSON
line per finished sample), aif/<id>.exr (all-in-focus, linear RGB),
depth/<id>.exr (planar metres), <lens>/aberrated|baseline|sharp/<id>.exr;
<id> is <recipe>-<index, 6 digits>. A sample counts only once its manifest
line is written; every file is written to a temporary name and renamed, so a
killed run restarted with the same arguments finishes the missing samples
and leaves no partial file (a torn manifest line and stale temporaries are
repaired and removed on resume); restarted with other settings it is
refused, naming them. ``--shard I/N`` takes the indices i with
i % N == I, so any job runner can split the work; ``--shard auto`` takes I
and N from a job array (``options.shard_from_environment``: Slurm's
SLURM_ARRAY_TASK_ID and SLURM_ARRAY_TASK_COUNT, or a Kubernetes indexed
Job's JOB_COMPLETION_INDEX with N from ``--shard auto/N`` or
DCDI_SHARD_COUNT). After the array, one folder per shard becomes one data
set with

    python -m blender_addon.factory merge SHARD_DIR... --count N --out DIR

(``merge_shards``: refuses shards of other settings, an index doubled,
missing or out of range).

Stops and faults. SIGINT (Ctrl-C) and SIGTERM (timeout, Slurm) stop the
run at any stage with one line ("factory: interrupted; the finished samples
are kept: ...") and exit 130 / 143; under ``blender --background`` the
factory takes SIGINT from Blender's own handler for the run
(``signals.stop_on_signals(take_over=True)``), and a stop while Blender
works (scene, render) waits for Blender to return (``signals.deferred``).
A sample's files are written as temporaries and renamed into place together
with its manifest line (``commit.commit_sample``): stopped, killed or out
of disk space, a sample is in the folder whole with its line, or not at
all (a resume removes what a SIGKILL left half-way). The sample folders are
made and probed before any render (``folder.check_sample_folders``). For
tests, ``DCDI_FACTORY_STOP_AFTER=N`` ends the run after N samples (exit 3).

This module is the run: the entry point (``run``; ``blender --python`` runs
it as a file), the folder made and locked, a stop or an error turned into
one line and an exit status. The rest, one module each: the Blender
(``blender``), the options and their checks (``options``), the settings a
folder records (``settings``), the folder made ready before the first
sample (``folder``), the Cycles render (``render``), a sample's stages
(``samples``), its files committed with its manifest line (``commit``).
"""
from __future__ import annotations

import os
import sys
import time
from pathlib import Path

if __package__ in (None, ""):          # run as a file by `blender --python`
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

# Checked before anything else so that an unsuitable Blender fails with a
# message, not with a traceback from deep inside the scene code.
from blender_addon.factory.blender import check_blender  # noqa: E402

if __name__ == "__main__" and sys.argv[1:2] != ["merge"]:      # the merge needs no Blender
    check_blender()

from blender_addon.factory.folder import check_sample_folders, prepare_folder  # noqa: E402
from blender_addon.factory.merge_shards import main as merge_main  # noqa: E402
from blender_addon.factory.meters import rss_mib  # noqa: E402
from blender_addon.factory.options import check_arguments, parse  # noqa: E402
from blender_addon.factory.samples import add_lenses, make_sample  # noqa: E402
from blender_addon.factory.settings import run_settings  # noqa: E402
from dcdi_core.dataset import factory_folder as ff  # noqa: E402
from dcdi_core.dataset.factory_folder import MANIFEST, finished_ids  # noqa: E402


def run(argv=None) -> int:
    """The factory: exit 0 when every sample of this shard is done, 2 with one
    line ("factory: error: ...") for any error a user can cause (options,
    lens files, the output folder, memory, a full disk), 130 / 143 with one
    line when stopped by SIGINT / SIGTERM at any stage (the finished samples
    kept, nothing half-written), 3 when stopped early by
    DCDI_FACTORY_STOP_AFTER (tests). A failed run leaves no folder it
    created without a finished sample."""
    import shutil

    from dcdi_core.errors import DcdiError
    argv = sys.argv[sys.argv.index("--") + 1:] if argv is None and "--" in sys.argv else argv
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["merge"]:
        return merge_main(argv[1:])
    a = parse(argv)
    out = Path(a.out)
    from dcdi_core.signals import stop_code, stop_on_signals
    created, lock = False, None
    try:
        # SIGINT and SIGTERM: stop, remove this run's temporaries, one line. take_over: under `blender
        # --background` SIGINT has Blender's own handler, which Python code never hears of (a Ctrl-C in the
        # simulation was lost) and which cancels a render only late, leaving no file; a batch job owns its
        # process, so the factory takes SIGINT for the whole run
        with stop_on_signals(take_over=True):
            check_arguments(a)
            check_output_folder(out)
            try:
                out.mkdir(parents=True)       # atomic: of two runs starting together, one creates the folder
                created = True
            except FileExistsError:
                pass
            lock = _lock(out)                 # before anything is written; refused while another run holds it
            return _run(a, out)
    except BaseException as e:
        # only the run that created the folder and holds its lock may remove it: never another run's data
        if created and lock is not None and not finished_ids(out / MANIFEST):
            shutil.rmtree(out, ignore_errors=True)       # nothing finished: leave no folder behind
        if isinstance(e, KeyboardInterrupt):
            code, word = stop_code(e)
            print(f"factory: {word}; the finished samples are kept: run the same command again to resume",
                  file=sys.stderr, flush=True)
            return code
        if not isinstance(e, (DcdiError, MemoryError)):
            raise                                        # a bug: keep its traceback
        msg = str(e) if isinstance(e, DcdiError) else ("out of memory: lower --psf-rays, --psf-wavelengths or "
                                                       "--resolution")
        print(f"factory: error: {' '.join(msg.split())}", file=sys.stderr, flush=True)
        return 2
    finally:
        if lock is not None:
            lock.close()


def check_output_folder(out: Path) -> None:
    from dcdi_core.errors import OutputError, check_writable_folder
    if out.exists() and not out.is_dir():
        raise OutputError(out, "--out must be a folder; this is a file")
    check_writable_folder(out, "--out")


def _run(a, out: Path) -> int:
    layout = ff.FolderLayout(out)
    records, notes, added = prepare_folder(out, run_settings(a), a.add_lens)
    for note in notes:
        print(f"factory: {note}", flush=True)
    check_sample_folders(layout, [lens.id for lens in a.lenses])      # before any render or simulation
    if added:
        add_lenses(out, records, [lens for lens in a.lenses if lens.id in added], a, run_settings(a))
    done = {r["id"] for r in records}
    todo = [i for i in range(a.count) if i % a.shard_count == a.shard_index
            and ff.sample_id(a.recipe, i) not in done]
    print(f"factory: {a.recipe}, {len(todo)} samples to do in shard {a.shard}, {len(done)} already in the manifest",
          flush=True)
    t_start = time.perf_counter()
    sims = {}                          # built on the first sample to do: no PSF work for a finished run
    for n, i in enumerate(todo):
        t0 = time.perf_counter()
        record = make_sample(a, layout, sims, i)
        el = time.perf_counter() - t_start
        rate = (n + 1) / el
        print(f"  {record['id']}: {time.perf_counter() - t0:.1f} s (render {record['render']['seconds']:.1f} s); "
              f"{rate * 3600:.0f} samples/h, ETA {(len(todo) - n - 1) / rate:.0f} s, RSS {rss_mib():.0f} MiB",
              flush=True)
        if os.environ.get("DCDI_FACTORY_STOP_AFTER") and n + 1 >= int(os.environ["DCDI_FACTORY_STOP_AFTER"]):
            print("factory: stopping early (DCDI_FACTORY_STOP_AFTER)", flush=True)
            return 3
    return 0


class _FolderLock:
    def __init__(self, fd):
        self.fd = fd

    def close(self):
        os.close(self.fd)


def _lock(out: Path):
    """An exclusive lock on the folder itself (flock on its descriptor: no
    lock file) for this run: another factory writing into it is refused.
    None where the platform has no fcntl (Windows)."""
    from dcdi_core.errors import DatasetError
    try:
        import fcntl
    except ImportError:
        return None
    fd = os.open(out, os.O_RDONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        os.close(fd)
        raise DatasetError(f"--out {out}: another factory run is writing into this folder; wait for it to end "
                           "or use another --out") from None
    return _FolderLock(fd)


if __name__ == "__main__":
    sys.exit(run())
