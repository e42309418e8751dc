"""Batch jobs and developer tools beside the add-on, not part of it (left
out of the extension zip as a whole by ``build.py``): they need the
repository (``scenes/``, OpenImageIO, a Blender binary).

- ``factory``: the dataset factory (``python -m blender_addon.factory``
  or ``blender --background --python blender_addon/factory/batch.py -- ...``);
- ``merge_shards``: one data set from the factory's shard folders
  (``python -m blender_addon.factory merge ...``); ``cluster/``: the
  Slurm array script and Kubernetes indexed Job that make them;
- ``render_noise``: the render error-against-time table the factory's
  defaults come from;
- ``depth_histogram``: how the factory's scenes spread over depth;
- ``screenshots``: the README's screenshots of the add-on in a real Blender UI;
- ``defocus_node``: the compositor's Defocus node (Z buffer) on an RGB-D image
  with the thin lens of a prescription, headless and timed (the comparison
  row of ``python build.py bench render``).
"""
