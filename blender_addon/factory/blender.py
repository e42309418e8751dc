"""Which Blender runs the factory, and what it has: refused in one line
(``factory: error: ...``, exit status 2) before any scene code runs when it
is too old or its Python lacks numpy (``check_blender``), or when it lacks
the Cycles engine (``check_cycles``); whether its Cycles can denoise
(``denoiser_available``: a distribution's build may have no
OpenImageDenoise). No numpy at import: ``batch`` checks the Blender with
it before anything else is imported."""
from __future__ import annotations

import sys

# the oldest Blender whose scene API the factory uses (check_blender says what older ones lack)
MIN_BLENDER = (5, 0, 0)


class BlenderRefused(SystemExit):
    """An unsuitable Blender or Python: exit status 2, like every refusal of
    the factory; the message is printed ("factory: error: ...") when raised."""

    def __init__(self, message: str):
        super().__init__(2)
        self.message = message

    def __str__(self):
        return self.message


def _refuse(message: str):
    print(f"factory: error: {message}", file=sys.stderr, flush=True)
    raise BlenderRefused(message)


def check_blender() -> None:
    """Refuse a Blender older than MIN_BLENDER (its scene API differs: materials
    without node trees, no image_settings.media_type, no OIDN quality) or one
    whose Python lacks numpy, in one line (BlenderRefused, exit status 2)."""
    try:
        import bpy
    except ImportError:
        _refuse("no bpy module: run it with Blender (blender --background --python "
                "blender_addon/factory/batch.py -- ...) or install the pip bpy module (see requirements.txt)")
    v = tuple(bpy.app.version)
    if v < MIN_BLENDER:
        _refuse(f"Blender {bpy.app.version_string} is too old: the factory needs Blender "
                f">= {'.'.join(map(str, MIN_BLENDER))} (Blender 5 from blender.org, or the pip bpy module "
                "of requirements.txt)")
    try:
        import numpy  # noqa: F401
    except ImportError:
        _refuse(f"this Blender's Python ({sys.executable}, {sys.version.split()[0]}) has no numpy; Blender from "
                "blender.org bundles it, a distribution's blender uses the system python3 (install its numpy "
                "package, e.g. python3-numpy)")


NO_DENOISER = "this Blender has no OpenImageDenoise"


def denoiser_available(scene=None) -> bool:
    """Whether this Blender's Cycles can denoise on the CPU: OpenImageDenoise
    is compiled in (Debian's Blender has none). The denoiser's enum is
    dynamic: its RNA lists no items to Python (``bl_rna.properties
    ['denoiser'].enum_items`` is empty with and without OpenImageDenoise), so
    the test is the assignment itself, on ``scene`` or a scratch scene."""
    import bpy
    own = scene is None
    if own:
        scene = bpy.data.scenes.new("dcdi-denoiser-probe")
    try:
        scene.cycles.denoiser = "OPENIMAGEDENOISE"
        return True
    except TypeError:                   # 'enum "OPENIMAGEDENOISE" not found in ()'
        return False
    finally:
        if own:
            bpy.data.scenes.remove(scene)


def check_cycles() -> None:
    """Refuse (InputRangeError naming --recipe) a Blender built without the
    Cycles render engine, which the Blender recipes render with."""
    import bpy

    from dcdi_core.errors import InputRangeError
    scene = bpy.data.scenes.new("dcdi-cycles-probe")
    try:
        scene.render.engine = "CYCLES"
        ok = hasattr(scene, "cycles")
    except TypeError:
        ok = False
    finally:
        bpy.data.scenes.remove(scene)
    if not ok:
        raise InputRangeError("--recipe", None, f"a Blender with the Cycles render engine (this Blender "
                                                f"{bpy.app.version_string} has none), or --recipe leaves (numpy)")

