"""`dcdi demo`: the engine's demo job on built-in defaults.

Written to one folder with a summary (report.md):

- DCDI, the project's main job (``demo.chain``): a MOS-S1 capture of each
  scene (depth-aware aberrations, distortion, sensor noise), corrected by the
  shipped DACN, its depth from the shipped depth network beside the true
  depth, and the 6P lens's depth of field rendered on the corrected image
  beside the ideal (the same bokeh of the true sharp frame with the true
  depth); a table of PSNRs against the truths (``dcdi_scores.json`` holds
  them all). The scenes (``demo.scenes``): the built-in synthetic RGB-D
  scene and, when ``python build.py demo`` rendered one, a dataset-factory
  sample;
- the simulation and the bokeh of the synthetic scene as input | depth |
  result pictures;
- a report for every lens in lenses/ with its spot diagrams and PSFs
  across field and depth (``demo.lenses``).

PSFs come from the lens's shipped PSF basis or the shipped Omni-Lens-Field
wherever one covers the request (``psf.sources.psf_source``),
else they are traced (and cached).
``python build.py demo`` renders the factory sample first (the Blender layer
is started from build.py: the engine never starts it) and passes its folder,
or why there is none, to ``python -m dcdi_core.demo``.
"""
from .chain import ChainSettings, run_chain
from .job import run

__all__ = ["ChainSettings", "run", "run_chain"]
