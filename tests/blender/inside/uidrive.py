"""Driving Blender's UI as a user does, with real X input (xdotool: pointer
moves, clicks, wheel, keys) on the virtual screen; used by the UI scripts
in this folder. Blender must run without --enable-event-simulate (that
mode ignores real input).

Widgets have no positions in Blender's Python API, so they are found by
hovering: over each probed point ``Ctrl+Shift+C`` (Copy Data Path) puts
the hovered property's path on the clipboard; the points where a path
appears are that widget's. Every function that waits is a sub-generator
(``yield from``): the window's event loop runs between the yields."""
import subprocess

import bpy

STEP_S = 0.04        # the event loop's turn between an input and the next


def _xdo(*args: str) -> None:
    subprocess.run(["xdotool", *args], check=True, timeout=30)


def screen_xy(win, x: float, y: float) -> tuple[int, int]:
    """Window coordinates (bottom-left origin) -> screen pixels (top-left)."""
    return int(round(win.x + x)), int(round(win.height + win.y - y))


def hover(win, x, y):
    _xdo("mousemove", *map(str, screen_xy(win, x, y)))
    yield STEP_S


def scan(win, region, x_fraction: float = 0.7, step: int = 6) -> dict:
    """A sub-generator: {data path: [(x, y) window coordinates, top to
    bottom]} of the properties under a vertical line through ``region``."""
    found: dict = {}
    x = region.x + region.width * x_fraction
    for y in range(region.y + region.height - step, region.y + step, -step):
        path = yield from path_at(win, x, y)
        if path:
            found.setdefault(path, []).append((x, y))
    return found


def path_at(win, x, y):
    """A sub-generator: the data path of the property under (x, y), or ''."""
    wm = bpy.context.window_manager
    wm.clipboard = ""
    yield from hover(win, x, y)
    _xdo("key", "ctrl+shift+c")
    yield STEP_S
    return wm.clipboard


def click(win, x, y, button: int = 1):
    yield from hover(win, x, y)
    _xdo("click", str(button))
    yield STEP_S


def ctrl_wheel(win, x, y, down: bool = True):
    """Ctrl + wheel over a field: the next (or previous) item of an enum, a step of a number."""
    yield from hover(win, x, y)
    _xdo("keydown", "ctrl", "click", "5" if down else "4", "keyup", "ctrl")
    yield STEP_S


def type_value(win, x, y, text: str):
    """Click a number field (it opens for typing), replace its text, Return."""
    yield from click(win, x, y)
    _xdo("key", "ctrl+a")
    _xdo("type", "--delay", "20", text)
    _xdo("key", "Return")
    yield STEP_S


def keys(win, x, y, *names: str):
    """Keys pressed with the pointer at (x, y) (a 3D view's shortcuts act where the pointer is)."""
    yield from hover(win, x, y)
    for k in names:
        _xdo("key", k)
        yield STEP_S
