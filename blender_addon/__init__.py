"""Blender side of dcdi: the Lens Bokeh add-on (panel and Apply Lens Bokeh).
Beside it, in ``tools/`` and not in its zip: the batch jobs and developer
tools (the dataset factory, ``python -m blender_addon.factory``).

bpy only: it gathers pixels and settings from Blender, calls dcdi_core, and
puts pixels back; no optics here. Importing this package imports no bpy, so
the factory and the tests can import it anywhere; Blender calls register().
Built as an extension zip by ``python build.py addon`` (Blender 4.2+, the
engine's wheel bundled and listed in ``blender_manifest.toml``); ``bl_info``
lets Blender versions before 4.2 load the same zip as a legacy add-on once
that wheel is installed into their Python.

What the add-on holds between calls (caches, jobs, the preview, a render in
progress, the handles of what it added to Blender) is one object,
``session.SESSION``; ``unregister`` clears it in one call. The modules
import downwards only, without a cycle: ``session`` and ``logic`` (no bpy),
then ``reading`` (the scene as a job reads it) and ``bpy_render``, then
``thumbnails``, ``viewport``, ``render_hook`` and ``operators``, then
``props`` and ``panel``, then this file, the one place that registers the
classes each UI module exports (``CLASSES``).
"""

bl_info = {
    "name": "DCDI Lens Bokeh",
    "author": "dcdi contributors",
    "version": (0, 1, 0),
    "blender": (3, 4, 0),
    "location": "Properties > Camera > Lens Bokeh; 3D View > Sidebar > Lens Bokeh",
    "description": "Depth of field of real lens prescriptions (ray-traced PSFs) on a Cycles render",
    "category": "Render",
}



def _classes():
    from . import operators, panel, props
    return props.CLASSES + operators.CLASSES + panel.CLASSES


def _engine_importable() -> None:
    """The engine comes in the extension's bundled wheel (Blender 4.2+
    installs it); say what to do where it did not come."""
    import importlib
    try:
        importlib.import_module("dcdi_core.app")
    except ImportError as e:
        raise ImportError("DCDI Lens Bokeh: its engine (dcdi_core) is not installed in this Blender's Python: "
                          "Blender 4.2+ installs it from the zip's wheels/ folder; before 4.2, run <Blender's "
                          "python> -m pip install wheels/dcdi-<version>-py3-none-any.whl from the zip first "
                          f"({e})") from None


def register():
    import bpy

    _engine_importable()

    from . import props, render_hook, thumbnails
    for cls in _classes():
        bpy.utils.register_class(cls)
    props.register_properties()
    render_hook.register()
    thumbnails.register()


def unregister():
    import bpy

    from . import props
    from .session import SESSION
    SESSION.clear()          # jobs told to stop, preview and render ended, handlers removed, caches dropped
    props.unregister_properties()
    for cls in reversed(_classes()):
        bpy.utils.unregister_class(cls)
