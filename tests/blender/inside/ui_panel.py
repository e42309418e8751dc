"""Run with a window (xvfb-run) by tests/blender/test_panel.py: the Lens
Bokeh panel as Blender draws it, in the 3D view's sidebar (tab "Lens
Bokeh") and in Properties > Camera, read back for the driver to judge.

Blender's Python cannot read a drawn layout's texts back, so the panel's
drawing function is wrapped: its layout becomes a recorder that forwards
every call to Blender's layout (the panel is drawn as always) and keeps a
tree of what was asked for (rows, columns, boxes, whether properties are
split, each label's, button's and property's text and icon, an enum's shown
item), with the region's width, the UI scale and each text's width in the
UI font (blf), so that the driver can tell what fits. Recorded in several
states: the 6P with its thumbnail; every lens of the list; Lens in Renders
on with Lock Interface off; a focus object missing; Network chosen; an
Apply Lens Bokeh run as a click runs it (its status and PSF source), then
the focus changed, then a new job started. The screen is captured
(ImageMagick's ``import -window root``) and the sidebar cropped from it.

Arguments (DCDI_TEST_ARGS): zip, out.
"""
import importlib
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import ARGS, MODULE, OUT, RESULT, build_scene, install, run_steps, wait_until  # noqa: E402
import uidrive  # noqa: E402

import blf  # noqa: E402
import bpy  # noqa: E402

scene, cam, cube = build_scene()
scene.render.resolution_x, scene.render.resolution_y = 1920, 1080
RESULT["install"], RESULT["install_s"] = install(ARGS["zip"])
panel = importlib.import_module(f"{MODULE}.panel")
logic = importlib.import_module(f"{MODULE}.logic")
reading = importlib.import_module(f"{MODULE}.reading")
thumbnails = importlib.import_module(f"{MODULE}.thumbnails")
SESSION = importlib.import_module(f"{MODULE}.session").SESSION
viewport = importlib.import_module(f"{MODULE}.viewport")
s = scene.dcdi_lens_bokeh
s.lens = "6p"
s.focus_mode = "DISTANCE"
s.focus_distance = 2.0
s.preview_size = 160
s.samples = 2
T0 = time.perf_counter()
ctx = bpy.context
win = ctx.window_manager.windows[0]
status = ctx.window_manager.dcdi_lens_bokeh_status
PREFS = ctx.preferences


def text_px(text: str) -> float:
    """The width of ``text`` in the UI font at the UI's scale, pixels."""
    blf.size(0, PREFS.ui_styles[0].widget.points * PREFS.system.ui_scale)
    return round(blf.dimensions(0, text)[0], 1)


# ------------------------------------------------------------------ the recorder
class Recorder:
    """A UILayout that forwards every call to Blender's and records it in ``node``."""

    def __init__(self, real, node):
        object.__setattr__(self, "_real", real)
        object.__setattr__(self, "_node", node)

    def __getattr__(self, name):
        return getattr(self._real, name)

    def __setattr__(self, name, value):
        setattr(self._real, name, value)
        self._node[name] = value

    def _child(self, kind, *a, **k):
        real = getattr(self._real, kind)(*a, **k)
        node = {"kind": kind, "use_property_split": self._node["use_property_split"], "items": [],
                "heading": k.get("heading", ""), "factor": k.get("factor")}
        self._node["items"].append(node)
        return Recorder(real, node)

    def row(self, *a, **k):
        return self._child("row", *a, **k)

    def column(self, *a, **k):
        return self._child("column", *a, **k)

    def box(self, *a, **k):
        return self._child("box", *a, **k)

    def split(self, *a, **k):
        return self._child("split", *a, **k)

    def label(self, text="", icon="NONE", **k):
        self._real.label(text=text, icon=icon, **k)
        self._node["items"].append({"kind": "label", "text": text, "icon": icon, "px": text_px(text)})

    def prop(self, data, name, **k):
        self._real.prop(data, name, **k)
        rna = data.bl_rna.properties[name]
        text = k.get("text", rna.name)
        item = {"kind": "prop", "prop": name, "type": rna.type, "text": text, "px": text_px(text),
                "icon": k.get("icon", "NONE"), "toggle": k.get("toggle", False), "expand": k.get("expand", False),
                "slider": k.get("slider", False), "split": self._node["use_property_split"]}
        if rna.type == "ENUM" and not k.get("expand"):
            shown = bpy.types.UILayout.enum_item_name(data, name, getattr(data, name))
            item.update(value=shown, value_px=text_px(shown))
        if rna.type == "ENUM" and k.get("expand"):
            names = [e.name for e in rna.enum_items]
            item.update(values=names, values_px=[text_px(n) for n in names])
        self._node["items"].append(item)

    def operator(self, idname, **k):
        op = self._real.operator(idname, **k)
        cat, name = idname.split(".")
        label = getattr(getattr(bpy.ops, cat), name).get_rna_type().name
        text = k.get("text", label)
        self._node["items"].append({"kind": "operator", "op": idname, "text": text, "px": text_px(text),
                                    "icon": k.get("icon", "NONE")})
        return op

    def template_icon(self, **k):
        self._real.template_icon(**k)
        self._node["items"].append({"kind": "icon", "scale": k.get("scale", 1.0)})


DRAWN: dict = {}
_draw = panel.draw_lens_bokeh


def recording_draw(layout, context, in_viewport: bool = True):
    node = {"kind": "panel", "use_property_split": False, "items": []}
    region = context.region
    DRAWN[context.area.type] = {"region_width": region.width, "ui_scale": PREFS.system.ui_scale,
                                "char_px": text_px("x"), "tree": node}
    _draw(Recorder(layout, node), context, in_viewport=in_viewport)


panel.draw_lens_bokeh = recording_draw          # the panel classes call the module's function when they draw


def areas():
    view = max((a for a in win.screen.areas if a.type == "VIEW_3D"), key=lambda a: a.width)
    props = next((a for a in win.screen.areas if a.type == "PROPERTIES"), None)
    return view, props


def redraw():
    """A sub-generator: both panels drawn anew (the recorder keeps what they drew)."""
    DRAWN.clear()
    shown = [a for a in areas() if a is not None]
    for a in shown:
        a.tag_redraw()
    yield from wait_until(lambda: len(DRAWN) == len(shown), 10)
    yield 0.2


def record(name: str):
    """A sub-generator: the panels as drawn now, kept as state ``name``."""
    print(f"ui_panel: {time.perf_counter() - T0:.1f} s: {name}", flush=True)
    yield from redraw()
    RESULT.setdefault("states", {})[name] = {k: v for k, v in DRAWN.items()}


def texts_of(fn, *a):
    """What one of the panel's text functions makes here, or the error (an add-on without it)."""
    try:
        return fn(*a)
    except Exception as e:            # an older add-on: the driver reports it
        return f"error: {e!r}"


def screenshot(name: str, crop=None) -> str:
    """The screen (or the ``crop`` box: x, y, w, h, screen pixels) as OUT/<name>.png."""
    args = ["import", "-window", "root"]
    if crop:
        x, y, w, h = crop
        args += ["-crop", f"{w}x{h}+{x}+{y}", "+repage"]
    subprocess.run([*args, str(OUT / f"{name}.png")], check=True, timeout=60)
    return f"{name}.png"


def region_box(area, kind="UI"):
    """(x, y, w, h) of ``area``'s region of ``kind`` on the screen (top-left origin)."""
    r = next(r for r in area.regions if r.type == kind)
    top = win.y + win.height
    return [win.x + r.x, top - (r.y + r.height), r.width, r.height]


def apply_as_a_click():
    """Apply Lens Bokeh invoked as its button does (a worker, a modal timer)."""
    view, _ = areas()
    region = next(r for r in view.regions if r.type == "WINDOW")
    with ctx.temp_override(window=win, area=view, region=region):
        return sorted(bpy.ops.dcdi.apply_lens_bokeh("INVOKE_DEFAULT"))


def status_now() -> dict:
    lines = texts_of(panel.status_lines, ctx) if hasattr(panel, "status_lines") else None
    return {"message": status.message, "psf_source": status.psf_source, "running": status.running,
            "lines": lines}


def sidebar_tab(view):
    """A sub-generator: the 3D view's sidebar on the tab "Lens Bokeh" (the
    region's active tab is read-only in Python: Ctrl + wheel over the
    sidebar steps through its tabs, as a user may)."""
    view.spaces.active.show_region_ui = True
    yield 0.3
    ui = next(r for r in view.regions if r.type == "UI")
    for _ in range(12):
        if ui.active_panel_category == "Lens Bokeh":
            break
        # over the tabs' strip at the region's right edge (over a number field Ctrl + wheel changes its value)
        yield from uidrive.ctrl_wheel(win, ui.x + ui.width - 10, ui.y + ui.height - 60)
        yield 0.2
    return ui.active_panel_category


def steps():
    view, props = areas()
    sp = view.spaces.active
    sp.show_region_toolbar = False
    # the results show in an Image Editor (the timeline's area), not in a new window over the panels
    timeline = min((a for a in win.screen.areas if a.type in ("DOPESHEET_EDITOR", "TIMELINE")),
                   key=lambda a: a.y, default=None)
    if timeline is not None:
        timeline.type = "IMAGE_EDITOR"
    bpy.ops.object.select_all(action="DESELECT")
    cam.select_set(True)
    ctx.view_layer.objects.active = cam              # Properties > Camera shows the panel
    props.spaces.active.context = "DATA"
    RESULT["sidebar_category"] = yield from sidebar_tab(view)
    # the panel drawn, the preview off: the preview's render worker starts warm (viewport.warm_up)
    worker = viewport.preview().worker_renders
    waited = yield from wait_until(lambda: worker.ready.is_set(), 60.0, 0.05)
    RESULT["warm"] = {"alive": worker.alive(), "ready_s": worker.ready_s, "waited_s": waited,
                      "table": worker.warm_table is not None and worker.warm_table.key == worker.warm_key,
                      "preview_on": viewport.preview().enabled, "error": worker.error}
    # Properties scrolled down to the panel (after Lens, Depth of Field, Camera...)
    pr = next(r for r in props.regions if r.type == "WINDOW")
    yield from uidrive.hover(win, pr.x + pr.width / 2, pr.y + pr.height / 2)
    uidrive._xdo("click", "--repeat", "40", "--delay", "10", "5")
    yield 0.5

    # the tooltips: every setting's and every operator's of the add-on
    RESULT["tooltips"] = {f"{owner.__name__}.{p.identifier}": p.description
                          for owner in (type(s), type(status)) for p in owner.bl_rna.properties
                          if p.identifier != "rna_type"}
    RESULT["tooltips"].update({f"dcdi.{name}": getattr(bpy.ops.dcdi, name).get_rna_type().description
                               for name in dir(bpy.ops.dcdi)})

    # every lens's thumbnail made (the list's icons), then the 6P as a user first sees it
    for e in reading.catalogue():
        thumbnails.icon(e)
    yield from wait_until(lambda: all(thumbnails.icon(e) for e in reading.catalogue()), 60)
    yield from record("6p")
    RESULT["lens_items"] = []
    for e in reading.catalogue():
        s.lens = e.id
        yield from record(f"lens {e.id}")
        RESULT["lens_items"].append({"id": e.id, "name": bpy.types.UILayout.enum_item_name(s, "lens", e.id),
                                     "description": bpy.types.UILayout.enum_item_description(s, "lens", e.id)})
    s.lens = "6p"

    s.lens_in_renders = True
    scene.render.use_lock_interface = False
    s.correction_method = "NETWORK"
    s.focus_mode = "OBJECT"
    s.focus_object = None
    yield from record("renders, network, no focus object")
    s.lens_in_renders = False
    scene.render.use_lock_interface = True
    s.correction_method = "AUTO"
    s.focus_mode = "DISTANCE"

    # Apply Lens Bokeh as a click runs it: its status, then the settings changed, then a new job
    RESULT["apply_started"] = apply_as_a_click()
    yield 0.2
    yield from wait_until(lambda: not status.running, 300)
    yield 0.5
    RESULT["after_apply"] = status_now()
    yield from record("after apply")
    RESULT["screen_after_apply"] = screenshot("screen-after-apply")
    RESULT["sidebar_box"] = region_box(view)
    RESULT["sidebar_after_apply"] = screenshot("sidebar-after-apply", region_box(view))

    s.focus_distance = 3.0
    yield 0.3
    RESULT["after_focus_change"] = status_now()
    yield from record("after focus change")
    s.focus_distance = 2.0
    yield 0.3
    RESULT["focus_back"] = status_now()

    s.refocus = True
    s.lens, s.focus_distance = "mos-s2", 3.3            # a traced build: long enough to see it running
    RESULT["second_started"] = apply_as_a_click()
    yield 0.2
    RESULT["second_running"] = status_now()
    yield from wait_until(lambda: not status.running, 300)
    yield 0.3
    RESULT["after_second"] = status_now()
    s.lens, s.focus_distance = "6p", 2.0

    # the wrapped texts the panel makes, at the sidebar's width
    ui = next(r for r in view.regions if r.type == "UI")
    with ctx.temp_override(window=win, area=view, region=ui):
        chars = texts_of(panel.text_chars, bpy.context) if hasattr(panel, "text_chars") else None
    RESULT["sidebar_chars"] = chars
    if chars and hasattr(panel, "wrap"):
        RESULT["wrapped"] = {t: panel.wrap(t, chars) for t in (RESULT["after_apply"]["psf_source"],
                                                              logic.torch_missing() or "",
                                                              "Turn Lock Interface on: the lens reads the scene "
                                                              "while Blender renders")}

    # the picture for docs/addon.md: the sidebar after the run, the 6P chosen, the 3D view maximized (a
    # taller sidebar: the whole panel)
    s.lens, s.focus_distance = "6p", 2.0
    RESULT["apply_again"] = apply_as_a_click()
    yield 0.2
    yield from wait_until(lambda: not status.running, 300)
    vr = next(r for r in view.regions if r.type == "WINDOW")
    yield from uidrive.hover(win, vr.x + 40, vr.y + vr.height / 2)     # no tooltip over the panels
    yield 1.0
    RESULT["screen"] = screenshot("screen")
    RESULT["properties"] = screenshot("properties", region_box(props, "WINDOW"))
    with ctx.temp_override(window=win, area=view, region=next(r for r in view.regions if r.type == "WINDOW")):
        bpy.ops.screen.screen_full_area()
    yield 0.5
    view, _ = areas()
    RESULT["sidebar_category_full"] = yield from sidebar_tab(view)
    vr = next(r for r in view.regions if r.type == "WINDOW")
    yield from uidrive.hover(win, vr.x + 40, vr.y + vr.height / 2)     # no tooltip over the panel
    yield 1.0
    yield from redraw()
    box = region_box(view)
    RESULT["sidebar"] = screenshot("sidebar", box)
    # the panel's end: the sidebar scrolled down; both halves side by side
    ui = next(r for r in view.regions if r.type == "UI")
    yield from uidrive.hover(win, ui.x + ui.width / 2, ui.y + ui.height / 2)
    uidrive._xdo("click", "--repeat", "30", "--delay", "10", "5")
    yield from uidrive.hover(win, vr.x + 40, vr.y + vr.height / 2)
    yield 1.0
    RESULT["sidebar_end"] = screenshot("sidebar-end", box)
    subprocess.run(["convert", str(OUT / "sidebar.png"), "-size", "12x1", "xc:#303030", str(OUT / "sidebar-end.png"),
                    "+append", "-strip", str(OUT / "addon-panel.png")], check=True, timeout=60)
    RESULT["docs_image"] = "addon-panel.png"


run_steps(steps())
