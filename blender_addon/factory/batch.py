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
and N from a job array (``shard_from_environment``: Slurm's
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
with its manifest line (``commit_sample``): stopped, killed or out of disk
space, a sample is in the folder whole with its line, or not at all (a
resume removes what a SIGKILL left half-way). The sample folders are made
and probed before any render (``check_sample_folders``). For tests,
``DCDI_FACTORY_STOP_AFTER=N`` ends the run after N samples (exit 3).
"""
from __future__ import annotations

import argparse
import math
import os
import signal
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

# Checked before anything else so that an unsuitable Blender fails with a
# message, not with a traceback from deep inside the scene code.
MIN_BLENDER = (5, 0, 0)


class BlenderRefused(SystemExit):
    """An unsuitable Blender or Python: exit status 2, like every refusal of
    the factory; the message is printed ("factory: error: ...") when raised."""

    def __init__(self, message: str):
        super().__init__(2)
        self.message = message

    def __str__(self):
        return self.message


def _refuse(message: str):
    print(f"factory: error: {message}", file=sys.stderr, flush=True)
    raise BlenderRefused(message)


def check_blender() -> None:
    """Refuse a Blender older than MIN_BLENDER (its scene API differs: materials
    without node trees, no image_settings.media_type, no OIDN quality) or one
    whose Python lacks numpy, in one line (BlenderRefused, exit status 2)."""
    try:
        import bpy
    except ImportError:
        _refuse("no bpy module: run it with Blender (blender --background --python "
                "blender_addon/factory/batch.py -- ...) or install the pip bpy module (see requirements.txt)")
    v = tuple(bpy.app.version)
    if v < MIN_BLENDER:
        _refuse(f"Blender {bpy.app.version_string} is too old: the factory needs Blender "
                f">= {'.'.join(map(str, MIN_BLENDER))} (Blender 5 from blender.org, or the pip bpy module "
                "of requirements.txt)")
    try:
        import numpy  # noqa: F401
    except ImportError:
        _refuse(f"this Blender's Python ({sys.executable}, {sys.version.split()[0]}) has no numpy; Blender from "
                "blender.org bundles it, a distribution's blender uses the system python3 (install its numpy "
                "package, e.g. python3-numpy)")


if __name__ == "__main__" and sys.argv[1:2] != ["merge"]:      # the merge needs no Blender
    check_blender()

import numpy as np  # noqa: E402

if __package__ in (None, ""):          # run as a file by `blender --python`
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from dcdi_core.dataset import factory_folder as ff  # noqa: E402
from dcdi_core.dataset.factory_folder import (  # noqa: E402
    MANIFEST, SETTINGS_FILE, append_record, finished_ids, read_manifest, settings_from_manifest)


def sample_seed(seed: int, index: int) -> int:
    """A well-mixed 31-bit seed per sample (same seed, same scene)."""
    return int(np.random.SeedSequence([seed, index]).generate_state(1)[0] & 0x7FFFFFFF)


def parse(argv):
    p = argparse.ArgumentParser(prog="factory", description=__doc__.split("\n\n")[0])
    from scenes.recipes import RECIPES
    p.add_argument("--recipe", required=True,
                   help="scene recipe: " + "; ".join(f"{r.name}: {r.summary}" for r in RECIPES.values()))
    p.add_argument("--count", type=int, required=True, metavar="N",
                   help="images in the whole dataset: indices 0 .. N-1 over all shards (a resume may raise it)")
    p.add_argument("--lens", action="append", default=[], help="lens id or .toml path (repeat for several; "
                                                               "default mos-s1); the first one's camera renders")
    p.add_argument("--out", required=True, help="output folder (created; a resume must use the same settings)")
    p.add_argument("--add-lens", action="store_true",
                   help="resume a folder with more --lens than it holds (listed after its own, which stay in "
                        "their order): the new lenses are simulated on its finished samples too")
    p.add_argument("--seed", type=int, default=0, help="dataset seed")
    p.add_argument("--shard", default="0/1",
                   help="I/N: this job's share of the indices (i %% N == I); auto: I and N from the job array "
                        "(SLURM_ARRAY_TASK_ID/SLURM_ARRAY_TASK_COUNT, or JOB_COMPLETION_INDEX with auto/N or "
                        "DCDI_SHARD_COUNT)")
    p.add_argument("--resolution", type=int, nargs=2, default=[480, 640], metavar=("H", "W"),
                   help="image rows and columns (default 480 640)")
    p.add_argument("--samples", dest="samples", type=int, default=argparse.SUPPRESS,
                   help=argparse.SUPPRESS)              # the former name of --cycles-samples
    p.add_argument("--cycles-samples", dest="samples", type=int, default=8, metavar="SPP",
                   help="Cycles render samples per pixel, denoised (not images: see --count; default 8: 45.5 dB "
                        "against 256 samples; 12: 46.7 dB for 30 %% more time; see python -m "
                        "blender_addon.tools.render_noise)")
    p.add_argument("--no-denoise", action="store_true",
                   help="switch the denoiser off (a Blender without OpenImageDenoise renders undenoised anyway, "
                        "with a warning)")
    p.add_argument("--denoise-quality", default=RenderSettings.denoising_quality, choices=["HIGH", "BALANCED", "FAST"],
                   help="Open Image Denoise quality (see python -m blender_addon.tools.render_noise)")
    p.add_argument("--denoise-prefilter", default=RenderSettings.denoising_prefilter,
                   choices=["NONE", "FAST", "ACCURATE"], help="prefilter of the denoiser's albedo and normal guides")
    p.add_argument("--diffuse-bounces", type=int, default=RenderSettings.diffuse_bounces,
                   help="diffuse light-path bounces (>= 0)")
    p.add_argument("--textures", metavar="DIR", default=None,
                   help="a folder of PNG, JPEG or EXR images (photographs, or CC0 material sets with colour, "
                        "normal and roughness maps) mapped onto a share of the surfaces, seeded")
    p.add_argument("--exposure", choices=["auto", "off"], default="auto",
                   help="auto (default): one gain per frame puts its mean at mid grey with at most 0.3 %% of "
                        "the pixels above 1.0 (a camera's meter); off: the render's values as they are")
    p.add_argument("--baseline-depth", type=float, default=2.0, help="depth of the depth-unaware baseline, m")
    p.add_argument("--psf-rays", type=int, default=None, help="PSF pupil grid (default: the library default)")
    p.add_argument("--psf-wavelengths", type=int, default=None, help="PSF wavelengths (default: the library default)")
    return p.parse_args(argv)


MAX_RESOLUTION = 65536          # Blender's own limits: 4 .. 65536 pixels a side
MIN_RESOLUTION = 4


def check_arguments(a):
    """Everything checked before the output folder is touched; raises a
    DcdiError naming the option and what is allowed. Sets a.shard_index,
    a.shard_count, a.render, a.lenses, a.psf_settings."""
    from dcdi_core.errors import InputRangeError
    from dcdi_core.optics.lens import load_lens
    from dcdi_core.psf.compute import PSFSettings, check_psf_memory
    from scenes.recipes import RECIPES

    if a.recipe not in RECIPES:
        raise InputRangeError("--recipe", a.recipe, ", ".join(RECIPES))
    blender_recipe = RECIPES[a.recipe].build is not None
    if blender_recipe:
        check_blender()
        check_cycles()
    from dcdi_core.dataset.exposure import ExposureOptions
    from dcdi_core.dataset.textures import TextureLibrary
    # Blender decodes the Blender recipes' textures itself; the numpy recipe decodes them with dcdi_core.io
    a.textures = (TextureLibrary.from_folder(a.textures, pixels=not blender_recipe) if a.textures is not None
                  else None)
    a.exposure_options = ExposureOptions() if a.exposure == "auto" else None
    if a.shard.strip().lower().startswith("auto"):
        a.shard = "{}/{}".format(*shard_from_environment(a.shard))      # recorded as resolved
    try:
        i, n = (int(v) for v in a.shard.split("/"))
        if not 0 <= i < n:
            raise ValueError
    except ValueError:
        raise InputRangeError("--shard", a.shard, "I/N with 0 <= I < N (integers)") from None
    a.shard_index, a.shard_count = i, n
    if a.count < 0:
        raise InputRangeError("--count", a.count, "an integer >= 0 (images in the dataset)")
    h, w = a.resolution
    if not (MIN_RESOLUTION <= h <= MAX_RESOLUTION and MIN_RESOLUTION <= w <= MAX_RESOLUTION):
        raise InputRangeError("--resolution", f"{h} {w}",
                              f"rows and columns from {MIN_RESOLUTION} to {MAX_RESOLUTION} pixels")
    if not (a.baseline_depth > 0):
        raise InputRangeError("--baseline-depth", a.baseline_depth, "> 0 metres, or inf")
    for name, v in (("--psf-rays", a.psf_rays), ("--psf-wavelengths", a.psf_wavelengths)):
        if v is not None and v < 1:
            raise InputRangeError(name, v, "an integer >= 1")
    denoise, reason = not a.no_denoise, "--no-denoise" if a.no_denoise else None
    if denoise and blender_recipe and not denoiser_available():
        import bpy
        denoise, reason = False, NO_DENOISER
        print(f"factory: warning: {NO_DENOISER} ({bpy.app.version_string}): frames are rendered undenoised "
              f"({a.samples} samples/pixel), as dataset.json and the manifest record; for denoised frames run "
              "Blender from blender.org or the pip bpy module, or pass --no-denoise to choose undenoised frames",
              file=sys.stderr, flush=True)
    try:
        a.render = RenderSettings(samples=a.samples, denoise=denoise, denoising_quality=a.denoise_quality,
                                  denoising_prefilter=a.denoise_prefilter, diffuse_bounces=a.diffuse_bounces,
                                  no_denoise_reason=reason)
    except ValueError as e:
        raise InputRangeError("--cycles-samples" if "samples" in str(e) else "--diffuse-bounces", None, str(e)) \
            from None
    a.lenses = [load_lens(x) for x in (a.lens or ["mos-s1"])]
    ids = [lens.id for lens in a.lenses]
    if len(set(ids)) != len(ids):
        raise InputRangeError("--lens", " ".join(ids), "each lens once (their files share a folder name)")
    base = PSFSettings()
    a.psf_settings = PSFSettings(pupil_samples=a.psf_rays or base.pupil_samples,
                                 n_wavelengths=a.psf_wavelengths or base.n_wavelengths)
    # per lens: a library of every bin (as the depth maps of a dataset reach them all) at the
    # settings' kernel, and the PSF map of one image (the baseline's, kept for the run)
    from dcdi_core.psf.library import LibraryGrid
    g = LibraryGrid()
    n_psf = g.n_fields * (g.n_depths + 1)
    patches = -(-h // 16) * -(-w // 16)
    check_psf_memory(a.psf_settings, n_psf, library_psfs=n_psf * len(a.lenses), map_kernels=2 * patches)
    return a


def shard_from_environment(text: str = "auto", env=None) -> tuple[int, int]:
    """(I, N) of ``--shard auto`` (or ``auto/N``) from a job array: Slurm
    (SLURM_ARRAY_TASK_ID, its MIN, STEP and COUNT: I is the task's position
    in the array, which must be evenly spaced, N the task count), else a
    Kubernetes indexed Job (JOB_COMPLETION_INDEX; N from ``auto/N``, else
    DCDI_SHARD_COUNT, which the Job sets to its ``completions``). Refused
    (InputRangeError naming --shard) when neither is there or they disagree."""
    from dcdi_core.errors import InputRangeError
    env = os.environ if env is None else env
    head, _, given = text.strip().lower().partition("/")
    if head != "auto" or (given and not given.isdigit()):
        raise InputRangeError("--shard", text, "I/N, auto or auto/N")
    n_given = int(given) if given else None

    def number(name, default=None):
        v = env.get(name, default)
        try:
            return int(v)
        except (TypeError, ValueError):
            raise InputRangeError(f"--shard {text}: environment variable {name}", v, "an integer") from None

    if env.get("SLURM_ARRAY_TASK_ID"):
        i, lo, step = number("SLURM_ARRAY_TASK_ID"), number("SLURM_ARRAY_TASK_MIN", 0), \
            number("SLURM_ARRAY_TASK_STEP", 1)
        n, hi = number("SLURM_ARRAY_TASK_COUNT"), number("SLURM_ARRAY_TASK_MAX")
        if step < 1 or (i - lo) % step or hi != lo + (n - 1) * step:
            raise InputRangeError("--shard auto", f"Slurm array {lo}-{hi}:{step} of {n} tasks",
                                  "an evenly spaced array (e.g. --array=0-7): each task's position is its shard")
        i = (i - lo) // step
    elif env.get("JOB_COMPLETION_INDEX"):
        i = number("JOB_COMPLETION_INDEX")
        n = n_given if n_given is not None else number("DCDI_SHARD_COUNT") if env.get("DCDI_SHARD_COUNT") else None
        if n is None:
            raise InputRangeError("--shard auto (JOB_COMPLETION_INDEX set)", None,
                                  "the shard count: --shard auto/N or DCDI_SHARD_COUNT=N (the Job's completions)")
    else:
        raise InputRangeError("--shard auto", None, "a job array's environment (SLURM_ARRAY_TASK_ID and "
                                                    "SLURM_ARRAY_TASK_COUNT, or JOB_COMPLETION_INDEX), or --shard I/N")
    if n_given is not None and n_given != n:
        raise InputRangeError("--shard", text, f"auto or auto/{n}: the job array has {n} tasks")
    if not 0 <= i < n:
        raise InputRangeError("--shard auto", f"{i}/{n}", "0 <= I < N (the job array's index and count)")
    return i, n


# ------------------------------------------------------------------ the folder: settings, manifest, temporaries
# (the format itself: dcdi_core.dataset.factory_folder)
# each recorded setting and the option that sets it (for the refusal's message)
OPTION_OF = {"recipe": "--recipe", "seed": "--seed", "shard": "--shard", "resolution": "--resolution",
             "lenses": "--lens", "baseline_depth_m": "--baseline-depth",
             "render.samples": "--cycles-samples", "render.denoise": "the denoiser (--no-denoise)",
             "render.no_denoise_reason": "why the frames are undenoised",
             "render.denoising_quality": "--denoise-quality", "render.denoising_prefilter": "--denoise-prefilter",
             "render.diffuse_bounces": "--diffuse-bounces",
             "psf_settings.pupil_samples": "--psf-rays", "psf_settings.n_wavelengths": "--psf-wavelengths",
             "scene.textures": "--textures", "scene.exposure": "--exposure",
             "scene.recipes_version": "the factory's version (its scene recipes changed)"}

# raised whenever a recipe's scenes change: a folder of older scenes is not resumed with newer ones
RECIPES_VERSION = 2


def run_settings(a) -> dict:
    """What defines the samples of this folder (the count may grow; all else
    must stay): recorded before the first sample, compared on every resume."""
    from dcdi_core.psf.library import lens_fingerprint
    return ff.settings_record(recipe=a.recipe, seed=a.seed, shard=a.shard, resolution=a.resolution,
                              lenses=[lens.id for lens in a.lenses],
                              lens_fingerprints={lens.id: lens_fingerprint(lens) for lens in a.lenses},
                              baseline_depth_m=a.baseline_depth, render=a.render.as_dict(),
                              psf_settings=a.psf_settings.as_dict(), scene=scene_settings(a))


def scene_settings(a) -> dict:
    """What shapes the frames besides the recipe and seed: the recipes'
    version, the texture folder (its path and a hash of its files' names and
    sizes), the exposure."""
    tex, exp = a.textures, a.exposure_options
    return {"recipes_version": RECIPES_VERSION,
            "textures": "none" if tex is None else f"{tex.folder} (files {tex.fingerprint()})",
            "exposure": "off" if exp is None else (f"auto (mean luminance {exp.mean_luminance}, at most "
                                                   f"{exp.max_clipped} clipped, gain <= {exp.max_gain})")}


# recorded but not compared: the format's number, and why undenoised frames are (their flag is compared)
NOT_COMPARED = ("format", "render.no_denoise_reason")


def settings_differences(have: dict, want: dict) -> list[str]:
    """'--option: folder X, this run Y' for every recorded setting that differs
    (settings the folder does not record are not compared)."""
    a, b = ff.flat_settings(have), ff.flat_settings(want)
    diffs = []
    if any(k.startswith("scene.") for k in b) and not any(k.startswith("scene.") for k in a):
        diffs.append("the scene recipes: the folder was made by an older factory, before its scenes changed")
    for key in sorted(set(a) & set(b)):
        if key in NOT_COMPARED or a[key] == b[key]:
            continue
        if key == "render.denoise":
            diffs.append(f"{OPTION_OF[key]}: the folder {_denoised(a)}, this run {_denoised(b)}")
            continue
        if key == "lens_fingerprints":
            changed = sorted(x for x in set(a[key]) & set(b[key]) if a[key][x] != b[key][x])
            if changed:
                diffs.append(f"the lens file of {', '.join(changed)} (its optics changed since the folder was made)")
            continue
        name = OPTION_OF.get(key, f"{key.replace('.', ' ').replace('_', ' ')} (not an option: another version "
                                  "of the factory or of dcdi_core)")
        show = (lambda v: " ".join(v) if key == "lenses" else " ".join(map(str, v)) if isinstance(v, list) else v)
        diffs.append(f"{name}: the folder {show(a[key])}, this run {show(b[key])}")
    return diffs


def _denoised(flat: dict) -> str:
    """'denoised', or 'undenoised (why)' of flattened settings."""
    if flat["render.denoise"]:
        return "denoised"
    why = flat.get("render.no_denoise_reason")
    return f"undenoised ({why})" if why else "undenoised"


def remove_stale_files(out: Path) -> list[Path]:
    """This run's own leftovers of a killed run: the hidden temporaries of
    atomic writes (.<name>.<random>.tmp<ext>, dcdi_core.atomic) and Blender's
    hand-over renders (.<id>.render.exr). Only called with the folder's lock
    held, so no live run's temporaries are touched."""
    from dcdi_core.atomic import remove_stale_temporaries
    return remove_stale_temporaries(out) + _removed(p for p in out.glob(".*" + ff.RENDER_HANDOVER_SUFFIX)
                                                    if ff.is_render_handover(p.name))


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


@dataclass(frozen=True)
class RenderSettings:
    """Cycles settings of the all-in-focus render (CPU). The defaults come from
    the error-against-time tables of ``python -m blender_addon.tools.render_noise``
    (docs/factory.md): samples per pixel; the Open Image Denoise pass (quality HIGH,
    BALANCED or FAST; prefilter of its albedo and normal guides NONE, FAST or
    ACCURATE), or none, and why (``no_denoise_reason``: --no-denoise, or a
    Blender without the denoiser); light-path bounces (counts)."""

    samples: int = 8
    denoise: bool = True
    # on the textured scenes at 8 samples (render_noise table, docs/factory.md): BALANCED with the FAST
    # prefilter 36.6 dB against 128 samples in 5.6 s; HIGH without a prefilter (the former default)
    # 35.2 dB in 6.4 s: fine texture makes the albedo guide noisy, and the prefilter cleans it
    denoising_quality: str = "BALANCED"
    denoising_prefilter: str = "FAST"
    max_bounces: int = 4
    diffuse_bounces: int = 2
    glossy_bounces: int = 2
    transmission_bounces: int = 2
    # why the frames are not denoised: "--no-denoise", or NO_DENOISER (this Blender has no
    # OpenImageDenoise); None when they are. Recorded, not compared: render.denoise is
    no_denoise_reason: str | None = None

    def __post_init__(self):
        if not (isinstance(self.samples, int) and 1 <= self.samples <= 65536):
            raise ValueError(f"render samples must be an integer in [1, 65536], got {self.samples!r}")
        if self.denoising_quality not in ("HIGH", "BALANCED", "FAST"):
            raise ValueError(f"denoising quality must be HIGH, BALANCED or FAST, got {self.denoising_quality!r}")
        if self.denoising_prefilter not in ("NONE", "FAST", "ACCURATE"):
            raise ValueError(f"denoising prefilter must be NONE, FAST or ACCURATE, got {self.denoising_prefilter!r}")
        for name in ("max_bounces", "diffuse_bounces", "glossy_bounces", "transmission_bounces"):
            v = getattr(self, name)
            if not (isinstance(v, int) and 0 <= v <= 1024):
                raise ValueError(f"{name.replace('_', ' ')} must be an integer in [0, 1024], got {v!r}")

    def as_dict(self) -> dict:
        """The settings as recorded (dataset.json, the manifest): the reason
        for undenoised frames only where they are undenoised."""
        d = asdict(self)
        if d["no_denoise_reason"] is None:
            del d["no_denoise_reason"]
        return d


NO_DENOISER = "this Blender has no OpenImageDenoise"


def denoiser_available(scene=None) -> bool:
    """Whether this Blender's Cycles can denoise on the CPU: OpenImageDenoise
    is compiled in (Debian's Blender has none). The denoiser's enum is
    dynamic: its RNA lists no items to Python (``bl_rna.properties
    ['denoiser'].enum_items`` is empty with and without OpenImageDenoise), so
    the test is the assignment itself, on ``scene`` or a scratch scene."""
    import bpy
    own = scene is None
    if own:
        scene = bpy.data.scenes.new("dcdi-denoiser-probe")
    try:
        scene.cycles.denoiser = "OPENIMAGEDENOISE"
        return True
    except TypeError:                   # 'enum "OPENIMAGEDENOISE" not found in ()'
        return False
    finally:
        if own:
            bpy.data.scenes.remove(scene)


def check_cycles() -> None:
    """Refuse (InputRangeError naming --recipe) a Blender built without the
    Cycles render engine, which the Blender recipes render with."""
    import bpy

    from dcdi_core.errors import InputRangeError
    scene = bpy.data.scenes.new("dcdi-cycles-probe")
    try:
        scene.render.engine = "CYCLES"
        ok = hasattr(scene, "cycles")
    except TypeError:
        ok = False
    finally:
        bpy.data.scenes.remove(scene)
    if not ok:
        raise InputRangeError("--recipe", None, f"a Blender with the Cycles render engine (this Blender "
                                                f"{bpy.app.version_string} has none), or --recipe leaves (numpy)")


def setup_render(scene, lens, height: int, width: int, render: RenderSettings, seed: int):
    """All-in-focus Cycles render on the CPU through the lens's pinhole
    camera (dcdi_core.render.camera: at the entrance pupil, paraxial focal
    length, the image spanning the sensor diagonal); returns that
    PinholeCamera."""
    import bpy

    from blender_addon.bpy_render import set_area_pixel_filter, set_light_paths, set_multilayer_exr
    from dcdi_core.render.camera import PinholeCamera

    pinhole = PinholeCamera.for_lens(lens, height, width)
    cam = bpy.data.cameras.new("lens")
    for name, value in pinhole.blender_camera_settings().items():
        setattr(cam, name, value)
    cam.dof.use_dof = False
    cam.clip_start = 0.01
    cam.clip_end = 1.0e5
    obj = bpy.data.objects.new("lens", cam)
    scene.collection.objects.link(obj)
    scene.camera = obj
    scene.render.engine = "CYCLES"
    c = scene.cycles
    c.device = "CPU"
    c.samples = render.samples
    c.seed = seed
    c.use_denoising = render.denoise
    if render.denoise:
        if not denoiser_available(scene):
            from dcdi_core.errors import RenderError
            raise RenderError(f"this Blender ({bpy.app.version_string}) has no OpenImageDenoise: render "
                              "undenoised (RenderSettings(denoise=False), the factory's --no-denoise) or use a "
                              "Blender that has it (blender.org's, or the pip bpy module)")
        c.denoiser = "OPENIMAGEDENOISE"
    c.denoising_quality = render.denoising_quality
    c.denoising_prefilter = render.denoising_prefilter
    # a dataset wants many clean images fast: few bounces, no caustics (render_noise's table)
    set_light_paths(c, render.max_bounces, render.diffuse_bounces, render.glossy_bounces,
                    render.transmission_bounces)
    set_area_pixel_filter(c)
    scene.render.resolution_x, scene.render.resolution_y = width, height
    scene.render.resolution_percentage = 100
    scene.render.film_transparent = False
    scene.view_layers[0].use_pass_z = True
    # the file is a hand-over read back at once and deleted: no compression (measured: no gain, no cost)
    set_multilayer_exr(scene.render.image_settings)
    return pinhole


def empty_scene() -> None:
    """Start each sample from Blender's factory startup file, emptied: the
    same scene settings whatever came before. ``read_homefile`` and not
    ``read_factory_settings``: the latter also resets the preferences and so
    unregisters and re-registers every add-on, which costs 0.05 s a sample
    and, in distributions' builds whose bundled add-ons fail to register
    (Debian's 5.2: bl_pkg without ``cattrs``), prints their traceback for
    every sample."""
    import bpy

    bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)


def render_rgbd(recipe: str, lens, seed: int, height: int, width: int, render: RenderSettings, tmp: Path,
                timings: dict | None = None, *, textures=None, scene_info: dict | None = None):
    """Build the scene, render; returns (image (H, W, 3) float32 linear,
    depth (H, W) float32 metres from the lens's first vertex, inf = background).
    ``timings``, if given, receives the wall seconds of each stage: "scene"
    (reset and recipe), "render" (Cycles: sync, BVH, path tracing, denoising,
    the EXR hand-over file), "read" (reading that file back), and their CPU
    seconds as "cpu_scene", "cpu_render", "cpu_read". ``textures``: a
    TextureLibrary for a share of the surfaces; ``scene_info``, if given,
    receives what the scene holds (objects placed, materials by kind, the
    texture sets used).

    A SIGINT or SIGTERM while Blender works (scene and render) stops the job
    once Blender returns (``signals.deferred``: Blender runs Python of its
    own, Cycles' engine and the handlers, and drops an exception raised
    there); the hand-over file ``tmp`` is removed whatever happens."""
    import bpy

    from dcdi_core.io.images import read_depth, read_image
    from dcdi_core.render.camera import depth_from_planar_z
    from dcdi_core.signals import deferred
    from scenes.recipes import build

    t, c = [time.perf_counter()], [_cpu_s()]
    try:
        with deferred():
            empty_scene()
            scene = bpy.context.scene
            builder = build(recipe, np.random.default_rng(seed), textures)
            if scene_info is not None:
                scene_info.update(scene_summary(builder))
            pinhole = setup_render(scene, lens, height, width, render, seed)
            scene.render.filepath = str(tmp)
            t.append(time.perf_counter()), c.append(_cpu_s())
            render_still(tmp)
            t.append(time.perf_counter()), c.append(_cpu_s())
        img = read_image(tmp)
        z = read_depth(tmp)
    finally:
        tmp.unlink(missing_ok=True)        # read, or left behind by a stop or a failure
    t.append(time.perf_counter()), c.append(_cpu_s())
    if timings is not None:
        timings.update(scene=t[1] - t[0], render=t[2] - t[1], read=t[3] - t[2])
        timings.update({"cpu_" + k: c[i + 1] - c[i] for i, k in enumerate(("scene", "render", "read"))})
    return img, depth_from_planar_z(z, pinhole.entrance_pupil_mm)


def render_still(path: Path) -> None:
    """Render the current scene's frame; Blender writes it to ``path``.
    Raises ``Stopped`` (SIGINT) when Blender's own break event cancelled the
    render (Ctrl-C reaching Blender's handler, where the factory could not
    take SIGINT: Blender then writes no file), and RenderError when Blender
    finished without writing the file."""
    import bpy

    from dcdi_core.errors import RenderError
    from dcdi_core.signals import Stopped
    cancelled = []

    def on_cancel(*_):
        cancelled.append(True)
    bpy.app.handlers.render_cancel.append(on_cancel)
    try:
        bpy.ops.render.render(write_still=True)
    finally:
        bpy.app.handlers.render_cancel.remove(on_cancel)
    if cancelled:
        raise Stopped(signal.SIGINT)
    if not path.is_file():
        raise RenderError(f"{path}: Blender finished the render but wrote no file (see its messages above: "
                          "a full disk?)")


def scene_summary(builder) -> dict:
    """The manifest's short account of a built scene."""
    kinds: dict[str, int] = {}
    for r in builder.records:
        kinds[r.get("kind", "?")] = kinds.get(r.get("kind", "?"), 0) + 1
    sets = sorted({r["set"] for r in builder.records if "set" in r})
    return {"objects": builder.objects, "materials": dict(sorted(kinds.items())), "texture_sets": sets}


def frame(a, lens, seed: int, tmp: Path, stages: dict):
    """One all-in-focus frame of the run's recipe, exposed: (image, depth,
    scene record). Blender renders its recipes; ``leaves`` is drawn in numpy."""
    from dcdi_core.dataset.exposure import expose
    from dcdi_core.dataset.statistics import clipped_fraction
    from scenes.recipes import RECIPES

    h, w = a.resolution
    info: dict = {}
    if RECIPES[a.recipe].build is None:
        from dcdi_core.dataset.leaves import leaves_rgbd
        t, c = time.perf_counter(), _cpu_s()
        img, depth, info = leaves_rgbd(seed, h, w, textures=a.textures)
        stages.update(scene=time.perf_counter() - t, cpu_scene=_cpu_s() - c)
    else:
        img, depth = render_rgbd(a.recipe, lens, seed, h, w, a.render, tmp, stages, textures=a.textures,
                                 scene_info=info)
    if a.exposure_options is not None:
        img, info["exposure"] = expose(img, a.exposure_options)
    else:
        info["exposure"] = {"gain": 1.0, "clipped": round(clipped_fraction(img), 6)}
    return img, depth, info


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
        from blender_addon.factory.merge_shards import main as merge_main
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
              f"{rate * 3600:.0f} samples/h, ETA {(len(todo) - n - 1) / rate:.0f} s, RSS {_rss_mib():.0f} MiB",
              flush=True)
        if os.environ.get("DCDI_FACTORY_STOP_AFTER") and n + 1 >= int(os.environ["DCDI_FACTORY_STOP_AFTER"]):
            print("factory: stopping early (DCDI_FACTORY_STOP_AFTER)", flush=True)
            return 3
    return 0


def make_sample(a, layout, sims: dict, i: int) -> dict:
    """Sample ``i``: render (or draw) its frame, simulate it through every
    lens, and commit its files with its manifest line (``commit_sample``);
    returns its manifest record. Its files are written as temporaries
    first: a failure or a stop at any stage leaves nothing of it behind.
    ``sims``: the run's LensSimulators by lens id, built on first use."""
    sid, seed = ff.sample_id(a.recipe, i), sample_seed(a.seed, i)
    t0, c0 = time.perf_counter(), _cpu_s()
    stages = {}
    files = StagedFiles(layout)
    try:
        img, depth, scene_info = frame(a, a.lenses[0], seed, layout.render_handover(sid), stages)
        t_render = time.perf_counter() - t0
        t1 = time.perf_counter()
        ff.write_rgbd(files, sid, img, depth)
        stages["write"] = time.perf_counter() - t1
        lens_records = {lens.id: simulate_lens(a, files, sims, lens, sid, img, depth, stages) for lens in a.lenses}
        record = sample_record(a, i, seed, depth, scene_info, stages, lens_records, t_render, t0, c0)
        commit_sample(files, layout.manifest, record)
    except BaseException:
        files.discard()
        raise
    return record


def simulate_lens(a, files, sims: dict, lens, sid: str, img, depth, stages: dict) -> dict:
    """Simulate ``lens`` on a frame (image, depth in metres) and stage its
    aberrated, baseline and sharp images in ``files``; adds the wall and
    CPU seconds to ``stages``; returns the lens's manifest entry."""
    from dcdi_core.progress import psf_progress
    from dcdi_core.render.geometry import ImageGeometry
    from dcdi_core.render.simulate import LensSimulator, SimulateOptions

    t1 = time.perf_counter()
    if lens.id not in sims:
        h, w = a.resolution
        options = SimulateOptions(geometry=ImageGeometry.full_sensor(lens, h, w), settings=a.psf_settings,
                                  baseline_depth_m=a.baseline_depth)
        sims[lens.id] = LensSimulator(lens, options, progress=psf_progress(f"factory: PSFs of {lens.id}"))
        stages["setup"] = stages.get("setup", 0.0) + time.perf_counter() - t1
    t2, c2 = time.perf_counter(), _cpu_s()
    r = sims[lens.id](img, depth)
    t3 = time.perf_counter()
    stages["cpu_simulate"] = stages.get("cpu_simulate", 0.0) + _cpu_s() - c2
    ff.write_lens_images(files, lens.id, sid, aberrated=r.image, baseline=r.baseline, sharp=r.sharp,
                         record=capture_record(sims[lens.id]))
    t4 = time.perf_counter()
    stages["simulate"] = stages.get("simulate", 0.0) + t3 - t2
    stages["write"] += t4 - t3
    return {"seconds": round(t4 - t1, 3), **r.info}


def sample_record(a, i: int, seed: int, depth, scene_info: dict, stages: dict, lens_records: dict,
                  t_render: float, t0: float, c0: float) -> dict:
    """A sample's manifest line: seed, recipe, camera, render settings, scene,
    depth range (metres), stage seconds, the render's and the whole
    sample's wall seconds (``t_render``; since ``t0``, a perf_counter) and
    CPU seconds (since ``c0``), lenses, versions."""
    from scenes.recipes import RECIPES
    finite = depth[np.isfinite(depth)]
    render = ({"engine": "CYCLES", "device": "CPU", **a.render.as_dict()} if RECIPES[a.recipe].build is not None
              else {"engine": "numpy"})
    return {"id": ff.sample_id(a.recipe, i), "index": i, "recipe": a.recipe, "seed": seed, "dataset_seed": a.seed,
            "resolution": list(a.resolution), "camera_lens": a.lenses[0].id,
            "render": {**render, "seconds": round(t_render, 3)},
            "scene": scene_info,
            "depth_m": {"min": float(finite.min()) if finite.size else None,
                        "max": float(finite.max()) if finite.size else None,
                        "infinite_fraction": float(np.isinf(depth).mean())},
            "stage_seconds": {k: round(v, 3) for k, v in stages.items()},
            "seconds": round(time.perf_counter() - t0, 3), "cpu_seconds": round(_cpu_s() - c0, 3),
            "lenses": lens_records, "psf_settings": a.psf_settings.as_dict(), "versions": _versions()}


# ------------------------------------------------------------------ a sample's files: staged, then committed
class StagedFiles:
    """A sample's files under hidden temporary names beside their places
    (``.<name>.p<pid>_<random>.tmp.exr``: the form a resume removes as a
    killed run's), renamed into place only with the sample's manifest line
    (:func:`commit_sample`). It stands in for the folder's layout when the
    folder format's writers (``factory_folder.write_rgbd``,
    ``write_lens_images``) ask where each file goes."""

    def __init__(self, layout):
        self.layout = layout
        self.moves: list[tuple[Path, Path]] = []        # (temporary, its place), in the order written

    def aif(self, sid: str) -> Path:
        return self._stage(self.layout.aif(sid))

    def depth(self, sid: str) -> Path:
        return self._stage(self.layout.depth(sid))

    def lens_image(self, lens: str, kind: str, sid: str) -> Path:
        return self._stage(self.layout.lens_image(lens, kind, sid))

    def _stage(self, path: Path) -> Path:
        import secrets
        tmp = path.with_name(f".{path.name}.p{os.getpid()}_{secrets.token_hex(4)}.tmp{path.suffix}")
        self.moves.append((tmp, path))
        return tmp

    def discard(self) -> None:
        """Remove the temporaries not renamed (all of them, unless committed)."""
        for tmp, _ in self.moves:
            tmp.unlink(missing_ok=True)


def commit_sample(files: StagedFiles, manifest: Path, record: dict) -> None:
    """Rename a sample's staged files into place, then append its manifest
    line: both or neither. A stop waits for the commit (``deferred``: a
    few renames and one flushed line, milliseconds), then stops the run
    with the sample kept. A failure (a full disk while appending) removes
    the files already renamed and cuts the manifest back to its length
    before, so the folder holds the sample whole with its line or not at
    all. A kill (SIGKILL, a power cut) between the renames and the line
    leaves files without a line: the next run removes them
    (:func:`remove_unfinished_files`)."""
    from dcdi_core.errors import output_error
    from dcdi_core.signals import deferred
    with deferred():
        size = manifest.stat().st_size if manifest.exists() else None
        placed = []
        try:
            for tmp, path in files.moves:
                try:
                    os.replace(tmp, path)
                except OSError as e:
                    raise output_error(path, e) from None
                placed.append(path)
            append_record(manifest, record)
        except BaseException:
            for path in placed:
                path.unlink(missing_ok=True)
            _cut_back(manifest, size)
            raise


def _cut_back(manifest: Path, size: int | None) -> None:
    """The manifest back to ``size`` bytes (None: it did not exist), best
    effort: a part of a line that stays is dropped as torn on resume."""
    try:
        if size is None:
            manifest.unlink(missing_ok=True)
        else:
            os.truncate(manifest, size)
    except OSError:
        pass


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


def add_lenses(out: Path, records: list[dict], lenses, a, settings: dict) -> None:
    """Simulate ``lenses`` on the finished samples (from their aif/ and depth/
    files), then rewrite the manifest (each record with the new lenses) and
    the settings record, atomically; killed half-way, the same command
    starts over (every file is replaced atomically)."""
    from dcdi_core.progress import psf_progress
    from dcdi_core.render.geometry import ImageGeometry
    from dcdi_core.render.simulate import LensSimulator, SimulateOptions

    layout = ff.FolderLayout(out)
    h, w = a.resolution
    print(f"factory: adding {', '.join(x.id for x in lenses)} to {len(records)} finished samples", flush=True)
    for lens in lenses:
        options = SimulateOptions(geometry=ImageGeometry.full_sensor(lens, h, w), settings=a.psf_settings,
                                  baseline_depth_m=a.baseline_depth)
        sim = LensSimulator(lens, options, progress=psf_progress(f"factory: PSFs of {lens.id}"))
        for rec in records:
            sid = rec["id"]
            t = time.perf_counter()
            r = sim(*ff.read_rgbd(layout, sid))
            ff.write_lens_images(layout, lens.id, sid, aberrated=r.image, baseline=r.baseline, sharp=r.sharp,
                                 record=capture_record(sim))
            rec.setdefault("lenses", {})[lens.id] = {"seconds": round(time.perf_counter() - t, 3), **r.info}
    ff.write_manifest(layout.manifest, records)
    ff.write_settings(out, settings)


def capture_record(sim):
    """What the factory's captures through ``sim`` (a ``LensSimulator``) remember: the app's record."""
    from dcdi_core.app.records import simulated_record
    return simulated_record(sim.lens, sim.geometry, focus_distance_m=sim.library.settings.focus_distance_m,
                            psf_source="trace", distortion=sim.table is not None, extra={"factory": True})


def _versions() -> dict:
    import platform

    import dcdi_core
    try:
        import bpy
        blender = bpy.app.version_string
    except ImportError:               # the numpy recipe runs without Blender
        blender = None
    return {"blender": blender, "dcdi": dcdi_core.__version__, "numpy": np.__version__,
            "python": platform.python_version()}


def _cpu_s() -> float:
    """CPU seconds (user + system) of this process, all threads."""
    try:
        import resource
    except ImportError:           # not on Windows
        return math.nan
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def _rss_mib() -> float:
    """Current resident memory (Linux /proc), else the peak (resource), MiB."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    try:
        import resource
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    except ImportError:
        return math.nan


if __name__ == "__main__":
    sys.exit(run())
