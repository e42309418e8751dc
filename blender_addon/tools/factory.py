"""The dataset factory: seeded scenes rendered all-in-focus with metric depth,
then passed through the depth-aware simulation of each requested lens.

    blender --background --python blender_addon/tools/factory.py -- --recipe room --count 10 \\
        --lens mos-s1 --out DIR --seed 0 [--shard I/N]
    python -m blender_addon.tools.factory --recipe room --count 10 --lens mos-s1 --out DIR --seed 0

Layout of DIR (paired folders share file names, so paired-folder loaders
read them directly):

    manifest.jsonl                one JSON line per finished sample
    aif/<id>.exr                  all-in-focus render, linear RGB float32
    depth/<id>.exr                planar depth in metres from the lens's first vertex ("Z"; background = inf)
    <lens>/aberrated/<id>.exr     depth-aware simulation (with the lens's distortion)
    <lens>/baseline/<id>.exr      depth-unaware baseline (one depth for the whole image)
    <lens>/sharp/<id>.exr         the all-in-focus image distorted like the others (the aligned target)

<id> is <recipe>-<index, 6 digits>. A sample counts only once its manifest
line is written; every file is written to a temporary name and renamed, so a
killed run restarted with the same arguments finishes the missing samples
and leaves no partial file. ``--shard I/N`` takes the indices i with
i % N == I, so any job runner can split the work.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

# Checked before anything else so that an unsuitable Blender fails with a
# message, not with a traceback from deep inside the scene code.
MIN_BLENDER = (5, 0, 0)


def check_blender() -> None:
    """Refuse a Blender older than MIN_BLENDER (its scene API differs: materials
    without node trees, no image_settings.media_type, no OIDN quality) or one
    whose Python lacks numpy."""
    try:
        import bpy
    except ImportError:
        raise SystemExit("factory: no bpy module: run it with Blender (blender --background --python "
                         "blender_addon/tools/factory.py -- ...) or install the pip bpy module (see requirements.txt)")
    v = tuple(bpy.app.version)
    if v < MIN_BLENDER:
        raise SystemExit(f"factory: Blender {bpy.app.version_string} is too old: the factory needs Blender "
                         f">= {'.'.join(map(str, MIN_BLENDER))} (Blender 5 from blender.org, or the pip bpy module "
                         "of requirements.txt)")
    try:
        import numpy  # noqa: F401
    except ImportError:
        raise SystemExit(f"factory: this Blender's Python ({sys.executable}, {sys.version.split()[0]}) has no "
                         "numpy; Blender from blender.org bundles it, a distribution's blender uses the "
                         "system python3 (install its numpy package)")


if __name__ == "__main__":
    check_blender()

import numpy as np  # noqa: E402

if __package__ in (None, ""):          # run as a file by `blender --python`
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

def sample_seed(seed: int, index: int) -> int:
    """A well-mixed 31-bit seed per sample (same seed, same scene)."""
    return int(np.random.SeedSequence([seed, index]).generate_state(1)[0] & 0x7FFFFFFF)


def parse(argv):
    p = argparse.ArgumentParser(prog="factory", description=__doc__.split("\n\n")[0])
    p.add_argument("--recipe", required=True, help="scene recipe: room, tabletop, street (or plane)")
    p.add_argument("--count", type=int, required=True, help="samples in the whole dataset")
    p.add_argument("--lens", action="append", default=[], help="lens id (repeat for several)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--seed", type=int, default=0, help="dataset seed")
    p.add_argument("--shard", default="0/1", help="I/N: this job's share of the indices")
    p.add_argument("--resolution", type=int, nargs=2, default=[480, 640], metavar=("H", "W"))
    p.add_argument("--samples", type=int, default=8,
                   help="Cycles samples per pixel, denoised (default 8: 45.5 dB against 256 samples; 12: 46.7 dB "
                        "for 30 %% more time; see python -m blender_addon.tools.render_noise)")
    p.add_argument("--no-denoise", action="store_true", help="switch the denoiser off")
    p.add_argument("--denoise-quality", default=RenderSettings.denoising_quality, choices=["HIGH", "BALANCED", "FAST"],
                   help="Open Image Denoise quality (see python -m blender_addon.tools.render_noise)")
    p.add_argument("--denoise-prefilter", default=RenderSettings.denoising_prefilter,
                   choices=["NONE", "FAST", "ACCURATE"], help="prefilter of the denoiser's albedo and normal guides")
    p.add_argument("--diffuse-bounces", type=int, default=RenderSettings.diffuse_bounces,
                   help="diffuse light-path bounces (>= 0)")
    p.add_argument("--baseline-depth", type=float, default=2.0, help="depth of the depth-unaware baseline, m")
    p.add_argument("--psf-rays", type=int, default=None, help="PSF pupil grid (default: the library default)")
    p.add_argument("--psf-wavelengths", type=int, default=None, help="PSF wavelengths (default: the library default)")
    a = p.parse_args(argv)
    try:
        i, n = (int(v) for v in a.shard.split("/"))
        if not 0 <= i < n:
            raise ValueError
    except ValueError:
        p.error(f"--shard must be I/N with 0 <= I < N, got {a.shard!r}")
    a.shard_index, a.shard_count = i, n
    if a.count < 0:
        p.error("--count must be >= 0")
    try:
        a.render = RenderSettings(samples=a.samples, denoise=not a.no_denoise, denoising_quality=a.denoise_quality,
                                  denoising_prefilter=a.denoise_prefilter, diffuse_bounces=a.diffuse_bounces)
    except ValueError as e:
        p.error(str(e))
    return a


def finished_ids(manifest: Path) -> set[str]:
    """Ids whose manifest line is complete (a torn last line does not count)."""
    if not manifest.exists():
        return set()
    done = set()
    for line in manifest.read_text().splitlines():
        try:
            done.add(json.loads(line)["id"])
        except (ValueError, KeyError):
            continue
    return done


@dataclass(frozen=True)
class RenderSettings:
    """Cycles settings of the all-in-focus render (CPU). The defaults come from
    the error-against-time tables of ``python -m blender_addon.tools.render_noise``
    (README): samples per pixel; the Open Image Denoise pass (quality HIGH,
    BALANCED or FAST; prefilter of its albedo and normal guides NONE, FAST or
    ACCURATE); light-path bounces (counts)."""

    samples: int = 8
    denoise: bool = True
    denoising_quality: str = "HIGH"
    # NONE: 0.7 dB below ACCURATE at 8 samples for a third less render time (render_noise table)
    denoising_prefilter: str = "NONE"
    max_bounces: int = 4
    diffuse_bounces: int = 2
    glossy_bounces: int = 2
    transmission_bounces: int = 2

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
        return asdict(self)


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


def render_rgbd(recipe: str, lens, seed: int, height: int, width: int, render: RenderSettings, tmp: Path,
                timings: dict | None = None):
    """Build the scene, render; returns (image (H, W, 3) float32 linear,
    depth (H, W) float32 metres from the lens's first vertex, inf = background).
    ``timings``, if given, receives the wall seconds of each stage: "scene"
    (reset and recipe), "render" (Cycles: sync, BVH, path tracing, denoising,
    the EXR hand-over file), "read" (reading that file back), and their CPU
    seconds as "cpu_scene", "cpu_render", "cpu_read"."""
    import bpy

    from dcdi_core.io.images import read_depth, read_image
    from dcdi_core.render.camera import depth_from_planar_z
    from scenes.recipes import RECIPES

    t, c = [time.perf_counter()], [_cpu_s()]
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    RECIPES[recipe](np.random.default_rng(seed))
    pinhole = setup_render(scene, lens, height, width, render, seed)
    scene.render.filepath = str(tmp)
    t.append(time.perf_counter()), c.append(_cpu_s())
    bpy.ops.render.render(write_still=True)
    t.append(time.perf_counter()), c.append(_cpu_s())
    img = read_image(tmp)
    z = read_depth(tmp)
    tmp.unlink()
    t.append(time.perf_counter()), c.append(_cpu_s())
    if timings is not None:
        timings.update(scene=t[1] - t[0], render=t[2] - t[1], read=t[3] - t[2])
        timings.update({"cpu_" + k: c[i + 1] - c[i] for i, k in enumerate(("scene", "render", "read"))})
    return img, depth_from_planar_z(z, pinhole.entrance_pupil_mm)


def run(argv=None) -> int:
    a = parse(sys.argv[sys.argv.index("--") + 1:] if argv is None and "--" in sys.argv else argv)
    from dcdi_core.io.images import write_depth, write_image
    from dcdi_core.optics.lens import load_lens
    from dcdi_core.psf.compute import PSFSettings
    from dcdi_core.render.geometry import ImageGeometry
    from dcdi_core.render.simulate import LensSimulator

    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    manifest = out / "manifest.jsonl"
    lenses = [load_lens(x) for x in (a.lens or ["mos-s1"])]
    h, w = a.resolution
    base = PSFSettings()
    settings = PSFSettings(pupil_samples=a.psf_rays or base.pupil_samples,
                           n_wavelengths=a.psf_wavelengths or base.n_wavelengths)
    render = a.render
    done = finished_ids(manifest)
    todo = [i for i in range(a.count) if i % a.shard_count == a.shard_index
            and f"{a.recipe}-{i:06d}" not in done]
    print(f"factory: {a.recipe}, {len(todo)} samples to do in shard {a.shard}, {len(done)} already in the manifest",
          flush=True)
    t_start = time.perf_counter()
    sims = {}                          # built on the first sample to do: no PSF work for a finished run
    for n, i in enumerate(todo):
        sid = f"{a.recipe}-{i:06d}"
        seed = sample_seed(a.seed, i)
        t0, c0 = time.perf_counter(), _cpu_s()
        stages = {}
        img, depth = render_rgbd(a.recipe, lenses[0], seed, h, w, render, out / f".{sid}.render.exr", stages)
        t_render = time.perf_counter() - t0
        t1 = time.perf_counter()
        write_image(out / "aif" / f"{sid}.exr", img)
        write_depth(out / "depth" / f"{sid}.exr", depth)
        stages["write"] = time.perf_counter() - t1
        lens_records = {}
        for lens in lenses:
            t1 = time.perf_counter()
            if lens.id not in sims:
                sims[lens.id] = LensSimulator(lens, ImageGeometry.full_sensor(lens, h, w), settings=settings,
                                              baseline_depth_m=a.baseline_depth)
                stages["setup"] = stages.get("setup", 0.0) + time.perf_counter() - t1
            t2, c2 = time.perf_counter(), _cpu_s()
            r = sims[lens.id](img, depth)
            aberrated, baseline, sharp, info = r.image, r.baseline, r.sharp, r.info
            t3 = time.perf_counter()
            stages["cpu_simulate"] = stages.get("cpu_simulate", 0.0) + _cpu_s() - c2
            write_image(out / lens.id / "aberrated" / f"{sid}.exr", aberrated)
            write_image(out / lens.id / "baseline" / f"{sid}.exr", baseline)
            write_image(out / lens.id / "sharp" / f"{sid}.exr", sharp)
            t4 = time.perf_counter()
            stages["simulate"] = stages.get("simulate", 0.0) + t3 - t2
            stages["write"] += t4 - t3
            lens_records[lens.id] = {"seconds": round(t4 - t1, 3), **info}
        finite = depth[np.isfinite(depth)]
        record = {"id": sid, "index": i, "recipe": a.recipe, "seed": seed, "dataset_seed": a.seed,
                  "resolution": [h, w], "camera_lens": lenses[0].id,
                  "render": {"engine": "CYCLES", "device": "CPU", **render.as_dict(), "seconds": round(t_render, 3)},
                  "depth_m": {"min": float(finite.min()) if finite.size else None,
                              "max": float(finite.max()) if finite.size else None,
                              "infinite_fraction": float(np.isinf(depth).mean())},
                  "stage_seconds": {k: round(v, 3) for k, v in stages.items()},
                  "seconds": round(time.perf_counter() - t0, 3), "cpu_seconds": round(_cpu_s() - c0, 3),
                  "lenses": lens_records, "psf_settings": settings.as_dict(), "versions": _versions()}
        with open(manifest, "a", encoding="utf-8") as f:
            f.write(json.dumps(record) + "\n")
            f.flush()
            os.fsync(f.fileno())
        el = time.perf_counter() - t_start
        rate = (n + 1) / el
        print(f"  {sid}: {time.perf_counter() - t0:.1f} s (render {t_render:.1f} s); {rate * 3600:.0f} samples/h, "
              f"ETA {(len(todo) - n - 1) / rate:.0f} s, RSS {_rss_mib():.0f} MiB", flush=True)
        if os.environ.get("DCDI_FACTORY_STOP_AFTER") and n + 1 >= int(os.environ["DCDI_FACTORY_STOP_AFTER"]):
            print("factory: stopping early (DCDI_FACTORY_STOP_AFTER)", flush=True)
            return 3
    return 0


def _versions() -> dict:
    import platform

    import bpy

    import dcdi_core
    return {"blender": bpy.app.version_string, "dcdi": dcdi_core.__version__, "numpy": np.__version__,
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
