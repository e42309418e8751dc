"""Developer tools beside the add-on, not part of it (left out of the
extension zip as a whole by ``build.py``): they need the repository
(``scenes/``, OpenImageIO, a Blender binary or the pip ``bpy``). Run each
with ``python -m blender_addon.tools.<name>``.

The dataset factory itself is ``blender_addon.factory`` (``python -m
blender_addon.factory``, its shard merge ``python -m blender_addon.factory
merge``); ``tools.factory`` is its old name, kept for one release. The
tools that study the factory use its render (``blender_addon.factory.batch``)
and read its folders through ``dcdi_core.dataset.factory_folder``:

- ``render_noise``: the render error-against-time table the factory's
  defaults come from;
- ``depth_histogram``: how the factory's scenes spread over depth;
- ``dataset_cost``: what a factory data set cost (seconds per sample, from
  its manifest);
- ``reproduce_dacn.sh``: the shipped DACN and depth networks from scratch
  (factory, DA2T pairs, study, exports);
- ``screenshots``: the screenshots of docs/addon.md of the add-on in a real Blender UI;
- ``addon_waits``: the add-on's waits (preview, F12, an animation), in pip bpy or a Blender binary;
- ``preview_quality``: the viewport preview's traced PSFs against the full trace (error, time);
- ``real_blender.sh``: provisions Debian's Blender with Xvfb for ``python build.py test-blender``;
- ``defocus_node``: the compositor's Defocus node (Z buffer) on an RGB-D image
  with the thin lens of a prescription, headless and timed (the comparison
  row of ``python build.py bench render``).
"""
