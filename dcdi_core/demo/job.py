"""The demo job: its scenes through the DCDI chain, the lens reports, and
the summary report.md (module ``dcdi_core.demo``)."""
from __future__ import annotations

import json
import resource
import time
from pathlib import Path

from ..atomic import write_text
from .chain import DEPTH_SCORED_BELOW_M, ChainSettings, Networks, run_chain
from .scenes import factory_scene, synthetic_scene

SYNTHETIC_SIZE = (240, 320)
NOT_RENDERED = ("not rendered here: `python build.py demo` renders one with Blender (bpy) and passes it on; "
                "the engine never starts Blender")


def _cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def run(out, *, factory_sample=None, factory_error: str | None = None, settings: ChainSettings | None = None,
        synthetic_size: tuple[int, int] = SYNTHETIC_SIZE, lenses: bool = True) -> int:
    """Write the demo to the folder ``out`` (module docstring). The factory
    sample: its folder ``factory_sample``, or ``factory_error`` saying why
    there is none. ``lenses`` False leaves out the lens reports."""
    t0, c0 = time.perf_counter(), _cpu_s()
    out = Path(out)
    settings = settings or ChainSettings()
    # everything that can be refused is refused before any work
    nets = Networks.load(settings)
    scenes = [synthetic_scene(nets.camera, synthetic_size, nets.pixel_pitch_mm)]
    if factory_sample is not None:
        scenes.append(factory_scene(factory_sample, nets.camera))
    out.mkdir(parents=True, exist_ok=True)
    print(f"dcdi demo: writing to {out.resolve()}", flush=True)
    print(f"DCDI: {nets.camera.id} captures -> {nets.target.id} depth of field (focus {settings.focus_m:g} m), "
          f"on {len(scenes)} scene(s)", flush=True)
    results = [run_chain(scene, nets, settings, out, log=lambda s: print(s, flush=True)) for scene in scenes]
    write_text(out / "dcdi_scores.json", json.dumps(
        {r.key: {"title": r.title, **r.scores, "corrected_share": r.corrected_share, "dof_refuses": r.refused,
                 "seconds": r.seconds} for r in results}, indent=1) + "\n")
    lines = ["# dcdi demo", ""] + dcdi_section(results, nets, settings, None if factory_sample is not None
                                                 else (factory_error or NOT_RENDERED))
    lines += ["", *simulation_section(scenes, results, nets, settings, out)]
    if lenses:
        from .lenses import lens_section
        print("lens reports:", flush=True)
        lines += ["", *lens_section(out)]
    write_text(out / "report.md", "\n".join(lines) + "\n")
    print(f"  summary: {out / 'report.md'} ({time.perf_counter() - t0:.0f} s, {_cpu_s() - c0:.0f} CPU s "
          "in this process)", flush=True)
    return 0


def _db(x: float) -> str:
    return f"{x:.2f}"


def _method(results, nets: Networks, cfg: dict) -> str:
    """What corrected the captures, as `dcdi correct --method auto` chose it."""
    rec = results[0].correction if results else {}
    if rec.get("method") == "dacn":
        return (f"the shipped DACN (`{nets.dacn_file.name}`: configuration {cfg.get('config', '?')}, "
                f"{cfg.get('iters', '?')} training iterations; {rec.get('reason', '')})")
    return (f"the deconvolution with {nets.camera.id}'s own PSFs at the estimated depth (`dcdi correct --method "
            f"auto`: {rec.get('reason', 'the engine rule')})")


def dcdi_section(results, nets: Networks, settings: ChainSettings, factory_missing: str | None) -> list[str]:
    """The report's DCDI section: what was done, the table, the verdicts."""
    cfg = nets.dacn_info.get("config") or {}
    cam, tgt = nets.camera.id, nets.target.id
    lines = [f"## DCDI: a {cam} capture -> the {tgt} lens's depth of field", "",
             f"Each scene through the camera lens {cam} (depth-aware aberrations and distortion, sensor noise as "
             f"in the correction network's training pairs), corrected by {_method(results, nets, cfg)}, "
             "its depth read from the capture's own blur (`dcdi depth estimate`: the camera lens's PSFs at "
             "every depth, docs/depth.md), "
             f"then the {tgt} lens's depth of field focused at {settings.focus_m:g} m rendered on the corrected "
             "image with the estimated depth (`dcdi_core.app.dof`). With a depth read from the blur, the "
             "correction is kept only where the depth's posterior expects it to bring the bokeh nearer the "
             "ideal (elsewhere the capture as it is: a depth too uncertain near the target's focus would blur a "
             "sharp image by the wrong amount; docs/depth.md). The *ideal* is the same bokeh of the "
             "true sharp frame with the true depth; the truth of the capture is the sharp frame on the same "
             "sensor (distorted alike).", ""]
    estimated = ["| scene | capture vs truth, dB | corrected vs truth, dB | "
                 f"{tgt} DoF of the uncorrected capture vs ideal, dB | the correction everywhere, dB | "
                 f"pipeline's {tgt} DoF vs ideal, dB (share corrected) | estimated depth AbsRel / delta<1.25 |",
                 "|---|---|---|---|---|---|---|"]
    for r in results:
        s = r.scores
        share = "" if r.corrected_share is None else f" ({r.corrected_share:.0%})"
        estimated.append(f"| {r.key} | {_db(s['capture_psnr'])} | {_db(s['corrected_psnr'])} | "
                         f"{_db(s['dof_uncorrected_psnr'])} | {_db(s['whole_dof_psnr'])} | {_db(s['dof_psnr'])}{share} | "
                         f"{s['depth_abs_rel']:.3f} / {s['depth_delta1']:.3f} |")
    estimated += ["", "PSNR over the imaged pixels; the depth over those whose true depth is below "
                  f"{DEPTH_SCORED_BELOW_M:g} m. The uncorrected capture's depth of field uses the same estimated "
                  "depth, so the two DoF columns differ by the correction alone.", ""]
    estimated += [f"- {verdict(r)}" for r in results]
    known = [f"| scene | corrected vs truth, dB | {tgt} DoF of the uncorrected capture vs ideal, dB | "
             f"pipeline's {tgt} DoF vs ideal, dB |", "|---|---|---|---|"]
    for r in results:
        s = r.scores
        if "true_depth_dof_psnr" in s:
            known.append(f"| {r.key} | {_db(s['true_depth_corrected_psnr'])} | "
                         f"{_db(s['true_depth_dof_uncorrected_psnr'])} | {_db(s['true_depth_dof_psnr'])} |")
    worse = [r.key for r in results if r.scores["dof_psnr"] <= r.scores["dof_uncorrected_psnr"] or r.refused]
    refused = [f"{r.key}: {r.refused}" for r in results if r.refused]
    if refused:
        lines += [f"`dcdi dof` refuses these captures' estimated depth and asks for a depth map ({'; '.join(refused)}); "
                  "the figures below are what `--uncertain-depth accept` gives.", ""]
    if worse:
        # the estimate costs more than the correction gains: say so, and lead with the chain that works
        lines += [f"**DCDI needs a depth map here.** With the depth read from the capture's own blur, the "
                  f"pipeline's {tgt} depth of field is no closer to the ideal than that of the uncorrected capture "
                  f"({', '.join(worse)}): give `dcdi dof` a depth map (`--depth`, an RGB-D camera's or a metric "
                  "estimator's). With the true depth (an RGB-D camera's) for the correction and both bokehs:", ""]
        lines += known + ["", "With the depth read from the capture's own blur:", ""] + estimated
    else:
        lines += estimated + ["", "With the true depth (an RGB-D camera's) for the correction and both bokehs:",
                              ""] + known
    lines += ["", "Pictures, one strip per scene: capture | corrected | estimated depth | true depth | "
              f"pipeline's {tgt} depth of field | ideal (depth: near bright, far dark, log scale 0.5-20 m; "
              "grey: not imaged)", ""]
    for r in results:
        lines.append(f"- `{r.picture.name}`: {r.title}")
    if factory_missing is not None:
        lines.append(f"- no factory scene: {factory_missing}")
    lines += ["", "PSF sources:", f"- capture ({cam}): {results[0].capture.psf_message}",
              f"- depth of field ({tgt}): {results[0].psf_message}"]
    notes = sorted({n for r in results for n in r.notes})
    lines += [f"- note: {n}" for n in notes]
    return lines


def verdict(r) -> str:
    """One plain sentence on what the correction did to a scene."""
    s = r.scores
    gain = s["corrected_psnr"] - s["capture_psnr"]
    dof_gain = s["dof_psnr"] - s["dof_uncorrected_psnr"]
    return (f"{r.key}: the correction {'raises' if gain > 0 else 'lowers'} the PSNR against the sharp truth by "
            f"{abs(gain):.2f} dB; the pipeline's depth of field is {abs(dof_gain):.2f} dB "
            f"{'closer to' if dof_gain > 0 else 'farther from'} the ideal than that of the uncorrected capture"
            + ("" if dof_gain > 0 else " (here no correction would have served better)")
            + f"; the estimated depth is off by {s['depth_abs_rel']:.0%} of the true depth on average (AbsRel)")


def simulation_section(scenes, results, nets: Networks, settings: ChainSettings, out: Path) -> list[str]:
    """Per scene, its simulation and its bokeh as input | depth | result
    pictures, from the chain's own results."""
    from ..render.pictures import side_by_side

    cam, tgt = nets.camera.id, nets.target.id
    lines = ["## Simulation and bokeh", ""]
    for scene, r in zip(scenes, results):
        sim, bk = f"simulate_{cam}_{scene.key}.png", f"bokeh_{tgt}_{scene.key}.png"
        side_by_side(out / sim, scene.aif, scene.depth_m, r.capture.image,
                     f"{scene.key}: {cam} depth-aware aberration simulation (with its distortion and sensor noise)")
        side_by_side(out / bk, r.capture.truth, r.capture.depth_m, r.ideal,
                     f"{scene.key}: {tgt} lens focused at {settings.focus_m:g} m (occlusion-aware)")
        lines += [f"- `{sim}`: the {scene.key} scene all in focus, its depth and its {cam} capture",
                  f"- `{bk}`: its sharp frame on the sensor, its depth and the {tgt} lens's bokeh of it "
                  "(the ideal above)"]
    return lines
