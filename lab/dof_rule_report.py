"""When `dcdi dof` may trust the depth read from the capture's own blur
(`python -m lab dof-rule`): the demo's chain (``demo.chain.run_chain``: a
capture with the DACN's training noise, its correction by the engine's
rule, the target lens's depth of field with the estimated depth) on many
scenes, beside the same depth of field of the uncorrected capture with the
same depth. Per scene the gain (dB against the ideal) and the estimate's
frame figures the rule can see (``app.depth``: the share of confident
tiles, the posterior's expected relative error, the mean confidence); then
how the shipped rule (``app.depth.DofDepthRule``) decides on each: it must
refuse every scene where the chain loses.

Scenes (none used to train anything): the demo's synthetic scene (seeds
0-2), photograph-like frames (dead leaves of natural-statistics textures,
``lab.depth_from_blur_report.natural``), natural-statistics planes and
plain dead leaves, 240 x 320 at the sensor's centre, at the DACN's pitch.
"""
from __future__ import annotations

import argparse
import tempfile
import time

import numpy as np

SIZE = (240, 320)


def scenes(camera, pitch_mm: float, count: int):
    from dcdi_core.demo.scenes import Scene
    from dcdi_core.render.geometry import ImageGeometry
    from dcdi_core.render.synthetic import synthetic_rgbd

    from .depth_from_blur_report import leaves, natural, natural_planes
    g = ImageGeometry.from_pixel_pitch(camera, *SIZE, pitch_mm)
    for seed in range(min(count, 3)):
        img, depth = synthetic_rgbd(*SIZE, seed=seed)
        yield Scene(f"synthetic-{seed}", "the demo's synthetic scene", img, depth, g)
    for name, make in (("natural", natural), ("natural-planes", natural_planes), ("leaves", leaves)):
        for seed in range(count):
            img, depth = make(100 + seed, *SIZE)
            yield Scene(f"{name}-{seed}", name, img, depth, g)


def study(lenses, count: int, target: str, focus_m: float):
    from dcdi_core.app.depth import DepthRequest, DofDepthRule, estimate
    from dcdi_core.demo.chain import ChainSettings, Networks, run_chain
    from dcdi_core.render.request import RenderRequest

    rule = DofDepthRule()
    rows = []
    with tempfile.TemporaryDirectory() as out:
        for lens_id in lenses:
            settings = ChainSettings(camera=lens_id, target=target, focus_m=focus_m)
            nets = Networks.load(settings)
            for scene in scenes(nets.camera, nets.pixel_pitch_mm, count):
                t = time.perf_counter()
                r = run_chain(scene, nets, settings, out, log=lambda s: None)
                g = scene.geometry
                camera = RenderRequest(nets.camera, image_pixel_pitch_mm=g.pixel_pitch_mm, axis_px=g.center_px)
                info = estimate(DepthRequest(r.capture.image, nets.camera, render=camera)).info
                s = r.scores
                gain = s["dof_psnr"] - s["dof_uncorrected_psnr"]
                whole = s["whole_dof_psnr"] - s["dof_uncorrected_psnr"]
                rows.append((lens_id, scene.key, gain, whole, s["depth_abs_rel"], info, r.corrected_share, r.refused))
                print(f"{lens_id} {scene.key}: gain {gain:+.2f} dB (whole correction {whole:+.2f}), AbsRel "
                      f"{s['depth_abs_rel']:.3f}, confident {info['confident_share']:.2f}, corrected share "
                      f"{r.corrected_share:.2f}, {'refused' if r.refused else 'runs'} "
                      f"({time.perf_counter() - t:.0f} s)", flush=True)
    return rows, rule


def report(rows, rule) -> None:
    print(f"\nThe rule (app.depth.DofDepthRule): residual {rule.residual_px:g} px, refuses below "
          f"{rule.min_share:.0%} of the frame corrected\n")
    print("| camera | scene | depth AbsRel | confident share | corrected share | DoF gain over the uncorrected "
          "capture, dB: the correction everywhere | with the rule | `dcdi dof` |")
    print("|---|---|---|---|---|---|---|---|")
    for lens_id, key, gain, whole, absrel, info, share, refused in rows:
        print(f"| {lens_id} | {key} | {absrel:.3f} | {info['confident_share']:.2f} | {share:.2f} | {whole:+.2f} | "
              f"{gain:+.2f} | {'refuses' if refused else 'runs'} |")
    gains = np.array([r[2] for r in rows])
    wholes = np.array([r[3] for r in rows])
    ran = np.array([not r[7] for r in rows])
    worst = f"{gains[ran].min():+.2f}" if ran.any() else "none"
    print(f"\n{len(rows)} scenes: the correction everywhere loses on {int((wholes <= 0).sum())} (worst "
          f"{wholes.min():+.2f} dB, mean {wholes.mean():+.2f}); with the rule it loses on {int((gains <= 0).sum())} "
          f"(worst {gains.min():+.2f} dB, mean {gains.mean():+.2f}); `dcdi dof` runs {int(ran.sum())} (worst "
          f"{worst} dB) and refuses {int((~ran).sum())}.")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m lab dof-rule", description=__doc__.split("\n\n")[0])
    p.add_argument("--lenses", nargs="+", default=["mos-s1", "mos-s2"])
    p.add_argument("--count", type=int, default=4, help="scenes of each kind (default 4)")
    p.add_argument("--target", default="6p", help="the lens whose depth of field is rendered (default 6p)")
    p.add_argument("--focus", type=float, default=1.2, help="its focus, m (default 1.2, the demo's)")
    a = p.parse_args(argv)
    rows, rule = study(a.lenses, a.count, a.target, a.focus)
    report(rows, rule)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
