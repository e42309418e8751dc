"""The demo's DCDI chain on one scene: a minimalist-lens capture -> its
correction and depth -> another lens's depth of field, each beside its truth.

1. capture: the scene through the camera lens (``render.simulate.
   LensSimulator``: depth-aware PSFs, its distortion), with the sensor noise
   and clipping of the correction network's training pairs (as its file
   records them), with the PSFs the source rule picks (``psf.rule``). Its truth: the sharp frame and
   the depth on the same sensor (distorted alike, NaN where nothing is
   imaged), what the network was trained to recover;
2. correction and depth: ``app.dof`` with the engine's rule (the
   deconvolution with the camera lens's own PSFs, or the shipped DACN where
   it is recorded better)
   and depth network renders the target lens's depth of field (focused at
   ``focus_m``) on the corrected image with the estimated depth;
3. the same bokeh of the uncorrected capture with the same estimated depth,
   and the *ideal*: the same bokeh of the true sharp frame with the true
   depth. All three with the same PSF source (``app.dof`` chooses it).

Scores (``ChainResult.scores``): PSNR (dB, over the imaged pixels) of the
capture and of the corrected image against the sharp truth, of both depths
of field against the ideal; AbsRel and delta1 of the estimated depth over
the pixels whose true depth is below ``DEPTH_SCORED_BELOW_M``.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InputRangeError
from .scenes import Scene

# the synthetic wall stands at 1e10 m (Blender's background value): no
# monocular estimate is scored against that
DEPTH_SCORED_BELOW_M = 100.0


@dataclass(frozen=True)
class ChainSettings:
    """The demo chain's lenses (ids in lenses/), the target lens's focus (m),
    the seed of the capture's sensor noise and the torch threads."""

    camera: str = "mos-s1"
    target: str = "6p"
    focus_m: float = 1.2
    seed: int = 0
    threads: int = 2

    def __post_init__(self):
        if isinstance(self.focus_m, bool) or not isinstance(self.focus_m, (int, float)) or not self.focus_m > 0:
            raise InputRangeError("demo focus", self.focus_m, "a distance > 0 metres (or inf)")
        for name, low in (("seed", 0), ("threads", 1)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < low:
                raise InputRangeError(f"demo {name}", v, f"an integer >= {low}")


@dataclass
class Networks:
    """The lenses and the camera lens's shipped networks, loaded once."""

    camera: object                 # optics.lens.Lens that takes the capture
    target: object                 # the lens whose depth of field is rendered
    dacn: object
    dacn_info: dict
    dacn_file: Path
    pixel_pitch_mm: float          # the pitch the DACN learned
    noise: dict | None             # add_sensor_noise's keywords, as in its training pairs
    saturate: bool                 # captures and targets clipped to [0, 1] in its training pairs

    @classmethod
    def load(cls, settings: ChainSettings) -> "Networks":
        """The shipped DACN of ``settings.camera``; refused by name before
        any work when none ships. The depth is read from each capture's own
        blur (``app.depth``), not by the shipped depth network: that one is
        recorded worse than a constant depth."""
        from ..models.dacn.correct import load_dacn
        from ..errors import ModelError
        from ..optics.lens import load_lens
        from ..app.correction_rule import shipped_lenses, shipped_model

        camera, target = load_lens(settings.camera), load_lens(settings.target)
        paths = {}
        for kind in ("dacn",):
            paths[kind] = shipped_model(kind, camera.id)
            if paths[kind] is None:
                raise ModelError(f"no shipped {kind} network for the demo's camera lens {camera.id} (shipped: "
                                 f"{', '.join(shipped_lenses(kind)) or 'none'})")
        dacn, info = load_dacn(paths["dacn"])
        meta, da2t = info.get("meta") or {}, info.get("da2t") or {}
        pitch = meta.get("pixel_pitch_mm")
        if not pitch:
            raise ModelError(f"{paths['dacn']}: no pixel_pitch_mm in its meta: the demo places its scenes at "
                             "the pitch the network learned")
        return cls(camera, target, dacn, info, paths["dacn"], float(pitch),
                   da2t.get("noise"), bool(da2t.get("saturate", False)))


@dataclass
class Capture:
    image: np.ndarray        # (H, W, 3) the camera lens's capture, noisy
    truth: np.ndarray        # (H, W, 3) the sharp frame on the same sensor
    depth_m: np.ndarray      # (H, W) true depth on the sensor (NaN: not imaged)
    psf_message: str


@dataclass
class ChainResult:
    key: str
    title: str
    capture: Capture
    corrected: np.ndarray
    depth_m: np.ndarray      # the estimated depth
    dof: np.ndarray          # the pipeline's: corrected image, estimated depth
    dof_uncorrected: np.ndarray
    ideal: np.ndarray
    psf_message: str         # the target lens's PSF source
    scores: dict
    seconds: dict
    notes: list = field(default_factory=list)
    picture: Path | None = None
    correction: dict = field(default_factory=dict)   # which method corrected, and why (pipeline.choose_correction)
    refused: str | None = None   # why `dcdi dof` refuses this capture's estimated depth (app.depth.DofDepthRule)
    corrected_share: float | None = None   # the share of the frame the rule kept the correction on


def simulate_capture(scene: Scene, nets: Networks, seed: int) -> Capture:
    """The camera lens's capture of ``scene`` and its truth (module docstring, 1)."""
    from ..psf.sources import psf_source
    from ..render.simulate import LensSimulator, SimulateOptions

    src = psf_source(nets.camera, pixel_pitch_mm=scene.geometry.pixel_pitch_mm)
    sim = LensSimulator(nets.camera, SimulateOptions(geometry=scene.geometry), library=src.library)
    r = sim(scene.aif, scene.depth_m, noise=nets.noise, seed=seed if nets.noise is not None else None)
    image, truth = r.image, r.sharp
    if nets.saturate:
        image, truth = np.clip(image, 0.0, 1.0), np.clip(truth, 0.0, 1.0)
    return Capture(image.astype(np.float32), truth.astype(np.float32), r.depth.astype(np.float32), src.message)


def chain_scores(capture: Capture, corrected, depth_m, dof, dof_uncorrected, ideal) -> dict:
    """PSNRs (dB) and depth scores of one scene (module docstring)."""
    from ..models.common.metrics import depth_scores
    from ..models.dacn.evaluate import image_scores

    truth_depth = capture.depth_m
    ideal = np.clip(ideal, 0.0, 1.0)

    def db(image, target):
        return image_scores(image, target, truth_depth)["psnr"]

    scored = np.where(truth_depth < DEPTH_SCORED_BELOW_M, truth_depth, np.nan)
    depth = depth_scores(depth_m, scored) if np.isfinite(scored).any() else {"abs_rel": math.nan, "delta1": math.nan}
    return {"capture_psnr": db(capture.image, capture.truth), "corrected_psnr": db(corrected, capture.truth),
            "dof_uncorrected_psnr": db(dof_uncorrected, ideal), "dof_psnr": db(dof, ideal),
            "depth_abs_rel": depth["abs_rel"], "depth_delta1": depth["delta1"]}


def true_depth_scores(capture: Capture, corrected, dof, dof_uncorrected, ideal) -> dict:
    """PSNRs (dB) of the chain given the true depth (no estimate)."""
    from ..models.dacn.evaluate import image_scores

    def db(image, target):
        return image_scores(image, target, capture.depth_m)["psnr"]
    ideal = np.clip(ideal, 0.0, 1.0)
    return {"true_depth_corrected_psnr": db(corrected, capture.truth), "true_depth_dof_psnr": db(dof, ideal),
            "true_depth_dof_uncorrected_psnr": db(dof_uncorrected, ideal)}


def run_chain(scene: Scene, nets: Networks, settings: ChainSettings, out: Path, log=print) -> ChainResult:
    """The chain on one scene (module docstring); writes its picture
    ``dcdi_<scene key>.png`` to ``out``: capture | corrected | estimated
    depth | true depth | the pipeline's depth of field | the ideal."""
    from ..app import BokehRequest, CorrectRequest, DofRequest, dof
    from ..models.dacn.evaluate import image_scores
    from ..render.request import RenderRequest

    seconds = {}
    t0 = time.perf_counter()
    cap = simulate_capture(scene, nets, settings.seed)
    seconds["capture"] = time.perf_counter() - t0
    log(f"  {scene.key}: {nets.camera.id} capture simulated in {seconds['capture']:.1f} s ({cap.psf_message})")
    g = scene.geometry
    # the target lens's frame lies where the camera's did, at the same pitch
    on_sensor = {"image_pixel_pitch_mm": g.pixel_pitch_mm, "axis_px": g.center_px}
    target = BokehRequest(None, None, nets.target, focus_m=settings.focus_m,
                          render=RenderRequest(nets.target, **on_sensor))
    camera = RenderRequest(nets.camera, **on_sensor)

    def chain(image, depth_m=None, corrected: bool = True):
        # the correction by the engine's rule (dcdi correct --method auto): the deconvolution with the
        # camera's own PSFs unless a shipped network is recorded better; without a depth map, the depth
        # read from the capture's own blur (`dcdi dof --depth-backend blur`), on the job's one frame
        fix = CorrectRequest(image, depth_m, nets.camera if corrected else None, render=camera if corrected else None)
        # the demo measures the chain whatever the depth's confidence; what `dcdi dof` would do is recorded
        return dof(DofRequest(fix, target, depth_backend="blur" if depth_m is None else None,
                              uncertain_depth="accept"))

    # the depth is the estimated one, as a user without an RGB-D camera has: from the capture's own blur
    from ..app.depth import DofDepthRule
    r = chain(cap.image)
    refused = DofDepthRule().verdict(r.corrected_share) if r.corrected_share is not None else None
    seconds.update(r.seconds)
    log(f"  {scene.key}: depth {r.seconds.get('depth', 0):.1f} s, correction {r.seconds.get('correction', 0):.1f} s, "
        f"{nets.target.id} depth of field {r.seconds.get('psfs and bokeh', 0):.1f} s ({r.bokeh.source.message})")
    t0 = time.perf_counter()
    uncorrected = chain(cap.image, r.depth_m, corrected=False).image
    whole = chain(cap.image, r.depth_m).image          # the correction everywhere (the estimate given as a map)
    ideal = chain(cap.truth, cap.depth_m, corrected=False).image
    # with the true depth (an RGB-D camera's): the correction and the bokeh both use it
    known = chain(cap.image, cap.depth_m)
    known_uncorrected = chain(cap.image, cap.depth_m, corrected=False).image
    seconds["references"] = time.perf_counter() - t0
    scores = chain_scores(cap, r.corrected, r.depth_m, r.image, uncorrected, ideal)
    scores["whole_dof_psnr"] = image_scores(whole, np.clip(ideal, 0.0, 1.0), cap.depth_m)["psnr"]
    scores.update(true_depth_scores(cap, known.corrected, known.image, known_uncorrected, ideal))
    # the correction's own result (the bokeh got it where the rule kept it: r.corrected_share)
    corrected = r.correction.image if r.correction is not None else r.corrected
    scores["corrected_psnr"] = chain_scores(cap, corrected, r.depth_m, r.image, uncorrected, ideal)["corrected_psnr"]
    result = ChainResult(scene.key, scene.title, cap, corrected, r.depth_m, r.image, uncorrected, ideal,
                         r.bokeh.source.message, scores, seconds, list(r.notes), correction=r.correction_dict(),
                         refused=refused, corrected_share=r.corrected_share)
    result.picture = write_strip(result, out)
    log(f"  {scene.key}: PSNR capture {scores['capture_psnr']:.2f} dB -> corrected {scores['corrected_psnr']:.2f} dB; "
        f"depth of field: pipeline {scores['dof_psnr']:.2f} dB, uncorrected {scores['dof_uncorrected_psnr']:.2f} dB "
        f"against the ideal ({seconds['references']:.1f} s for those two); {result.picture.name}")
    return result


def write_strip(result: ChainResult, out: Path) -> Path:
    from ..io.images import write_image
    from ..models.dacn.evaluate import panel_strip
    from ..render.pictures import depth_panel

    path = Path(out) / f"dcdi_{result.key}.png"
    write_image(path, panel_strip([result.capture.image, result.corrected, depth_panel(result.depth_m),
                                   depth_panel(result.capture.depth_m), result.dof, result.ideal]))
    return path
