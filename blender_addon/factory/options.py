"""The factory's command line: its options (``parse``), everything checked
before the output folder is touched (``check_arguments``: each refusal
names the option and what is allowed), and the shard of a job array
(``shard_from_environment``)."""
from __future__ import annotations

import argparse
import os
import sys

from .blender import NO_DENOISER, check_blender, check_cycles, denoiser_available
from .render import RenderSettings

DESCRIPTION = ("The dataset factory: seeded scenes rendered all-in-focus with metric depth, then passed through "
               "the depth-aware simulation of each requested lens.")


def parse(argv):
    p = argparse.ArgumentParser(prog="factory", description=DESCRIPTION)
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
    p.add_argument("--cycles-samples", dest="samples", type=int, default=8, metavar="SPP",
                   help="Cycles render samples per pixel, denoised (not images: see --count; default 8: 36.6 dB "
                        "against 128 samples on the textured scenes; 12: 37.6 dB for 41 %% more time; see "
                        "docs/factory.md and python -m blender_addon.tools.render_noise)")
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
