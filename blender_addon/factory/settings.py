"""What defines a factory folder's samples (``run_settings``: recorded in
dataset.json before the first sample) and how two records of it differ
(``settings_differences``, each difference named by the option that sets
it: ``OPTION_OF``); the folder format itself is
``dcdi_core.dataset.factory_folder``. Below both the run and the merge of
shards (``merge_shards``), which name differing settings alike."""
from __future__ import annotations

from dcdi_core.dataset import factory_folder as ff

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
    from dcdi_core.optics.lens import lens_fingerprint
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
