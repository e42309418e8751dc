"""One sample, stage by stage: its seed (``sample_seed``), its frame
(``frame``: rendered by Blender or drawn in numpy, exposed), its simulation
through each lens (``simulate_lens``), its manifest record
(``sample_record``), its files committed with that line
(``make_sample``); and lenses added to a folder's finished samples
(``add_lenses``)."""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from dcdi_core.dataset import factory_folder as ff

from .commit import StagedFiles, commit_sample
from .meters import cpu_seconds
from .render import render_rgbd


def sample_seed(seed: int, index: int) -> int:
    """A well-mixed 31-bit seed per sample (same seed, same scene)."""
    return int(np.random.SeedSequence([seed, index]).generate_state(1)[0] & 0x7FFFFFFF)


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
        t, c = time.perf_counter(), cpu_seconds()
        img, depth, info = leaves_rgbd(seed, h, w, textures=a.textures)
        stages.update(scene=time.perf_counter() - t, cpu_scene=cpu_seconds() - c)
    else:
        img, depth = render_rgbd(a.recipe, lens, seed, h, w, a.render, tmp, stages, textures=a.textures,
                                 scene_info=info)
    if a.exposure_options is not None:
        img, info["exposure"] = expose(img, a.exposure_options)
    else:
        info["exposure"] = {"gain": 1.0, "clipped": round(clipped_fraction(img), 6)}
    return img, depth, info


def make_sample(a, layout, sims: dict, i: int) -> dict:
    """Sample ``i``: render (or draw) its frame, simulate it through every
    lens, and commit its files with its manifest line (``commit_sample``);
    returns its manifest record. Its files are written as temporaries
    first: a failure or a stop at any stage leaves nothing of it behind.
    ``sims``: the run's LensSimulators by lens id, built on first use."""
    sid, seed = ff.sample_id(a.recipe, i), sample_seed(a.seed, i)
    t0, c0 = time.perf_counter(), cpu_seconds()
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
    t2, c2 = time.perf_counter(), cpu_seconds()
    r = sims[lens.id](img, depth)
    t3 = time.perf_counter()
    stages["cpu_simulate"] = stages.get("cpu_simulate", 0.0) + cpu_seconds() - c2
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
            "seconds": round(time.perf_counter() - t0, 3), "cpu_seconds": round(cpu_seconds() - c0, 3),
            "lenses": lens_records, "psf_settings": a.psf_settings.as_dict(), "versions": _versions()}


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
