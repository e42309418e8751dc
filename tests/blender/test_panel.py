"""The Lens Bokeh panel as Blender 5.x draws it (a window under Xvfb), in the
3D view's sidebar and in Properties > Camera: readable by an artist.

tests/blender/inside/ui_panel.py records what the panel's drawing asked
Blender for (each text, icon, whether properties were split, the region's
width and each text's width in the UI font); here each text is checked to
fit the width Blender gives it, by the widths measured on Blender 5.2.2's
screen (below), and to say what it should: switches with their names, one
readout per lens (the traced one), lenses by name, no file paths or ids,
texts wrapped at whole words, the Kept Sharp heading, a status that
describes the settings as they are, tooltips without optics jargon. The
screen is captured too (OUT/sidebar.png, OUT/addon-panel.png: the picture
in docs/addon.md)."""
import re

import pytest

# the fixtures by import: a conftest.py here would shadow tests/conftest.py's helpers
from realblender_support import ROOT, addon_zip, blender, run_inside  # noqa: F401

pytestmark = pytest.mark.realblender

# Widths at UI scale 1, measured on the captured screen of Blender 5.2.2 (Debian's, Xvfb): what of a
# region's width a panel's layout gets (the sidebar: 236 of 292 px at scale 1.04, its tabs included;
# Properties: 219 of 252), what a box takes of it, an icon before a label's text (with its gap), a checkbox,
# an icon button in a row, a dropdown's arrow; the thumbnail and its gap in the lens's box; the part of a
# split layout the property's name gets (Blender's 0.4).
PANEL_MARGIN = {"VIEW_3D": 54.0, "PROPERTIES": 32.0}
BOX = 20.0
LABEL_ICON = 28.0
CHECKBOX = 20.0
ICON_BUTTON = 20.0
ARROW = 16.0
PADDING = 6.0
THUMBNAIL = 73.0
SPLIT = 0.4
SLACK_PX = 1.0           # blf's widths are fractional

LENS_IDS = tuple(sorted(p.stem for p in (ROOT / "lenses").glob("*.toml")))     # the paper's four and the catalogue
ABSOLUTE_PATH = re.compile(r"(?:^|[\s\"'(])(?:/[\w.+-]+){2,}|[A-Za-z]:\\")


@pytest.fixture(scope="module")
def panel_run(blender, addon_zip, tmp_path_factory):
    work = tmp_path_factory.mktemp("ui-panel")
    return work, run_inside(blender, "ui_panel.py", work, {"zip": str(addon_zip)}, ui=True)


def _items(node, width, scale, out, space):
    """(item, width it gets in px) of every label, button and property under ``node``."""
    kind = node["kind"]
    if kind == "box":
        width -= BOX * scale
    children = node["items"]
    if kind == "row" and children:
        fixed = [c for c in children if c.get("kind") in ("operator", "prop") and c.get("text") == ""
                 and c.get("icon", "NONE") != "NONE"]
        icon = [c for c in children if c.get("kind") == "icon"]
        rest = len(children) - len(fixed) - len(icon)
        share = (width - len(fixed) * ICON_BUTTON * scale - len(icon) * THUMBNAIL * scale) / max(rest, 1)
        widths = [ICON_BUTTON * scale if c in fixed else THUMBNAIL * scale if c in icon else share
                  for c in children]
    else:
        widths = [width] * len(children)
    for c, w in zip(children, widths):
        if "items" in c:
            _items(c, w, scale, out, space)
        else:
            out.append((c, w))
    return out


def drawn(state) -> list:
    """[(space, item, width px, scale)] of a recorded state, both panels."""
    out = []
    for space, d in state.items():
        scale = d["ui_scale"]
        width = d["region_width"] - PANEL_MARGIN[space] * scale
        out += [(space, item, w, scale) for item, w in _items(d["tree"], width, scale, [], space)]
    return out


def needed(item, scale) -> list[tuple[str, float, float]]:
    """(text, px it needs, fraction of the width it gets) of each text an item shows."""
    t, px = item.get("text", ""), item.get("px", 0.0)
    icon = item.get("icon", "NONE") not in ("NONE", "")
    if item["kind"] == "label":
        return [(t, px + (LABEL_ICON * scale if icon else 0), 1.0)] if t else []
    if item["kind"] == "operator":
        return [(t, px + (ICON_BUTTON * scale if icon else 0) + 2 * PADDING * scale, 1.0)] if t else []
    if item["kind"] != "prop" or item.get("slider"):
        return []
    out = []
    if item["type"] == "BOOLEAN":
        if item["split"] and not icon:                  # a checkbox, its name in the right part
            out.append((t, px + CHECKBOX * scale, 1 - SPLIT))
        elif item["split"]:                             # the name in the left part (the button an icon alone)
            out.append((t, px + PADDING * scale, SPLIT))
        else:
            out.append((t, px + (ICON_BUTTON if icon or item["toggle"] else CHECKBOX) * scale
                        + PADDING * scale, 1.0))
        return [x for x in out if x[0]]
    if item["split"] and t:
        out.append((t, px + PADDING * scale, SPLIT))
    part = 1 - SPLIT if item["split"] and t else 1.0
    if "value" in item:                                 # a dropdown: its item's name, an icon, the arrow
        icon_px = ICON_BUTTON * scale if item["prop"] == "lens" else 0.0
        out.append((item["value"], item["value_px"] + icon_px + (ARROW + PADDING) * scale, part))
    for v, v_px in zip(item.get("values", []), item.get("values_px", [])):
        out.append((v, v_px + PADDING * scale, part))
    return out


def labels(state, space=None) -> list[str]:
    return [i["text"] for sp, i, _, _ in drawn(state) if i["kind"] == "label" and space in (None, sp)]


def props(state, name) -> list[dict]:
    return [i for _, i, _, _ in drawn(state) if i["kind"] == "prop" and i["prop"] == name]


def test_every_text_fits_the_width_blender_gives_it(panel_run):
    """Nothing the panel shows is shortened by Blender ("Preview in Vie...",
    "Correction M...", a lens's name in its box): checked in every recorded
    state, in the sidebar and in Properties."""
    _, res = panel_run
    cut = []
    for name, state in res["states"].items():
        for space, item, width, scale in drawn(state):
            for text, px, part in needed(item, scale):
                if px > width * part + SLACK_PX:
                    cut.append(f"{name} / {space}: {text!r} needs {px:.0f} px, gets {width * part:.0f}")
    assert cut == []


def test_switches_show_their_names(panel_run):
    """Preview in Viewport, Lens in Renders and Lock Interface: a button with
    its name (a split layout with an icon would draw the button as the icon
    alone, its name shortened beside it)."""
    _, res = panel_run
    state = res["states"]["renders, network, no focus object"]
    for name, want in (("viewport_preview", "Preview in Viewport"), ("lens_in_renders", "Lens in Renders"),
                       ("use_lock_interface", "Lock Interface")):
        shown = props(state, name)
        assert len(shown) == 2, (name, shown)                       # in both panels
        for p in shown:
            assert p["text"] == want, p
            assert not (p["split"] and p["icon"] != "NONE"), f"{want} drawn as an icon alone: {p}"


def _traced(lens_id):
    from dcdi_core.optics import paraxial
    from dcdi_core.optics.lens import Lens
    lens = Lens.from_toml(ROOT / "lenses" / f"{lens_id}.toml")
    fo = paraxial.first_order(lens)
    return lens, float(fo.effective_focal_length_mm), float(fo.f_number)


def test_one_readout_per_lens_the_traced_one(panel_run):
    """Each lens's box shows its focal length and F-number once, as its
    prescription traces; the figures its source states (the 6P's F/1.8,
    f = 26.44 mm) only in the list's tooltip, said to be the source's."""
    _, res = panel_run
    for lens_id in LENS_IDS:
        lens, efl, fno = _traced(lens_id)
        texts = labels(res["states"][f"lens {lens_id}"], "VIEW_3D")
        figures = [t for t in texts if re.search(r"\bF/\d", t)]
        assert len(figures) == 1, (lens_id, texts)
        assert f"f = {efl:.2f} mm" in figures[0] and f"F/{fno:.2f}" in figures[0], (lens_id, figures)
        stated = lens.stated or {}
        if "f_number" in stated and f"{stated['f_number']:.2f}" != f"{fno:.2f}":
            assert not any(re.search(rf"F/{stated['f_number']}(?!\d)", t) for t in texts), (lens_id, texts)
    tips = {i["id"]: i["description"] for i in res["lens_items"]}
    assert "F/1.8" in tips["6p"] and "as its source states" in tips["6p"], tips["6p"]


def test_the_lens_list_shows_whole_names(panel_run):
    """The list's items are the lenses' names (not ids), without the stated
    figures, whole, and short enough for the list's field: each fits the
    dropdown in both panels (the fit test measures it)."""
    _, res = panel_run
    items = {i["id"]: i["name"] for i in res["lens_items"]}
    assert set(items) == set(LENS_IDS)
    for lens_id, name in items.items():
        assert name != lens_id and "F/" not in name and " mm" not in name, items
        assert not name.endswith(("...", "\N{HORIZONTAL ELLIPSIS}")), items
    assert items["mos-s1"].startswith("MOS-S1") and items["mos-s2"].startswith("MOS-S2"), items
    for lens_id in LENS_IDS:
        for p in props(res["states"][f"lens {lens_id}"], "lens"):
            assert p["value"] == items[lens_id]


def test_no_path_and_no_id_is_shown(panel_run):
    """No text of the panel shows an absolute path (the PSF source says
    "shipped", a file goes by its name) or a lens id where the lens has a
    name; the one exception is the command that installs PyTorch, which
    must name Blender's Python to be run."""
    _, res = panel_run
    for name, state in res["states"].items():
        for space, item, _, _ in drawn(state):
            for text, _, _ in needed(item, 1.0):
                assert not ABSOLUTE_PATH.search(text) or "-m pip" in text, (name, space, text)
                assert not any(re.search(rf"(?<![\w.-]){re.escape(i)}(?![\w.-])", text) for i in LENS_IDS), \
                    (name, space, text)
    source = res["after_apply"]["psf_source"]
    assert source and not ABSOLUTE_PATH.search(source) and "ships with the add-on" in source, source


def _wrapped_groups(state, space):
    """The texts drawn over several labels: each a first label and the
    labels after it that carry the blank icon (or, without an icon, the
    labels of one column)."""
    groups = []

    def walk(node):
        labs = [i for i in node["items"] if i.get("kind") == "label"]
        if len(labs) > 1 and len(labs) == len(node["items"]):
            groups.append([i["text"] for i in labs])
        for c in node["items"]:
            if "items" in c:
                walk(c)
    walk(state[space]["tree"])
    return groups


def test_the_blur_line_speaks_plainly_with_the_detail_as_its_tooltip(panel_run):
    """After Apply the panel says where the blur came from in one short line
    of an artist's words; the engine's message is
    its tooltip (an operator's description), which a click copies."""
    _, res = panel_run
    source = res["after_apply"]["psf_source"]
    assert source.startswith("PSFs"), source
    for space in ("VIEW_3D", "PROPERTIES"):
        ops = [i for _, i, _, _ in drawn({space: res["states"]["after apply"][space]})
               if i["kind"] == "operator" and i["op"] == "dcdi.status_detail"]
        assert len(ops) == 1 and ops[0]["text"].startswith("Blur from the "), ops
        assert not [t for t in labels(res["states"]["after apply"]) if t.startswith("PSFs")]


def test_texts_wrap_at_whole_words(panel_run):
    """The sharp range's error and the warnings are wrapped between words:
    the lines hold the message's words, whole, in order."""
    _, res = panel_run
    for space in ("VIEW_3D", "PROPERTIES"):
        warn = res["states"]["renders, network, no focus object"]
        groups = _wrapped_groups(warn, space)
        lock = next(g for g in groups if g[0].startswith("Turn Lock Interface on"))
        assert " ".join(lock).split() == ("Turn Lock Interface on: the lens reads the scene while Blender renders "
                                          "(F12 in the window; command-line renders do not need it)").split(), lock
    for text, lines in res["wrapped"].items():
        assert " ".join(lines).split() == text.split(), lines


def test_kept_sharp_has_its_heading(panel_run):
    """"Kept Sharp" shows above In Front and Behind (a column's heading
    would show only before a checkbox)."""
    _, res = panel_run
    for space, d in res["states"]["6p"].items():
        flat = [i for _, i, _, _ in drawn({space: d})]
        at = next(k for k, i in enumerate(flat) if i["kind"] == "prop" and i["prop"] == "keep_front")
        assert flat[at - 1]["kind"] == "label" and flat[at - 1]["text"] == "Kept Sharp", flat[at - 1]
        assert [flat[at]["text"], flat[at + 1]["text"]] == ["In Front", "Behind"]


def test_the_status_describes_the_settings_as_they_are(panel_run):
    """After Apply Lens Bokeh (as a click runs it) the panel says which job
    did what and where its PSFs came from; once a setting changes it says
    nothing of that run (it would describe another result), and the next
    job's status replaces it."""
    _, res = panel_run

    def status_texts(state):
        return [t for t in labels(state) if "done in" in t or t.startswith("PSFs")]
    after = status_texts(res["states"]["after apply"])
    assert any(t.startswith("Lens Bokeh: done in") for t in after), after
    assert status_texts(res["states"]["after focus change"]) == []
    assert res["focus_back"]["lines"] and res["focus_back"]["lines"][0][0].startswith("Lens Bokeh: done in")
    assert res["second_started"] == ["RUNNING_MODAL"] and res["second_running"]["running"]
    assert res["second_running"]["psf_source"] == ""                 # the last job's source is gone
    # the second job: MOS-S1 refocused, served by its focus stack
    assert res["after_second"]["psf_source"].startswith("PSFs from the PSF basis") and \
        "a focus stack" in res["after_second"]["psf_source"], res["after_second"]


def test_tooltips_speak_plainly(panel_run):
    """No setting's or operator's tooltip speaks of a lens's vertex; the focus
    distance says where it is measured from in an artist's words."""
    _, res = panel_run
    tips = res["tooltips"]
    assert [k for k, t in tips.items() if "vertex" in t.lower()] == []
    assert "from the camera" in tips["DCDI_LensBokehSettings.focus_distance"]


def test_the_panel_is_captured(panel_run):
    """The screenshots exist; the docs' picture (the sidebar, its two halves) stays small."""
    work, res = panel_run
    for key in ("screen", "sidebar", "properties", "docs_image"):
        assert (work / res[key]).stat().st_size > 10_000, key
    assert (work / res["docs_image"]).stat().st_size < 300_000
    print(f"the panel's screenshots: {work}")           # pytest -s shows where (kept as pytest keeps tmp folders)


def test_the_drawn_panel_starts_the_preview_worker_warm(panel_run):
    """With the panel drawn and the preview off, the render worker starts
    ahead of the toggle and bakes the scene's view-transform table there,
    so that the toggle's first picture waits for neither."""
    _, res = panel_run
    warm = res["warm"]
    assert warm["alive"] and warm["waited_s"] is not None and warm["table"], warm
    assert warm["preview_on"] is False, warm
