"""The first import of a headless add-on script (before bpy): the zip and
output folder from the command line, Blender's user folder inside the
output, and the modules Blender's own Python lacks made unimportable."""
import os
import sys
from pathlib import Path

BLENDERS_PYTHON_LACKS = ("OpenImageIO", "OpenEXR", "matplotlib", "torch")


def start(block=BLENDERS_PYTHON_LACKS) -> tuple[Path, Path]:
    """(ZIP, OUT) of ``script ZIP OUT ...`` (with the pip bpy module) or of
    ``blender -b --python script -- ZIP OUT ...`` (a Blender binary: then
    sys.argv becomes ``[script, ZIP, OUT, ...]``, as under Python); sets
    BLENDER_USER_RESOURCES (with pip bpy it must be set before bpy is
    imported; a binary reads it at start, so its runner sets it too) and
    blocks ``block``; hides this checkout's ``dcdi_core``."""
    if "--" in sys.argv:
        sys.argv = [sys.argv[0]] + sys.argv[sys.argv.index("--") + 1:]
    zip_path, out = Path(sys.argv[1]), Path(sys.argv[2])
    os.environ["BLENDER_USER_RESOURCES"] = str(out / "blender-user")
    # the engine must come from the extension's bundled wheel, as for a user:
    # not from this checkout (its folder, or the editable install's finder)
    root = str(Path(__file__).resolve().parents[2])
    sys.path[:] = [p for p in sys.path if p not in ("", root)]
    sys.meta_path[:] = [f for f in sys.meta_path if "__editable__" not in getattr(f, "__module__", "")]
    for name in block:
        sys.modules[name] = None
    return zip_path, out
