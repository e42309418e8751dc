"""Developer tools beside the add-on, not part of it (left out of the
extension zip as a whole by ``build.py``): they need the repository
(``scenes/``, OpenImageIO, a Blender binary or the pip ``bpy``). Run each
with ``python -m blender_addon.tools.<name>``.

The dataset factory itself is ``blender_addon.factory`` (``python -m
blender_addon.factory``, its shard merge ``python -m blender_addon.factory
merge``). The tools that study the factory use its render
(``blender_addon.factory.render``) and read its folders through
``dcdi_core.dataset.factory_folder``:

- ``render_noise``: the render error-against-time table the factory's
  defaults come from;
- ``depth_histogram``: how the factory's scenes spread over depth;
- ``dataset_cost``: what a factory data set cost (seconds per sample, from
  its manifest);
- ``screenshots``: the screenshots of docs/addon.md of the add-on in a real Blender UI;
- ``addon_waits``: the add-on's waits (preview, F12, an animation), in pip bpy or a Blender binary;
- ``preview_quality``: the viewport preview's traced PSFs against the full trace (error, time);
- ``real_blender.sh``: provisions Debian's Blender with Xvfb for ``python build.py test-blender``.

The studies, and the Defocus node beside the lens bokeh (the comparison row
of ``python build.py bench render``), are the lab's (``lab/``); the shipped
networks are remade from its configs (``python -m lab reproduce NAME``).
"""
