"""The Blender add-on: the extension zip, the engine's wheel it bundles, and (with the
pip bpy module, in a subprocess) install, Apply Lens Bokeh, settings left
as they were, error messages, disable without leftovers."""
import importlib.util
import json
import math
import os
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

import numpy as np
import pytest

from blender_addon import logic
from headless_run import run_headless
from support.build import build_module

ROOT = Path(__file__).resolve().parents[2]
EXT_ID = tomllib.loads((ROOT / "blender_addon" / "blender_manifest.toml").read_text())["id"]


@pytest.fixture(scope="module")
def addon_zip(tmp_path_factory):
    return build_module().build_addon(tmp_path_factory.mktemp("dist"))


# ------------------------------------------------------------------ the zip
WHEEL = build_module().wheel_name()


def _unpack(addon_zip, where: Path) -> tuple[Path, Path]:
    """The zip as Blender installs it: (the folder holding the add-on's
    package, the site folder its bundled wheel is extracted into)."""
    with zipfile.ZipFile(addon_zip) as z:
        z.extractall(where / "ext")
    site = where / "site"
    with zipfile.ZipFile(where / "ext" / EXT_ID / "wheels" / WHEEL) as w:
        w.extractall(site)
    return where / "ext", site


# the first lines of a subprocess that sees the unpacked zip alone: not this
# checkout (its folder, the editable install's finder), not $PYTHONPATH
_ISOLATED = """
import sys
sys.path = [p for p in sys.path if p not in ('', {root!r})]
sys.meta_path = [f for f in sys.meta_path if "__editable__" not in getattr(f, "__module__", "")]
sys.path[:0] = [{ext!r}, {site!r}]
"""


def _isolated_run(code: str, addon_zip, where: Path, **env_extra):
    ext, site = _unpack(addon_zip, where)
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "DCDI_LENS_PATH")}
    env.update(env_extra)
    head = _ISOLATED.format(root=str(ROOT), ext=str(ext), site=str(site))
    out = subprocess.run([sys.executable, "-c", head + code.format(ext=EXT_ID, site=str(site))],
                         capture_output=True, text=True, env=env, cwd=where, timeout=300)
    assert out.returncode == 0, out.stderr[-3000:]
    return out.stdout


def test_zip_is_an_extension_bundling_the_engines_wheel(addon_zip, tmp_path):
    assert EXT_ID.isidentifier() and addon_zip.name == f"{EXT_ID}-0.1.0.zip"
    with zipfile.ZipFile(addon_zip) as z:
        names = set(z.namelist())
        manifest = tomllib.loads(z.read(f"{EXT_ID}/blender_manifest.toml").decode())
        init = z.read(f"{EXT_ID}/__init__.py").decode()
        wheel = set(zipfile.ZipFile(z.open(f"{EXT_ID}/wheels/{WHEEL}")).namelist())
    assert all(n.startswith(f"{EXT_ID}/") for n in names)          # one folder: extension and legacy layout
    assert manifest["blender_version_min"] == "4.2.0" and manifest["license"] == ["SPDX:GPL-3.0-or-later"]
    assert manifest["type"] == "add-on" and manifest["tags"] and manifest["schema_version"] == "1.0.0"
    assert manifest["wheels"] == [f"./wheels/{WHEEL}"]
    assert "bl_info" in init and "def register" in init and "def unregister" in init
    for need in ("operators.py", "panel.py", "props.py", "logic.py"):
        assert f"{EXT_ID}/{need}" in names
    # no vendored copy of the engine: it comes in the wheel only
    assert not any(n.startswith((f"{EXT_ID}/dcdi_core/", f"{EXT_ID}/lenses/")) for n in names)
    assert f"{EXT_ID}/core.py" not in names
    tools = {p.name for p in (ROOT / "blender_addon" / "tools").glob("*.py")}
    assert {"render_noise.py", "depth_histogram.py", "screenshots.py"} <= tools
    assert not any(n.rsplit("/", 1)[-1] in tools - {"__init__.py"} or "/tools/" in n or "/factory/" in n
                   or "__pycache__" in n for n in names)
    # the wheel carries every shipped data file
    for data in [*(ROOT / "lenses").glob("*.toml"), *(ROOT / "dcdi_core/psf/data").rglob("*.*"),
                 *(ROOT / "dcdi_core/models/weights").glob("*.npz")]:
        name = f"dcdi_core/lenses/{data.name}" if data.suffix == ".toml" else data.relative_to(ROOT).as_posix()
        assert name in wheel, name
    again = build_module().build_addon(tmp_path)
    assert again.read_bytes() == addon_zip.read_bytes()              # same sources, same bytes


def test_unpacked_zip_runs_without_the_repository_or_image_libraries(addon_zip, tmp_path):
    code = """
for m in ("OpenImageIO", "OpenEXR", "matplotlib", "torch", "bpy", "scipy"):
    sys.modules[m] = None
from {ext} import logic
import dcdi_core
assert dcdi_core.__file__.startswith({site!r}), dcdi_core.__file__
cat = {{e.id: e.path for e in logic.lens_catalogue()}}
assert set(cat) >= {{"6p", "mos-s1", "mos-s2", "double-gauss"}}, cat
assert all(p.startswith({site!r}) for p in cat.values()), cat
ro = logic.lens_readout(cat["mos-s1"])
print(round(ro["focal_length_mm"], 3), round(ro["f_number"], 3))
"""
    assert _isolated_run(code, addon_zip, tmp_path).split() == ["19.946", "4.999"]


_IMPORT_ALL = """
import importlib, json, traceback
for m in {blocked!r}:
    sys.modules[m] = None                      # as absent as in Blender's own Python
res = {{}}
for name in {modules!r}:
    try:
        importlib.import_module(name)
        res[name] = None
    except BaseException as e:                 # noqa: BLE001 - reported by name
        res[name] = f"{{type(e).__name__}}: {{e}}"
print(json.dumps(res))
"""


def _import_all(addon_zip, where, modules, blocked):
    code = _IMPORT_ALL.format(blocked=list(blocked), modules=modules).replace("{", "{{").replace("}", "}}")
    return json.loads(_isolated_run(code, addon_zip, where).strip().splitlines()[-1])


def _modules(addon_zip) -> list[str]:
    with zipfile.ZipFile(addon_zip) as z:
        names = [n for n in z.namelist() if n.endswith(".py")]
        wheel = zipfile.ZipFile(z.open(f"{EXT_ID}/wheels/{WHEEL}"))
        names += [n for n in wheel.namelist() if n.endswith(".py") and n.startswith("dcdi_core/")]
    # (a __main__ module runs its program when imported: an entry point, not imported here)
    return sorted(n[:-3].replace("/", ".").removesuffix(".__init__") for n in names
                  if not n.endswith("/__main__.py"))


# what the add-on may not need in Blender's own Python: its bpy modules, the
# networks' torch code, the reports' plotting
_BPY_ONLY = {f"{EXT_ID}.{m}" for m in ("operators", "panel", "props", "bpy_render", "render_hook", "viewport",
                                       "thumbnails", "reading", "view_transform", "gpu_capture")}


def test_every_module_of_the_zip_imports(addon_zip, tmp_path):
    """Every module of the zip and of its wheel imports from them alone: in a
    Python like Blender's own (numpy, no torch, scipy, tqdm, OpenImageIO,
    matplotlib) only the bpy modules, the networks' torch modules and the
    reports may fail, and only for want of bpy, torch or matplotlib; every
    module the add-on imports works there; with bpy (the pip module) every
    module but those needing torch imports."""
    modules = _modules(addon_zip)
    assert len(modules) > 40 and "dcdi_core.render.simulate" in modules and f"{EXT_ID}.logic" in modules
    bare = _import_all(addon_zip, tmp_path / "bare", modules, ["bpy", "torch", "scipy", "tqdm", "OpenImageIO",
                                                                "OpenEXR", "matplotlib"])
    failed = {m: e for m, e in bare.items() if e}
    optional = {m for m in modules if m.startswith("dcdi_core.models.") and ".runtime" not in m}
    assert set(failed) <= _BPY_ONLY | optional, failed
    assert all(any(w in e for w in ("bpy", "torch", "matplotlib")) for e in failed.values()), failed
    if importlib.util.find_spec("bpy") is None:
        pytest.skip("pip bpy not installed: the bpy modules were not imported")
    blocked = [] if importlib.util.find_spec("torch") else ["torch"]
    full = _import_all(addon_zip, tmp_path / "full", modules, blocked)
    failed = {m: e for m, e in full.items() if e and not (blocked and "torch" in e)}
    assert not failed, failed


# the one module of the engine that starts the Blender layer: `dcdi-factory`, the project's command for the
# dataset factory, which runs the clone's factory as a separate process (it imports none of it)
FACTORY_LAUNCHER = ROOT / "dcdi_core" / "cli" / "factory.py"


def test_the_engine_never_imports_or_starts_the_blender_layer():
    """Imports (at any depth) and module runs (``-m blender_addon...`` as a
    string literal), not mentions: a docstring may name the factory. The
    factory's command starts it, in a process of its own, and imports
    nothing of it."""
    import ast
    for p in (ROOT / "dcdi_core").rglob("*.py"):
        tree = ast.parse(p.read_text())
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0:
                names = [node.module or ""]
            elif isinstance(node, ast.Constant) and isinstance(node.value, str):
                if p != FACTORY_LAUNCHER:
                    assert not node.value.startswith(("blender_addon.", "-m blender_addon")), (p, node.value)
                continue
            else:
                continue
            for n in names:
                assert n.split(".")[0] not in ("blender_addon", "bpy", "scenes"), (p, n)


# ------------------------------------------------------------------ logic without bpy
def test_preview_shape_keeps_the_render_aspect():
    assert logic.preview_shape(640, 480, 1.0, 1.0, 64) == (48, 64)
    assert logic.preview_shape(1080, 1920, 1.0, 1.0, 320) == (320, 180)
    assert logic.preview_shape(1000, 1000, 2.0, 1.0, 100) == (50, 100)   # anamorphic pixels
    with pytest.raises(logic.BokehInputError, match="allowed 8 and up"):
        logic.preview_shape(640, 480, 1.0, 1.0, 4)


def test_keep_range():
    # (the depth conversion is dcdi_core.render.camera's: tests/render/test_camera.py)
    assert logic.keep_range(2.0, 0.5, 1.0) == (1.5, 3.0)
    with pytest.raises(logic.BokehInputError, match="positive and finite"):
        logic.keep_range(-1.0, 0.1, 0.1)


def _detail(img):
    """Mean absolute difference of neighbouring pixels: what a blur takes away."""
    return float(np.abs(np.diff(img, axis=0)).mean() + np.abs(np.diff(img, axis=1)).mean())


def test_a_focus_on_empty_space_blurs_everything():
    # a camera may focus where nothing lies: no error, everything out of focus, and a note saying so
    from dcdi_core.optics.lens import load_lens
    # (a full-frame lens: a small sensor's 320 px hold 5 m within the depth of field of a 1.5 m focus)
    rng = np.random.default_rng(0)
    img = rng.random((240, 320, 3)).astype(np.float32)
    lens = load_lens("zeiss-sonnar-50mm-f1-5")
    out, info = logic.run_bokeh(img, np.full((240, 320), 5.0, np.float32), lens, focus_m=1.5, keep=(1.0, 2.0))
    assert info["kept_pixels"] == 0 and np.isfinite(out).all()
    assert "nothing in view is in focus: nothing lies at the kept range 1.00-2.00 m" in info["focus_note"]
    assert "the sharpest, at 5.00 m, is blurred" in info["focus_note"]
    assert "everything is out of focus" in info["focus_note"]
    assert _detail(out[16:-16, 16:-16]) < 0.5 * _detail(img[16:-16, 16:-16])       # measured: 0.12
    # in focus, the note is empty and the image stays sharp
    sharp, info2 = logic.run_bokeh(img, np.full((240, 320), 1.5, np.float32), lens, focus_m=1.5, keep=(1.0, 2.0))
    assert info2["focus_note"] == "" and info2["kept_pixels"] == 240 * 320
    assert _detail(sharp[16:-16, 16:-16]) > 0.9 * _detail(img[16:-16, 16:-16])
    # kept sharp 0 / 0 (the lens alone): a subject within the lens's depth of field is in focus, no note;
    # one far from any focus is told, with its blur
    depth = np.full((240, 320), 5.0, np.float32)
    depth[100:140, 140:180] = 1.52
    _, near = logic.run_bokeh(img, depth, lens, focus_m=1.5, keep=(1.5, 1.5))
    assert near["kept_pixels"] == 0 and near["focus_note"] == "", near["focus_note"]
    _, far = logic.run_bokeh(img, np.full((240, 320), 5.0, np.float32), lens, focus_m=1.5, keep=(1.5, 1.5))
    assert "nothing lies at the focus 1.50 m" in far["focus_note"] and "blurred" in far["focus_note"]


def test_the_preview_and_apply_plan_their_psfs_by_their_error_budgets():
    """A catalogue lens's PSFs are planned (logic.run_bokeh: the preview 30 dB
    unless the panel's Preview Quality says otherwise, Apply 40); the panel's
    default is the engine's."""
    import ast
    from dcdi_core import app
    from dcdi_core.optics.lens import load_lens
    img = np.random.default_rng(0).random((60, 90, 3)).astype(np.float32)
    depth = np.linspace(0.8, 8.0, 90, dtype=np.float32)[None].repeat(60, 0)
    lens = load_lens("zeiss-sonnar-50mm-f1-5")
    budgets = {}
    for kw in (dict(preview=True), dict(preview=False), dict(preview=True, max_error_db=70.0)):
        _, info = logic.run_bokeh(img, depth, lens, focus_m=2.0, keep=(1.9, 2.1), **kw)
        q = info["quality"]
        assert q["expected_db"] >= q["budget_db"] and "error table" in q["plan"]
        assert f"PSFs planned for {q['budget_db']:g} dB" in info["psf_source_message"]
        budgets[q["budget_db"]] = q["relative_cost"]
    assert set(budgets) == {app.DEFAULT_BUDGET_DB["preview"], app.DEFAULT_BUDGET_DB["render"], 70.0}
    assert budgets[70.0] > budgets[app.DEFAULT_BUDGET_DB["preview"]]       # a tighter budget costs more work
    props = ast.parse((Path(logic.__file__).parent / "props.py").read_text())
    default = next(k.value.value for n in ast.walk(props) if isinstance(n, ast.AnnAssign)
                   and getattr(n.target, "id", "") == "preview_quality" for k in n.annotation.keywords
                   if k.arg == "default")
    assert default == app.DEFAULT_BUDGET_DB["preview"]


# ------------------------------------------------------------------ headless Blender (pip bpy)
@pytest.fixture(scope="module")
def headless(addon_zip, tmp_path_factory):
    pytest.importorskip("bpy")
    return run_headless("addon_headless.py", addon_zip, tmp_path_factory.mktemp("addon-run"))


def test_zip_installs_into_a_temporary_user_folder_and_enables(headless):
    assert headless["install"] == ["FINISHED"] and headless["enabled"]
    # the engine is the extension's bundled wheel, installed into the user folder with it
    assert headless["engine_file"].startswith(headless["user_folder"]), headless["engine_file"]
    assert set(headless["lenses"]) == {p.stem for p in (ROOT / "lenses").glob("*.toml")}
    assert all(p.startswith(headless["user_folder"]) for p in headless["lenses"].values())
    assert headless["default_lens"] == "zeiss-sonnar-50mm-f1-5"      # a standard photographic lens


def test_match_camera_sets_the_lens_focal_length(headless):
    """With Lens Geometry the camera frames what the lens focused at the
    focus distance shows (the 6P's 14.5 % barrel at the corner: a wider
    camera); without, the scale of the lens's ideal image (its focal length
    at its prescribed sensor), which the engine reads back from the camera
    as the lens's own."""
    from dcdi_core.optics.lens import load_lens
    from dcdi_core.render.camera import framing_focal_length_mm, ideal_scale_mm
    assert headless["match_camera"] == ["FINISHED"]
    lens = load_lens("6p")
    efl, scale = headless["readout"]["focal_length_mm"], ideal_scale_mm(lens)
    assert scale == pytest.approx(efl, rel=1e-3)
    framing = framing_focal_length_mm(lens, headless["match_focus_m"], 480, 640)
    assert headless["camera_lens_mm"] == pytest.approx(framing, rel=1e-6)
    assert framing < 0.9 * efl
    assert headless["camera_lens_mm_no_geometry"] == pytest.approx(scale, rel=1e-6)
    assert headless["camera_pinhole_mm"] == pytest.approx(scale, rel=1e-6)


def test_lens_geometry_moves_the_picture_as_the_engine_does(headless):
    """Lens Geometry (off by default: the camera's framing as it stands):
    Apply is the engine's bokeh with the lens's distortion and breathing at
    the focus, the render read at the camera's focal length (Match Camera at
    the focus: the 6P's framing, 14.5 % barrel at the corner)."""
    assert headless["lens_geometry_default"] is False
    assert headless["geometry_apply"] == ["FINISHED"]
    assert headless["geometry_engine_diff"] < 1e-5
    assert headless["geometry_pinhole_mm"] < 0.9 * headless["readout"]["focal_length_mm"]
    assert headless["geometry_vs_plain"] > 0.01


def test_match_camera_keeps_the_double_gauss_field_of_view(headless):
    # its sensor (0.28 mm wide at 640 x 480) is below Blender's 1 mm minimum:
    # focal length and sensor are scaled together, the angle stays the lens's
    from dcdi_core.optics.lens import load_lens
    from dcdi_core.render.camera import PinholeCamera
    dg = headless["double_gauss_camera"]
    assert dg["match"] == ["FINISHED"] and dg["sensor_fit"] == "HORIZONTAL"
    pinhole = PinholeCamera.for_lens(load_lens("double-gauss"), 480, 640)
    true_angle = 2.0 * math.atan(pinhole.sensor_width_mm / (2.0 * pinhole.focal_length_mm))
    assert dg["angle"] == pytest.approx(true_angle, rel=1e-3)           # Blender's own angle (sensor width)
    assert dg["sensor_width"] >= 1.0 and dg["lens"] > pinhole.focal_length_mm
    diagonal = dg["sensor_width"] * math.hypot(480, 640) / 640
    assert 2.0 * math.atan(diagonal / (2.0 * dg["lens"])) == pytest.approx(
        math.radians(pinhole.diagonal_field_of_view_deg), rel=1e-3)


def test_result_equals_the_render_in_the_kept_range_and_is_blurred_outside(headless):
    assert headless["apply_cold"] == ["FINISHED"] and headless["apply_warm"] == ["FINISHED"]
    out, aif = np.load(headless["dir"] / "out.npy"), np.load(headless["dir"] / "aif.npy")
    depth = np.load(headless["dir"] / "depth.npy")[..., 0]
    assert out.shape == aif.shape == (96, 128, 3) and headless["result_float"]
    assert "linear" in headless["result_colorspace"].lower()
    f = headless["focus_m"]
    kept = (depth >= f - headless["keep_m"][0]) & (depth <= f + headless["keep_m"][1])
    assert 200 < kept.sum() < 0.8 * kept.size                         # the cube, not the whole frame
    assert np.abs(out - aif)[kept].max() < 1e-5
    # the wall (8 m) away from the cube's edge, blurred by the lens focused at 1 m: a blur
    # disc of ~2.7 px at this preview's 0.14 mm pitch (measured: mean |out - aif| 0.069,
    # edge energy 0.75 of the render's)
    near_cube = kept.copy()
    for _ in range(4):
        near_cube = near_cube | np.roll(near_cube, 1, 0) | np.roll(near_cube, -1, 0) \
            | np.roll(near_cube, 1, 1) | np.roll(near_cube, -1, 1)
    wall = (depth > 7.0) & ~near_cube
    assert wall.sum() > 1000
    assert np.abs(out - aif)[wall].mean() > 0.04

    def edge_energy(im):
        g = np.abs(np.diff(im, axis=0))[:, :-1] + np.abs(np.diff(im, axis=1))[:-1]
        return g[wall[:-1, :-1]].mean()
    assert edge_energy(out) < 0.85 * edge_energy(aif)
    # blur moves light, it does not make or lose it
    assert np.isfinite(out).all() and abs(out[wall].mean() - aif[wall].mean()) < 0.02 * aif[wall].mean()


def test_scene_render_settings_and_camera_are_as_before(headless):
    assert headless["settings_diff"] == []
    assert headless["snapshot_detects_a_change"]
    # only the result images are new: no scene, camera, object or mesh left behind
    assert headless["new_data"] == {"images": 3}
    assert headless["images"] == ["Lens Bokeh", "Lens Bokeh AiF", "Lens Bokeh Depth"]      # the new ones


def test_a_focus_on_empty_space_renders_everything_out_of_focus(headless):
    assert headless["empty_focus"] == ["FINISHED"]
    out, aif = (np.load(headless["dir"] / f"{n}.npy")[..., :3] for n in ("empty-focus", "empty-focus-aif"))
    # a small preview of a noisy render: blurred, less detail than the sharp render (measured 0.90 of it)
    assert np.isfinite(out).all() and _detail(out) < 0.95 * _detail(aif)
    assert np.abs(out - aif).mean() > 0.01


def test_what_cannot_work_says_why(headless):
    e = headless["errors"]
    assert "no active camera" in e["no_camera"]
    assert "the lens file is broken" in e["broken_lens"] and "broken-lens.toml" in e["broken_lens"]


def test_disable_leaves_nothing_registered(headless):
    assert headless["disable"] == ["FINISHED"] and not headless["still_enabled"]
    assert headless["leftovers"] == []
    assert not headless["scene_prop_left"] and not headless["wm_prop_left"] and not headless["operator_left"]


def test_disable_clears_the_session_in_one_call(headless):
    """What the add-on held (caches, the lens list, the preview and its
    handlers, the render handlers, the thumbnails) is gone after the disable."""
    before, after = headless["session_before_disable"], headless["session_after_disable"]
    assert before["handles"] == ["preview", "render", "thumbnails"] and before["preview_on"] and before["thumbnails"]
    assert all(before[k] > 0 for k in ("lens_names", "lenses", "readouts", "lens_items", "lens_folders")), before
    assert after == {"lens_names": 0, "lenses": 0, "readouts": 0, "lens_items": 0, "lens_folders": 0, "handles": [],
                     "preview_on": False, "thumbnails": False}
    assert not headless["preview_handler_left"]


def test_numpy_exr_reader_matches_openimageio(headless):
    from dcdi_core.io.images import read_depth, read_image
    from dcdi_core.io.rawexr import RawExrError, read_exr_channels
    path = headless["dir"] / "multilayer.exr"
    ch = read_exr_channels(path)
    rgb = np.stack([ch[f"ViewLayer.Combined.{c}"] for c in "RGB"], axis=-1)
    assert np.array_equal(rgb, read_image(path)) and rgb.std() > 0
    assert np.array_equal(ch["ViewLayer.Depth.Z"], read_depth(path))
    bad = headless["dir"] / "not.exr"
    bad.write_bytes(b"\x00" * 64)
    with pytest.raises(RawExrError, match="not an OpenEXR file"):
        read_exr_channels(bad)


def test_cancel_stops_the_psf_build_and_progress_is_reported(tmp_path, monkeypatch):
    from dcdi_core.optics.lens import load_lens
    from dcdi_core.psf import sources
    monkeypatch.setenv("DCDI_CACHE_DIR", str(tmp_path / "cache"))
    # traced PSFs (no focus stack of MOS-S1 to serve its refocus): what is cancelled is the trace
    monkeypatch.setattr(sources, "shipped_store", lambda lens_id, focus_stack=False: None)
    logic.SESSION.sources.clear()
    img = np.random.default_rng(0).random((24, 32, 3), dtype=np.float32)
    depth = np.full((24, 32), 8.0, np.float32)
    depth[8:16, 10:20] = 1.0
    seen = []
    with pytest.raises(logic.Cancelled):
        logic.run_bokeh(img, depth, load_lens("mos-s1"), focus_m=1.0, keep=(0.9, 1.1),
                        progress=lambda stage, f: seen.append((stage, f)), cancelled=lambda: True)
    assert seen == []                                   # stopped at the first batch, before any report
    out, info = logic.run_bokeh(img, depth, load_lens("mos-s1"), focus_m=1.0, keep=(0.9, 1.1),
                                progress=lambda stage, f: seen.append((stage, f)))
    assert [s for s, _ in seen][-1] == "depth layers" and any(s == "PSFs" for s, _ in seen)
    assert all(0.0 <= f <= 1.0 for _, f in seen)
    assert info["kept_pixels"] == 80 and np.abs(out - img)[8:16, 10:20].max() < 1e-6
    # the PSFs are cached now: a cancel after the build stops the convolution between its layers
    asked = []
    with pytest.raises(logic.Cancelled):
        logic.run_bokeh(img, depth, load_lens("mos-s1"), focus_m=1.0, keep=(0.9, 1.1),
                        cancelled=lambda: asked.append(1) or len(asked) > 1)
    assert len(asked) == 2


# ------------------------------------------------------------------ the bundled Omni-Lens-Field
_BUNDLED_OLF = """
import importlib, importlib.abc


class NoTorch(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name == "torch" or name.startswith("torch."):
            raise ImportError("torch is blocked: Blender's Python has none")
        return None


sys.meta_path.insert(0, NoTorch())
for m in ("OpenImageIO", "OpenEXR", "matplotlib", "bpy", "scipy"):
    sys.modules[m] = None
import numpy as np
from {ext} import logic
import dcdi_core
assert dcdi_core.__file__.startswith({site!r}), dcdi_core.__file__


def no_tracing(*a, **k):
    raise RuntimeError("the ray tracer was called")


for m in ("psf.library", "psf.compute"):
    setattr(importlib.import_module("dcdi_core." + m), "compute_sources", no_tracing)
lib_mod = importlib.import_module("dcdi_core.psf.sources")
assert str(lib_mod.SHIPPED).startswith({site!r}) and lib_mod.SHIPPED.exists(), lib_mod.SHIPPED
lens = logic.load_lens_cached(dict((e.id, e.path) for e in logic.lens_catalogue())["mos-s1"])
olf = importlib.import_module("dcdi_core.psf.olf").OmniLensField.load(lib_mod.SHIPPED)
k = olf.psf(lens, [0.0, 0.7], 2.0)
assert k.shape == (2, 3, 41, 41) and abs(k.sum(axis=(-1, -2)) - 1).max() < 1e-5 and k.min() >= 0
rng = np.random.default_rng(0)
img = rng.random((96, 128, 3), dtype=np.float32)
depth = np.full((96, 128), 8.0, np.float32)
depth[16:32, 20:44] = 1.0
out, info = logic.run_bokeh(img, depth, lens, focus_m=1.0, keep=(0.9, 1.1), refocus=False)
assert info["psf_source"] == "basis" and "PSF basis" in info["psf_source_message"], info["psf_source_message"]
assert np.abs(out - img)[16:32, 20:44].max() < 1e-6 and np.abs(out - img)[depth > 5].mean() > 1e-3
# refocused (Refocus Lens on): MOS-S1's focus stack serves it inside 0.7 m to infinity, nearer is traced
outr, infor = logic.run_bokeh(img, depth, lens, focus_m=1.0, keep=(0.9, 1.1))
assert infor["psf_source"] == "basis" and "a focus stack" in infor["psf_source_message"], infor["psf_source_message"]
assert np.abs(outr - img)[16:32, 20:44].max() < 1e-6 and np.abs(outr - img)[depth > 5].mean() > 1e-3
# nearer: the OLF in ray space (any focus and stop of the paper's lenses), nothing traced
_, infon = logic.run_bokeh(img, np.where(depth < 5, 0.5, depth).astype(np.float32), lens, focus_m=0.5,
                           keep=(0.45, 0.55))
assert infon["psf_source"] == "olf" and "in ray space" in infon["psf_source_message"], infon["psf_source_message"]
# the 6P, learned across focus: refocused (Refocus Lens on, the default) inside the range, served
lens6 = logic.load_lens_cached(dict((e.id, e.path) for e in logic.lens_catalogue())["6p"])
out6, info6 = logic.run_bokeh(img, depth, lens6, focus_m=1.0, keep=(0.9, 1.1))
# the PSFs of a focus within logic.FOCUS_TOLERANCE_PX of blur serve 1 m (psf.sampling), said in the message
from dcdi_core.psf import sampling
used = sampling.snap_focus(lens6, 1.0, info6["pixel_pitch_mm"], logic.FOCUS_TOLERANCE_PX)
assert info6.get("focus_used_m", 1.0) == used and 1.0 <= used <= 1.2, (used, info6)
assert info6["psf_source"] == "olf" and "focus %.3g m" % used in info6["psf_source_message"] \
    and "serve the focus at 1 m" in info6["psf_source_message"], info6["psf_source_message"]
assert np.abs(out6 - img)[16:32, 20:44].max() < 1e-6 and np.abs(out6 - img)[depth > 5].mean() > 1e-3
near = depth.copy()
near[16:32, 20:44] = 0.5
_, info6n = logic.run_bokeh(img, near, lens6, focus_m=0.5, keep=(0.45, 0.55))      # nearer than 0.7 m too
assert info6n["psf_source"] == "olf" and "in ray space" in info6n["psf_source_message"] \
    and "serve the focus at 0.5 m" in info6n["psf_source_message"], info6n
assert "torch" not in sys.modules
print("ok", info["psf_source_message"])
"""


def test_bundled_engine_serves_the_olf_with_torch_blocked(addon_zip, tmp_path):
    """The unpacked zip alone, torch blocked by an import hook: the vendored
    OLF serves kernels, and a bokeh of a shipped lens as prescribed runs
    through it with the tracer patched to raise (refocused: MOS-S1 from its
    focus stack inside 0.7 m to infinity, both lenses from the OLF in ray
    space at any focus, nearer too)."""
    out = _isolated_run(_BUNDLED_OLF, addon_zip, tmp_path, DCDI_CACHE_DIR=str(tmp_path / "cache"),
                        OMP_NUM_THREADS="1")
    assert out.startswith("ok") and "area-resampled" in out, out


def test_first_apply_on_a_shipped_lens_traces_nothing(headless):
    """Apply Lens Bokeh (the operator, headless) with Refocus Lens off, the
    tracer patched to raise: 6p and MOS-S1 at the 128 x 96 preview's pitch
    (14.4 x the stored one: the PSF basis's kernels area-resampled) finish,
    the status says the PSF basis served them, the cube is kept sharp and
    the rest is blurred."""
    aif = np.load(headless["dir"] / "aif.npy")
    depth = np.load(headless["dir"] / "depth.npy")[..., 0]
    f = headless["focus_m"]
    kept = (depth >= f - headless["keep_m"][0]) & (depth <= f + headless["keep_m"][1])
    for lens_id in ("6p", "mos-s1"):
        run = headless["olf_apply"][lens_id]
        assert run["result"] == ["FINISHED"], run
        assert run["status"].startswith("PSFs from the PSF basis"), run
        assert "area-resampled" in run["status"] and "prescribed focus" in run["status"]
        out = np.load(headless["dir"] / f"olf-{lens_id}.npy")
        assert out.shape == aif.shape and np.isfinite(out).all()
        assert np.abs(out - aif)[kept].max() < 1e-5
        assert np.abs(out - aif)[depth > 7.0].mean() > 1e-3


def test_first_apply_with_refocus_on_a_focus_lens_traces_nothing(headless):
    """Refocus Lens on (the default), the 6P focused inside the range the
    shipped OLF learned it across, the tracer patched to raise: finished,
    served by the OLF at that focus, the cube sharp, the rest blurred."""
    aif = np.load(headless["dir"] / "aif.npy")
    depth = np.load(headless["dir"] / "depth.npy")[..., 0]
    f = headless["focus_m"]
    kept = (depth >= f - headless["keep_m"][0]) & (depth <= f + headless["keep_m"][1])
    run = headless["olf_apply_refocus"]
    assert run["result"] == ["FINISHED"], run
    assert run["status"].startswith("PSFs from the Omni-Lens-Field") and "focus " in run["status"], run
    assert "prescribed focus" not in run["status"], run
    out = np.load(headless["dir"] / "olf-6p-refocus.npy")
    assert np.abs(out - aif)[kept].max() < 1e-5
    assert np.abs(out - aif)[depth > 7.0].mean() > 1e-3


def test_a_catalogue_lens_stopped_down_and_refocused_traces_nothing(headless):
    """A catalogue lens with Camera Aperture on (f/5.6, 6 blades) and
    Refocus Lens on, the tracer patched to raise: finished, served by its
    ray map (the status says so and names the iris), the far wall blurred."""
    run = headless["raymap_apply"]
    assert run["result"] == ["FINISHED"], run
    assert run["status"].startswith("PSFs from the ray map") and "f/5.6, 6 blades" in run["status"], run
    out = np.load(headless["dir"] / "raymap-tessar.npy")
    aif = np.load(headless["dir"] / "aif.npy")
    depth = np.load(headless["dir"] / "depth.npy")[..., 0]
    assert out.shape == aif.shape and np.isfinite(out).all()
    assert np.abs(out - aif)[depth > 7.0].mean() > 1e-4


def test_camera_aperture_stops_the_lens_down_to_the_cameras_f_stop(headless):
    """Camera Aperture on, the camera at f/4 with 6 blades: the 6P (matched
    wide open, f/1.64) is stopped down and served by the OLF in ray space
    (the status says its stop), the kept cube as before, the far wall less
    blurred than wide open; an F-Stop wider than the lens's leaves it wide
    open, saying so."""
    assert headless["matched_fstop"] == pytest.approx(headless["readout"]["f_number"], rel=1e-3)
    run = headless["aperture_apply"]
    assert run["iris"] == "f/4, 6 blades" and run["result"] == ["FINISHED"], run
    assert "in ray space, f/4, 6 blades" in run["status"], run["status"]
    aif = np.load(headless["dir"] / "aif.npy")
    depth = np.load(headless["dir"] / "depth.npy")[..., 0]
    f4, wide = np.load(headless["dir"] / "aperture-f4.npy"), np.load(headless["dir"] / "out.npy")
    f = headless["focus_m"]
    kept = (depth >= f - headless["keep_m"][0]) & (depth <= f + headless["keep_m"][1])
    assert np.abs(f4 - aif)[kept].max() < 1e-5
    far = depth > 7.0
    assert 1e-4 < np.abs(f4 - aif)[far].mean() < 0.7 * np.abs(wide - aif)[far].mean()
    assert headless["aperture_wide"]["iris"] == "f/1.64, 6 blades"          # wide open, its blades kept
    assert "F-Stop 1.2 is wider than this lens's widest, f/1.64" in headless["aperture_wide"]["note"]


# ------------------------------------------------------------------ the DCDI round trip in Blender
ROUND_TRIP_LENS = "mos-s2"          # the lens of test_dacn_train's tiny pairs


def test_correction_model_path_names_the_lenses_with_a_network(tmp_path, monkeypatch):
    """The choice names the network file it will run: the one given, else
    the lens's shipped one; a lens without one is refused in the engine's
    words shown as the panel's."""
    import dcdi_core.shipped as registry
    monkeypatch.setattr(registry, "WEIGHTS_DIR", tmp_path)
    monkeypatch.setattr(logic, "torch_missing", lambda: None)
    with pytest.raises(logic.BokehInputError, match="no shipped DACN for lens 6p .shipped for: none.; give "
                                                    "Correction Model"):
        logic.choose_correction("network", "6p", 0.0122)
    (tmp_path / "dacn-mos-s1.npz").write_bytes(b"")
    (tmp_path / "dacn-mos-s2.npz").write_bytes(b"")
    assert logic.choose_correction("network", "mos-s1", 0.0122).model_path == tmp_path / "dacn-mos-s1.npz"
    with pytest.raises(logic.BokehInputError, match="shipped for: mos-s1, mos-s2.; give Correction Model"):
        logic.choose_correction("network", "6p", 0.0122)
    given = str(tmp_path / "dacn-mos-s2.npz")
    assert logic.choose_correction("network", "6p", 0.0122, given).model_path == tmp_path / "dacn-mos-s2.npz"
    with pytest.raises(logic.BokehInputError, match="no such file"):
        logic.correction_model_path("6p", str(tmp_path / "mine.npz"))


def test_torch_missing_gives_the_install_command_for_this_python(monkeypatch):
    monkeypatch.setitem(sys.modules, "torch", None)          # as absent as in Blender's own Python
    msg = logic.torch_missing()
    assert msg and f'"{sys.executable}" -m pip install torch==2.13.0' in msg and "restart Blender" in msg


@pytest.fixture(scope="module")
def tiny_dacn(tmp_path_factory):
    """A tiny DACN of mos-s2 (test_dacn_train's pairs, 2 steps), exported as shipped."""
    pytest.importorskip("torch")
    from conftest import PAIR_FAST as FAST, Frames, dacn_config as _config

    from dcdi_core.models.dacn.export import export_dacn
    from dcdi_core.models.dacn.data import DA2TConfig, build_pairs
    from dcdi_core.models.dacn.train import train_dacn
    d = tmp_path_factory.mktemp("tiny-dacn")
    build_pairs(Frames(), d / "pairs", DA2TConfig(lens=ROUND_TRIP_LENS, **FAST))
    train_dacn(_config(d / "pairs", iters=2, checkpoint_every=2), d / "run")
    export_dacn(d / "run", d / "dacn.npz")
    return d / "dacn.npz"


@pytest.fixture(scope="module")
def round_trip(addon_zip, tiny_dacn, tmp_path_factory):
    pytest.importorskip("bpy")
    return run_headless("addon_headless_roundtrip.py", addon_zip, tmp_path_factory.mktemp("addon-round-trip"),
                        str(tiny_dacn), ROUND_TRIP_LENS)


def test_simulate_and_correct_leave_the_scene_as_it_was(round_trip):
    r = round_trip
    assert r["install"] == ["FINISHED"] and r["simulate"] == ["FINISHED"] and r["correct_cold"] == ["FINISHED"]
    assert r["round_trip_diff"] == []        # scene, render settings, camera, frame, objects
    assert r["new_data"] == {"images": 2}
    assert r["images"] == sorted(r["images_before"] + ["Lens Simulation", "Lens Corrected"])


def test_simulation_is_dcdi_cores_simulate_of_the_render(round_trip):
    """The image Simulate shows is dcdi_core's depth-aware simulate() of the
    operator's own render (the same PSF source: the bundled OLF), blurred."""
    from dcdi_core.psf.sources import psf_source
    from dcdi_core.optics.lens import load_lens
    from dcdi_core.render.geometry import ImageGeometry
    from dcdi_core.render.simulate import simulate
    d = round_trip["dir"]
    rgb, depth = np.load(d / "rt-rgb.npy"), np.load(d / "rt-depth.npy")
    lens = load_lens(ROUND_TRIP_LENS)
    geom = ImageGeometry.full_sensor(lens, *rgb.shape[:2])
    src = psf_source(lens, pixel_pitch_mm=geom.pixel_pitch_mm)
    assert src.kind == "basis" and round_trip["simulate_report_status"].startswith("PSFs from the PSF basis")
    want = simulate(rgb, depth, lens, library=src.library)
    shown = np.load(d / "rt-sim-image.npy")
    assert shown.shape == rgb.shape == (96, 128, 3)
    np.testing.assert_allclose(shown, want.image, atol=1e-5)
    np.testing.assert_array_equal(np.load(d / "rt-sensor_depth.npy"), want.depth.astype(np.float32))
    assert round_trip["pixel_pitch_mm"] == pytest.approx(geom.pixel_pitch_mm)

    def edge_energy(im, where):
        return (np.abs(np.diff(im, axis=0))[:, :-1] + np.abs(np.diff(im, axis=1))[:-1])[where[:-1, :-1]].mean()
    # blurred where the lens blurs: at this preview's 176 um pixels MOS-S2's kernels are 5 x 5 px;
    # measured edge energy of the sharp image on the sensor: cube 0.89, wall 0.94
    cube, wall = want.depth < 2.0, want.depth > 7.0
    assert cube.sum() > 1000 and wall.sum() > 4000
    assert edge_energy(shown, cube) < 0.92 * edge_energy(want.sharp, cube)
    assert edge_energy(shown, wall) < 0.97 * edge_energy(want.sharp, wall)
    noisy = np.load(d / "rt-sim-noise.npy")
    assert round_trip["simulate_noise"] == ["FINISHED"] and 1e-3 < np.abs(noisy - shown).mean() < 0.05


def test_correct_runs_the_shipped_dacn_on_the_simulation_with_its_depth(round_trip, tiny_dacn):
    from dcdi_core.models.dacn.correct import load_dacn
    from dcdi_core.optics.lens import load_lens
    from dcdi_core.app.correction_rule import NetworkCorrection, recover
    from dcdi_core.render.geometry import ImageGeometry
    d = round_trip["dir"]
    r = round_trip
    assert r["correct_warm"] == ["FINISHED"] and r["correct_model_file"] == ["FINISHED"]
    got = np.load(d / "rt-correct_cold.npy")
    np.testing.assert_array_equal(np.load(d / "rt-correct_warm.npy"), got)
    assert r["correct_cold_line"].startswith(f"Network with dacn-{ROUND_TRIP_LENS}.npz (chosen in the panel), ")
    model, info = load_dacn(tiny_dacn)
    want, _ = recover(np.load(d / "rt-sim.npy"), np.load(d / "rt-sensor_depth.npy"),
                      NetworkCorrection(model, info, geometry=ImageGeometry.full_sensor(load_lens(ROUND_TRIP_LENS),
                                                                                       96, 128)))
    assert got.shape == (96, 128, 3) and np.isfinite(got).all()
    np.testing.assert_allclose(got, want, atol=1e-4)


def _panel_lines(drawn, icon):
    """The texts the panel wraps over lines, each starting with ``icon``."""
    out, inside = [], False
    for kind, text, ic in drawn:
        if kind == "label" and ic == "BLANK1":
            if inside:
                out[-1] += " " + text          # the lines of a text wrapped at its words
            continue
        inside = kind == "label" and ic == icon
        if inside:
            out.append(text)
    return out


def test_network_without_torch_says_what_to_install_and_changes_nothing(round_trip):
    r = round_trip
    command = r["install_command"]
    assert command.endswith('" -m pip install torch==2.13.0') and command.startswith('"')
    assert "poll()" in r["no_torch_error"] and command in r["no_torch_error"]
    assert command in r["no_torch_run"]                 # the worker's path says the same
    assert r["no_torch_changed"] == [] and not r["torch_imported_while_blocked"]
    # the panel shows both buttons, and without torch the install command (wrapped over its lines)
    for drawn in (r["panel_no_torch"], r["panel_with_torch"]):
        ops = [x[1] for x in drawn if x[0] == "operator"]
        assert {"dcdi.apply_lens_bokeh", "dcdi.simulate_lens", "dcdi.correct_lens_simulation"} <= set(ops)
    assert any(command in line and "Deconvolution runs without it" in line
               for line in _panel_lines(r["panel_no_torch"], "ERROR"))
    assert not any(command in x[1] for x in r["panel_with_torch"] if x[0] == "label")
    # with torch: what Network will run, and the last method that ran
    will_run = f"Network with dacn-{ROUND_TRIP_LENS}.npz: chosen in the panel"
    assert _panel_lines(r["panel_with_torch"], "INFO")[-1] == will_run
    assert _panel_lines(r["panel_with_torch"], "CHECKMARK") == [f"Last Correct: {r['correct_warm_line']}"]


def test_correct_says_what_it_needs(round_trip):
    r = round_trip
    assert "run Simulate Minimalist Lens first" in r["correct_first"]
    assert f"no shipped DACN for lens {ROUND_TRIP_LENS} (shipped for: none); give Correction Model" \
        in r["no_shipped_error"]
    assert "missing.npz': no such file" in r["missing_model_error"]



def _correct_messages(r) -> dict:
    """Every message of Correct the round trip saw, by where it was seen: the
    errors (an ERROR report or a failed poll), the worker path's refusals,
    each finished Correct's info report and panel line, and the panel's texts."""
    out = {k: r[k] for k in ("correct_first", "no_torch_error", "no_torch_run", "no_shipped_error",
                             "missing_model_error", "junk_model_error", "no_shipped_6p", "shipped_network_error")
           if r[k] is not None}
    out.update({k: v for k, v in r.items() if k.endswith("_line") and isinstance(v, str)})
    out.update({f"report {i}": m for i, m in enumerate(r["correct_reports"])})
    for k, drawn in r.items():
        if k.startswith("panel_"):
            out.update({f"{k} {i}": x[1] for i, x in enumerate(drawn) if x[0] == "label"})
    return out


def test_correct_speaks_the_panels_words(round_trip):
    """What Correct shows a Blender user (no torch, no shipped network, a
    missing or broken Correction Model, each run's report) names the panel's
    settings, never a `dcdi` option."""
    r = round_trip
    messages = _correct_messages(r)
    for k in ("no_torch_error", "no_torch_run", "no_shipped_error", "missing_model_error", "junk_model_error",
              "no_shipped_6p"):
        assert messages[k], k                                   # each case was refused, saying why
    assert "junk.npz" in messages["junk_model_error"]
    assert "no shipped DACN for lens 6p (shipped for: mos-s1, mos-s2)" in messages["no_shipped_6p"]
    assert len(r["correct_reports"]) >= 10 and any("the deconvolution it refined: PSFs from" in m
                                                   for m in r["correct_reports"])
    assert {k: m for k, m in messages.items() if "--" in m} == {}


def test_psf_source_messages_on_corrects_path_name_no_option(monkeypatch):
    """The PSF source Correct's deconvolutions report, for a lens without a
    shipped basis and no OLF: the engine names its request's fields, the
    panel shows its own words (no CLI option), the CLI its options."""
    import dcdi_core.psf.sources as library
    from dcdi_core.cli.common import WORDS
    from dcdi_core.errors import in_words
    from dcdi_core.optics.lens import Lens
    from conftest import singlet_dict
    monkeypatch.setattr(library, "SHIPPED", Path("/nonexistent/olf.npz"))
    monkeypatch.setattr(library, "olf_rays_file", lambda: None)
    lens = Lens.from_dict(singlet_dict())
    src = library.psf_source(lens, pixel_pitch_mm=0.01)
    assert src.kind == "trace" and "no PSF basis of test-singlet ships with this engine" in src.message
    assert "(--basis)" in in_words(src.message, WORDS) and "(--olf)" in in_words(src.message, WORDS)
    panel = logic._note(src.message)
    assert "--" not in panel and "\u2039" not in panel, panel
    assert logic._note(library.psf_source(lens, source="trace").message) == "PSFs traced (PSF source trace)"


def test_round_trip_disable_leaves_nothing_registered(round_trip):
    assert round_trip["disable"] == ["FINISHED"] and round_trip["leftovers"] == []
    assert round_trip["operators_left"] == [] and not round_trip["simulation_kept"]


# ------------------------------------------------------------------ Correct without torch, and Auto
def _psnr(image, sharp, where):
    """PSNR (dB) on [0, 1]-clipped linear values at ``where``."""
    err = np.clip(image, 0, 1)[where] - np.clip(sharp, 0, 1)[where]
    return float(10 * np.log10(1.0 / np.mean(err ** 2)))


def _sharp_on_the_sensor(rgb, depth):
    """The render as a perfect lens would image it on the sensor (simulate's aligned sharp image)."""
    from dcdi_core.psf.sources import psf_source
    from dcdi_core.optics.lens import load_lens
    from dcdi_core.render.geometry import ImageGeometry
    from dcdi_core.render.simulate import simulate
    lens = load_lens(ROUND_TRIP_LENS)
    geom = ImageGeometry.full_sensor(lens, *rgb.shape[:2])
    src = psf_source(lens, pixel_pitch_mm=geom.pixel_pitch_mm)
    return simulate(rgb, depth, lens, library=src.library).sharp, lens, geom, src


def _deconvolved(capture, sensor_depth, noise):
    from dcdi_core.correct import DeconvOptions, deconvolve
    from dcdi_core.psf.sources import psf_source
    from dcdi_core.optics.lens import load_lens
    from dcdi_core.render.geometry import ImageGeometry
    lens = load_lens(ROUND_TRIP_LENS)
    geom = ImageGeometry.full_sensor(lens, *capture.shape[:2])
    src = psf_source(lens, pixel_pitch_mm=geom.pixel_pitch_mm)
    return deconvolve(capture, sensor_depth, lens, DeconvOptions(noise=noise), geometry=geom,
                      library=src.library).image


def test_correct_without_torch_deconvolves_and_sharpens_the_simulation(round_trip):
    """torch blocked: Auto and Deconvolution run dcdi_core.correct's
    deconvolution with the simulation's PSF source (the bundled OLF), its
    geometry and its depth on the sensor, the noise estimated on the image
    (Sensor Noise off); the result is nearer the render's sharp image on the
    sensor than the simulation is (measured 30.4 -> 36.7 dB)."""
    r = round_trip
    d = r["dir"]
    assert r["deconv_auto"] == ["FINISHED"] and r["deconv"] == ["FINISHED"]
    assert not r["torch_imported_while_blocked"]
    assert r["deconv_line"].startswith("Deconvolution (chosen in the panel), ")
    assert r["geometry"] == {"height": 96, "width": 128, "pixel_pitch_mm": pytest.approx(r["pixel_pitch_mm"])}
    sim, sensor_depth = np.load(d / "rt-sim.npy"), np.load(d / "rt-sensor_depth.npy")
    got = np.load(d / "rt-deconv.npy")
    np.testing.assert_array_equal(np.load(d / "rt-deconv_auto.npy"), got)
    np.testing.assert_allclose(got, _deconvolved(sim, sensor_depth, None), atol=1e-5)
    sharp, *_ = _sharp_on_the_sensor(np.load(d / "rt-rgb.npy"), np.load(d / "rt-depth.npy"))
    seen = np.isfinite(sensor_depth)
    before, after = _psnr(sim, sharp, seen), _psnr(got, sharp, seen)
    print(f"round trip, no sensor noise: simulation {before:.2f} dB, deconvolution {after:.2f} dB")
    assert after > before + 1.0, (before, after)


def test_correct_after_sensor_noise_weighs_by_the_sensors_noise_model(round_trip):
    """Sensor Noise on: the deconvolution's prior is weighed by the sensor's
    model (10000 e- full well, 3 e- read noise), not an estimate; it still
    sharpens the noisy simulation (measured 30.2 -> 36.5 dB)."""
    from dcdi_core.correct import NoiseModel
    r = round_trip
    d = r["dir"]
    assert r["deconv_noise"] == ["FINISHED"] and r["line_after_new_simulation"] == ""
    noisy, sensor_depth = np.load(d / "rt-sim-noise.npy"), np.load(d / "rt-noise-sensor_depth.npy")
    got = np.load(d / "rt-deconv_noise.npy")
    np.testing.assert_allclose(got, _deconvolved(noisy, sensor_depth, NoiseModel.sensor(10000.0, 3.0)), atol=1e-5)
    assert np.abs(got - _deconvolved(noisy, sensor_depth, None)).max() > 1e-3     # the estimate differs
    sharp, *_ = _sharp_on_the_sensor(np.load(d / "rt-noise-rgb.npy"), np.load(d / "rt-noise-depth.npy"))
    seen = np.isfinite(sensor_depth)
    before, after = _psnr(noisy, sharp, seen), _psnr(got, sharp, seen)
    print(f"round trip, sensor noise: simulation {before:.2f} dB, deconvolution {after:.2f} dB")
    assert after > before + 1.0, (before, after)


def test_auto_picks_what_the_engines_rule_says(round_trip, tiny_dacn, tmp_path, monkeypatch):
    """The operator's Auto against dcdi_core.app.correction_rule.choose_correction asked
    the same (the panel's option names): no shipped network, a shipped one
    not recorded better than the deconvolution, a network file given; where
    the rule picks a network and torch is blocked, the deconvolution runs."""
    import shutil

    import dcdi_core.shipped as registry
    from dcdi_core.app.correction_rule import choose_correction
    r = round_trip
    pitch = r["pixel_pitch_mm"]

    def rule(model=None):
        method, why = choose_correction(ROUND_TRIP_LENS, pitch, "auto", model)
        return method, logic._note(why)               # the engine's reason in the panel's words

    empty, shipped = tmp_path / "empty", tmp_path / "shipped"
    empty.mkdir()
    shipped.mkdir()
    shutil.copy(tiny_dacn, shipped / f"dacn-{ROUND_TRIP_LENS}.npz")
    monkeypatch.setattr(registry, "WEIGHTS_DIR", empty)
    assert rule()[0] == "deconv" and r["auto_choice_no_network"] == ["deconvolution", rule()[1]]
    monkeypatch.setattr(registry, "WEIGHTS_DIR", shipped)
    method, why = rule()
    assert method == "deconv" and r["auto_choice_with_torch"] == ["deconvolution", why]
    assert r["auto_with_torch_line"].startswith(f"Deconvolution ({why}), ")
    method, why = rule(Path(tiny_dacn))
    assert method == "dacn" and "Correction Model" in why
    assert r["auto_given_line"].startswith(f"Network with dacn.npz ({why}), ")
    assert r["deconv_auto_given_line"].startswith(f"Deconvolution ({why}; but this Python has no PyTorch for it), ")
    np.testing.assert_allclose(np.load(r["dir"] / "rt-auto_given.npy"), np.load(r["dir"] / "rt-correct_cold.npy"),
                               atol=1e-6)


def test_auto_runs_a_shipped_network_recorded_better_at_its_pitch(tiny_dacn, tmp_path, monkeypatch):
    """Auto's network branch without bpy: a shipped DACN recorded better
    than the deconvolution runs at the pixel pitch it learned (with torch),
    the deconvolution at another pitch, and without torch."""
    import dataclasses
    import shutil

    import dcdi_core.shipped as registry
    from dcdi_core.app.correction_rule import trained_pitch_mm
    shutil.copy(tiny_dacn, tmp_path / f"dacn-{ROUND_TRIP_LENS}.npz")
    monkeypatch.setattr(registry, "WEIGHTS_DIR", tmp_path)
    monkeypatch.setitem(registry.NETWORKS, "dacn", dataclasses.replace(registry.NETWORKS["dacn"],
                                                                       beats_deconvolution=(ROUND_TRIP_LENS,)))
    learned = trained_pitch_mm(tiny_dacn)
    c = logic.choose_correction("auto", ROUND_TRIP_LENS, learned)
    assert c.method == "network" and c.model_path == tmp_path / f"dacn-{ROUND_TRIP_LENS}.npz", c
    assert "recorded better than the deconvolution" in c.reason
    c = logic.choose_correction("auto", ROUND_TRIP_LENS, learned / 2)
    assert c.method == "deconvolution" and "learned" in c.reason and c.model_path is None
    assert logic.choose_correction("deconvolution", ROUND_TRIP_LENS, learned).method == "deconvolution"
    monkeypatch.setitem(sys.modules, "torch", None)          # as absent as in Blender's own Python
    c = logic.choose_correction("auto", ROUND_TRIP_LENS, learned)
    assert c.method == "deconvolution" and c.reason.endswith("but this Python has no PyTorch for it")
    with pytest.raises(logic.BokehInputError, match="Deconvolution runs without it"):
        logic.choose_correction("network", ROUND_TRIP_LENS, learned)
    with pytest.raises(logic.BokehInputError, match="allowed auto, deconvolution, network"):
        logic.choose_correction("wiener", ROUND_TRIP_LENS, learned)



# ------------------------------------------------------------------ Correct with the shipped (refining) DACNs
SHIPPED_PITCH_MM = 0.0122            # the pitch the shipped DACNs learned (registry: the DACN study's 12.2 um)


def _capture_at_the_shipped_pitch(tmp_path, lens_id, height=64, width=96):
    """A small simulated capture of ``lens_id`` at the shipped DACNs' pitch
    (a crop of the sensor round the axis): its EXR and depth files, and
    (capture as read back, depth on the sensor, lens, geometry)."""
    from dcdi_core.io.images import read_image, write_image
    from dcdi_core.psf.sources import psf_source
    from dcdi_core.render.geometry import ImageGeometry
    from dcdi_core.render.simulate import SimulateOptions, simulate
    from dcdi_core.render.synthetic import synthetic_rgbd
    lens = logic.load_lens_cached(str(ROOT / "lenses" / f"{lens_id}.toml"))
    geom = ImageGeometry.from_pixel_pitch(lens, height, width, SHIPPED_PITCH_MM)
    rgb, depth = synthetic_rgbd(height, width, seed=1)
    sim = simulate(rgb, depth, lens, SimulateOptions(geometry=geom),
                   library=psf_source(lens, pixel_pitch_mm=SHIPPED_PITCH_MM).library)
    write_image(tmp_path / "capture.exr", sim.image)
    np.save(tmp_path / "depth.npy", sim.depth)
    return read_image(tmp_path / "capture.exr"), sim.depth.astype(np.float32), lens, geom


def _cli_correct(capsys, tmp_path, lens_id, method, name, *extra):
    """`dcdi correct --method METHOD --lens LENS [extra]` of the capture at the shipped pitch: (image, its JSON
    record)."""
    from dcdi_core.io.images import read_image
    from support.cli import run_cli
    out = tmp_path / f"{name}.exr"
    code, stdout, err = run_cli(capsys, "correct", "--method", method, "--lens", lens_id, "--image",
                                tmp_path / "capture.exr", "--depth", tmp_path / "depth.npy", "--image-pixel-pitch",
                                repr(SHIPPED_PITCH_MM), "-o", out, *extra)
    assert code == 0, err
    return read_image(out), json.loads(stdout)


@pytest.mark.parametrize("lens_id", ["mos-s1", "mos-s2"])
def test_network_runs_the_shipped_refining_dacn_as_dcdi_correct_does(lens_id, tmp_path, capsys, monkeypatch):
    """Correct's Network on a capture of a lens whose shipped DACN refines
    the deconvolution (and reads depth and field): the add-on's result is
    `dcdi correct --method dacn --lens L` on the same capture, depth and
    pixel pitch; Auto at that pitch picks the network (recorded better) and
    gives `dcdi correct --method auto`'s result."""
    pytest.importorskip("torch")
    monkeypatch.setenv("DCDI_CACHE_DIR", str(tmp_path / "cache"))
    from dcdi_core.models.dacn.correct import load_dacn
    from dcdi_core.app.correction_rule import shipped_model
    spec = load_dacn(shipped_model("dacn", lens_id))[0].spec
    assert spec.refine and spec.condition                       # the defect's case: a refining, conditioned DACN
    capture, depth, lens, geom = _capture_at_the_shipped_pitch(tmp_path, lens_id)
    want, record = _cli_correct(capsys, tmp_path, lens_id, "dacn", "cli-dacn")
    assert record["correction"]["method"] == "dacn" and "deconvolution" in record["correction"]
    choice = logic.choose_correction("network", lens_id, geom.pixel_pitch_mm)
    assert choice.method == "network" and choice.model_path == shipped_model("dacn", lens_id)
    got, info = logic.run_correction(capture, depth, lens, choice, geometry=geom)
    assert got.shape == (64, 96, 3) and got.dtype == np.float32
    np.testing.assert_allclose(got, want, atol=1e-5)
    assert info["notes"] == []                                  # its own lens, the pitch it learned
    # Auto: the network, recorded better than the deconvolution, at the pitch it learned
    auto = logic.choose_correction("auto", lens_id, geom.pixel_pitch_mm)
    assert auto.method == "network" and "recorded better than the deconvolution" in auto.reason, auto
    want_auto, record = _cli_correct(capsys, tmp_path, lens_id, "auto", "cli-auto")
    assert record["correction"]["method"] == "dacn"
    got_auto, _ = logic.run_correction(capture, depth, lens, auto, geometry=geom)
    np.testing.assert_allclose(got_auto, want_auto, atol=1e-5)





def test_auto_at_the_shipped_pitch_without_torch_deconvolves_saying_why(tmp_path, capsys, monkeypatch):
    """Auto where the rule picks the shipped network (MOS-S1 at 12.2 um) and
    Blender's Python has no torch: the deconvolution runs (`dcdi correct
    --method deconv`'s result), its reason in the panel's words; Network
    asked for says what to install."""
    monkeypatch.setenv("DCDI_CACHE_DIR", str(tmp_path / "cache"))
    capture, depth, lens, geom = _capture_at_the_shipped_pitch(tmp_path, "mos-s1")
    want, record = _cli_correct(capsys, tmp_path, "mos-s1", "deconv", "cli-deconv")
    monkeypatch.setitem(sys.modules, "torch", None)          # as absent as in Blender's own Python
    auto = logic.choose_correction("auto", "mos-s1", geom.pixel_pitch_mm)
    assert auto.method == "deconvolution" and auto.model_path is None
    assert auto.reason.startswith("the shipped DACN of mos-s1 is recorded better than the deconvolution")
    assert auto.reason.endswith("; but this Python has no PyTorch for it") and "--" not in auto.reason
    got, info = logic.run_correction(capture, depth, lens, auto, geometry=geom)
    np.testing.assert_allclose(got, want, atol=1e-5)
    assert info["psf_source"] == record["correction"]["psf_source"] == "basis"
    line = logic.correction_report(info, 0.1, got.shape)
    assert line.startswith(f"Correct Simulation: Deconvolution ({auto.reason}), 0.1 s; 96 x 64 px; PSFs from")
    assert "--" not in line
    with pytest.raises(logic.BokehInputError, match="Deconvolution runs without it") as e:
        logic.choose_correction("network", "mos-s1", geom.pixel_pitch_mm)
    assert "--" not in str(e.value)


def test_network_tells_a_one_depth_dacn_its_depth_as_dcdi_correct_does(tmp_path, capsys, monkeypatch):
    """A Correction Model trained told one depth (models.dacn.unaware: here
    the shipped MOS-S1 network's file recorded so, told 2 m): the add-on
    tells it that depth and refines the one-depth deconvolution, as `dcdi
    correct --model FILE` does."""
    pytest.importorskip("torch")
    monkeypatch.setenv("DCDI_CACHE_DIR", str(tmp_path / "cache"))
    from dcdi_core.models.runtime.dacn_file import read_dacn_file
    from dcdi_core.io.model_npz import write_model_npz
    from dcdi_core.app.correction_rule import shipped_model
    meta, arrays = read_dacn_file(shipped_model("dacn", "mos-s1"))
    meta = {k: v for k, v in meta.items() if k != "checksum"}
    meta["da2t"] = dict(meta["da2t"], told_depth_m=2.0)
    told = tmp_path / "told-2m.npz"
    write_model_npz(told, meta, arrays)
    capture, depth, lens, geom = _capture_at_the_shipped_pitch(tmp_path, "mos-s1")
    want, record = _cli_correct(capsys, tmp_path, "mos-s1", "dacn", "cli-told", "--model", told)
    assert record["correction"]["deconvolution"]["one_depth_m"] == 2.0
    choice = logic.choose_correction("network", "mos-s1", geom.pixel_pitch_mm, str(told))
    got, info = logic.run_correction(capture, depth, lens, choice, geometry=geom)
    np.testing.assert_allclose(got, want, atol=1e-5)
    assert info["deconvolution"]["one_depth_m"] == 2.0
    shipped, _ = logic.run_correction(capture, depth, lens, logic.choose_correction("network", "mos-s1",
                                                                                    geom.pixel_pitch_mm),
                                      geometry=geom)
    assert np.abs(shipped - got).max() > 1e-3                 # told one depth: another result


def test_network_in_blender_runs_the_lenss_shipped_dacn_as_dcdi_correct_does(round_trip, tmp_path, capsys):
    """The operator with Network and the lens's real shipped DACN (MOS-S2's
    refines the deconvolution): it runs, and its image is `dcdi correct
    --method dacn --lens mos-s2` of the simulation at the preview's pixel
    pitch and with its depth on the sensor."""
    from dcdi_core.io.images import read_image, write_image
    from support.cli import run_cli
    r, d = round_trip, round_trip["dir"]
    assert r["shipped_network_error"] is None and r["correct_shipped"] == ["FINISHED"]
    assert r["correct_shipped_line"].startswith(f"Network with dacn-{ROUND_TRIP_LENS}.npz (chosen in the panel), ")
    write_image(tmp_path / "capture.exr", np.load(d / "rt-sim.npy"))
    code, _, err = run_cli(capsys, "correct", "--method", "dacn", "--lens", ROUND_TRIP_LENS, "--image",
                           tmp_path / "capture.exr", "--depth", d / "rt-sensor_depth.npy", "--image-pixel-pitch",
                           repr(r["pixel_pitch_mm"]), "-o", tmp_path / "cli.exr")
    assert code == 0, err
    got = np.load(d / "rt-correct_shipped.npy")
    assert got.shape == (96, 128, 3) and np.isfinite(got).all()
    np.testing.assert_allclose(got, read_image(tmp_path / "cli.exr"), atol=1e-5)


def test_psf_thumbnail_is_a_grid_of_peak_normalised_psfs():
    lens = logic.load_lens_cached(str(ROOT / "lenses" / "mos-s1.toml"))
    img = logic.psf_thumbnail(lens, tile=15)
    nf, nd = len(logic.THUMBNAIL_FIELDS), len(logic.THUMBNAIL_DEPTHS_M)
    assert img.shape == (nf * 16 - 1, nd * 16 - 1, 3) and img.dtype == np.float32
    assert np.isfinite(img).all() and img.min() >= 0.0
    for i in range(nf):
        for j in range(nd):
            tile = img[i * 16:i * 16 + 15, j * 16:j * 16 + 15]
            assert tile.max() == pytest.approx(1.0)                 # each PSF scaled to its own peak
    assert not img[15::16].any() and not img[:, 15::16].any()       # the gaps stay black


def test_the_bokehs_psf_source_message_speaks_the_panels_words():
    """Apply Lens Bokeh, Simulate and Lens in Renders show the PSF source's
    message: for an imported lens the engine's names its request's field
    (basis), the CLI shows its option, the panel its own words."""
    from conftest import singlet_dict
    from dcdi_core.cli.common import WORDS
    from dcdi_core.errors import in_words
    from dcdi_core.psf.sources import psf_source
    from dcdi_core.optics.lens import Lens
    lens = Lens.from_dict(singlet_dict())
    message = psf_source(lens, pixel_pitch_mm=0.05).message
    assert "--basis" in in_words(message, WORDS)                                     # the CLI's
    msg = logic._note(message)                                                        # run_bokeh's, the panel's
    assert "PSFs traced" in msg and "--" not in msg and "\u2039" not in msg, msg


def test_the_preview_traces_what_no_shipped_source_holds_at_its_own_quality(tmp_path, monkeypatch):
    """For a lens without an error table, the viewport preview's traced PSFs
    (logic.PREVIEW_TRACE) are a proxy of the full trace; with one, both are
    planned by their budgets; where a shipped source serves, the preview is
    the full result, bit for bit."""
    from dcdi_core.optics.lens import load_lens
    from dcdi_core.psf import budget, sources
    monkeypatch.setenv("DCDI_CACHE_DIR", str(tmp_path / "cache"))
    with_table = budget.load_table
    monkeypatch.setattr(budget, "load_table", lambda lens_id, folder=None: None)
    # refocused MOS-S2 without its focus stack: what no shipped source holds
    shipped = sources.shipped_store
    monkeypatch.setattr(sources, "shipped_store", lambda lens_id, focus_stack=False:
                        None if focus_stack else shipped(lens_id))
    monkeypatch.setattr(sources, "olf_rays_file", lambda: None)
    logic.clear_psf_sources()
    rng = np.random.default_rng(0)
    img = rng.random((36, 48, 3), dtype=np.float32)
    depth = np.full((36, 48), 3.0, np.float32)
    depth[:, :20] = 1.2
    lens = load_lens("mos-s2")
    full, info_full = logic.run_bokeh(img, depth, lens, focus_m=2.0, keep=(2.0, 2.0))
    prev, info_prev = logic.run_bokeh(img, depth, lens, focus_m=2.0, keep=(2.0, 2.0), preview=True)
    assert info_full["psf_source"] == info_prev["psf_source"] == "trace"
    assert (info_full["psf_quality"], info_prev["psf_quality"]) == ("full", "preview")
    mse = float(np.mean((prev.astype(np.float64) - full) ** 2))
    assert 0 < mse and 10 * np.log10(1 / mse) >= 45.0              # a proxy, not the same PSFs
    monkeypatch.setattr(budget, "load_table", with_table)
    logic.clear_psf_sources()
    _, info_planned = logic.run_bokeh(img, depth, lens, focus_m=2.0, keep=(2.0, 2.0), preview=True)
    assert info_planned["psf_source"] == "trace" and info_planned["psf_quality"] == "planned"
    held, info_held = logic.run_bokeh(img, depth, lens, focus_m=2.0, keep=(2.0, 2.0), refocus=False, preview=True)
    same, _ = logic.run_bokeh(img, depth, lens, focus_m=2.0, keep=(2.0, 2.0), refocus=False)
    assert info_held["psf_source"] == "basis" and info_held["psf_quality"] == "full"
    assert np.array_equal(held, same)


# ------------------------------------------------------------------ the panel, readable by an artist
# the checkout's add-on registered in pip bpy, its panel drawn into a recording layout (what it asks
# Blender for: each text and icon, whether properties are split); prints JSON
_PANEL = r"""
import json, sys
sys.path.insert(0, {root!r})
sys.path.insert(0, {here!r})
import bpy
import blender_addon
from blender_addon import panel, reading
from addon_scene import build_scene
blender_addon.register()
scene, cam, cube = build_scene()
s = scene.dcdi_lens_bokeh
st = bpy.context.window_manager.dcdi_lens_bokeh_status


class Rec:
    def __init__(self, log, split=False):
        object.__setattr__(self, "log", log)
        object.__setattr__(self, "use_property_split", split)

    def _child(self, *a, **k):
        self.log.append(("layout", k.get("heading", ""), None, self.use_property_split))
        return Rec(self.log, self.use_property_split)

    row = column = box = split = _child

    def label(self, text="", icon="NONE", **k):
        self.log.append(("label", text, icon, self.use_property_split))

    def operator(self, idname, **k):
        self.log.append(("operator", idname, k.get("icon", "NONE"), self.use_property_split))
        return Rec([])

    def prop(self, data, name, **k):
        text = k.get("text", data.bl_rna.properties[name].name)
        self.log.append(("prop", name, k.get("icon", "NONE"), self.use_property_split, text))

    def template_icon(self, **k):
        pass


def draw():
    log = []
    panel.draw_lens_bokeh(Rec(log), bpy.context)
    return log


def stamp():                  # the status as an operator leaves it (the settings it ran with)
    if hasattr(reading, "inputs_key"):
        st.job, st.inputs = "Lens Bokeh", reading.inputs_key(scene)


res = {{}}
s.lens = "6p"
s.lens_in_renders = True
scene.render.use_lock_interface = False
res["drawn"] = draw()
s.lens_in_renders = False
st.message, st.psf_source = "done in 5.9 s", "PSFs from the PSF basis that ships with the add-on (rank 160)"
stamp()
res["done"] = draw()
s.focus_distance = 3.0
res["changed"] = draw()
res["focus_tooltip"] = s.bl_rna.properties["focus_distance"].description
print(json.dumps(res))
"""


@pytest.fixture(scope="module")
def panel_drawn(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("panel")
    env = dict(os.environ, BLENDER_USER_RESOURCES=str(tmp / "user"), DCDI_CACHE_DIR=str(tmp / "cache"))
    env.pop("DCDI_LENS_PATH", None)
    code = _PANEL.format(root=str(ROOT), here=str(Path(__file__).resolve().parent))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, cwd=tmp, timeout=300)
    assert out.returncode == 0, out.stderr[-3000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_the_lens_list_names_lenses_whole_without_stated_figures():
    """The lens list shows each lens's name (not its id, not cut), without the
    figures its source states (the readout shows the traced ones), short
    enough for the list's field; a file without a name goes by its id."""
    names = {e.id: e.name for e in logic.lens_catalogue()}
    assert names["6p"] == "6P lens (OptiFusion)" and names["double-gauss"] == "Double Gauss"
    assert names["mos-s1"] == "MOS-S1 (H-K9L singlet)" and names["mos-s2"] == "MOS-S2 (model-glass singlet)"
    for lens_id, name in names.items():
        assert name != lens_id and "F/" not in name and len(name) <= 28, names


def test_the_lens_list_is_sorted_by_maker_and_focal_length():
    """The makers' lenses first, by maker and focal length, named as the
    maker sells them; then the designs and research lenses (no maker)."""
    entries = logic.lens_catalogue()
    order = [logic._lens_order(__import__("pathlib").Path(e.path)) for e in entries]
    assert order == sorted(order)
    makers = [logic._lens_facts(__import__("pathlib").Path(e.path))[0] for e in entries]
    first_research = makers.index("")
    assert all(makers[:first_research]) and not any(makers[first_research:]), makers
    names = {e.id: e.name for e in entries}
    assert names["zeiss-sonnar-50mm-f1-5"] == "Zeiss Sonnar 50mm f/1.5"
    assert names["nikkor-85mm-f1-4"] == "Nikon Nikkor 85mm f/1.4" and names["canon-fd-100mm-f2"] == "Canon FD 100mm f/2"
    nikon = [e.id for e in entries if e.id.startswith(("nikkor", "nikon"))]
    assert nikon == ["nikkor-24mm-f2", "nikon-retrofocus-28mm-f2-8", "nikkor-35mm-f2", "nikkor-85mm-f1-4",
                     "nikkor-180mm-f2-8-ed"]
    assert {"6p", "mos-s1", "mos-s2", "double-gauss"} <= {e.id for e in entries[first_research:]}


def test_a_hostile_maker_is_no_maker(tmp_path):
    from blender_addon import logic as lg
    for i, maker in enumerate(("x" * 500, "[1, 2]", "{a = 1}")):
        p = tmp_path / f"m{i}" / "x.toml"
        p.parent.mkdir()
        p.write_text(f'name = "Lens"\nmaker = {maker if maker[0] in "[{" else repr(maker)}\n')
        assert lg._lens_facts(p) == ("", float("inf")) and lg._lens_name(p) == "Lens"


def test_the_lens_name_is_shortened_by_whole_parts_only(tmp_path):
    from blender_addon import logic as lg
    cases = {"": "x", "A very long imported Zemax lens title with many words":
             "A very long imported Zemax lens title with many words",
             "Cooke triplet F/4.5, f = 50 mm": "Cooke triplet",
             "Tessar (Zeiss, 1902, four elements), F/6.3": "Tessar (Zeiss)"}
    for i, (given, want) in enumerate(cases.items()):
        p = tmp_path / f"l{i}" / "x.toml"
        p.parent.mkdir()
        p.write_text(f'name = "{given}"\n')
        assert lg._lens_name(p) == want, given


def test_the_psf_source_line_names_no_path_and_no_lens_id(tmp_path):
    """Where the PSFs came from, as the panel and the report say it: the
    engine makes its message in the panel's words (``logic.panel_words``):
    its files are "shipped", another file goes by its name, no absolute
    path, no lens id; the command line's names both."""
    import shutil
    from dcdi_core.optics.lens import load_lens
    from dcdi_core.psf.sources import psf_source
    from dcdi_core.shipped import BASIS_DIR
    for lens_id, focus, want in (("6p", None, "PSFs from the PSF basis that ships with the add-on ("),
                                 ("6p", 2.0, "PSFs from the Omni-Lens-Field that ships with the add-on ("),
                                 ("mos-s1", 2.0, "PSFs from the PSF basis that ships with the add-on ("),
                                 ("mos-s1", 0.5, "PSFs from the Omni-Lens-Field that ships with the add-on ("),
                                 ("nikkor-85mm-f1-4", 2.0, "PSFs from the ray map that ships with the add-on (")):
        lens = load_lens(lens_id)
        src = psf_source(lens, pixel_pitch_mm=0.05, focus_m=focus)
        assert str(src.basis_file or src.olf_file or src.raymap_file or "/") in src.message, src.message
        assert lens_id in src.message
        got = logic._note(psf_source(lens, pixel_pitch_mm=0.05, focus_m=focus, words=logic.panel_words()).message)
        assert got.startswith(want), got
        assert "/" not in got.replace("F/", "") and ".npz" not in got, got
        assert lens_id not in got, got
    # a lens no store holds: traced, the reasons naming the shipped files by what they are
    from conftest import singlet_dict
    from dcdi_core.optics.lens import Lens
    got = logic._note(psf_source(Lens.from_dict(singlet_dict()), pixel_pitch_mm=0.05,
                                 words=logic.panel_words()).message)
    assert got.startswith("PSFs traced: ") and "shipped Omni-Lens-Field" in got, got
    assert "/" not in got and ".npz" not in got and "test-singlet" not in got, got
    # a user's file: by its name alone
    mine = tmp_path / "my-basis.npz"
    shutil.copy(BASIS_DIR / "6p.npz", mine)
    got = psf_source(load_lens("6p"), pixel_pitch_mm=0.05, basis_file=mine, words=logic.panel_words()).message
    assert got.startswith("PSFs from the PSF basis my-basis.npz (rank"), got


def _labels(log):
    return [x[1] for x in log if x[0] == "label"]


def test_the_panels_switches_show_their_names(panel_drawn):
    """Preview in Viewport, Lens in Renders, Lock Interface: never an icon
    in a split layout (Blender draws that button as its icon alone)."""
    props = {x[1]: x for x in panel_drawn["drawn"] if x[0] == "prop"}
    for name, text in (("viewport_preview", "Preview in Viewport"), ("lens_in_renders", "Lens in Renders"),
                       ("use_lock_interface", "Lock Interface")):
        _, _, icon, split, shown = props[name]
        assert shown == text and not (split and icon != "NONE"), props[name]


def test_the_panel_shows_one_readout_the_traced_one(panel_drawn):
    texts = _labels(panel_drawn["drawn"])
    figures = [t for t in texts if "F/" in t]
    assert figures == ["f = 26.45 mm, F/1.64, FoV 63.8\N{DEGREE SIGN}"], texts
    assert "6P lens (OptiFusion)" in texts


def test_kept_sharp_is_a_label_over_its_two_settings(panel_drawn):
    log = panel_drawn["drawn"]
    at = next(i for i, x in enumerate(log) if x[0] == "prop" and x[1] == "keep_front")
    before = [x for x in log[:at] if x[0] != "layout"]
    assert before[-1][:2] == ["label", "Kept Sharp"], before[-1]
    assert [log[at][4], next(x for x in log[at + 1:] if x[0] == "prop")[4]] == ["In Front", "Behind"]
    assert not any(x[0] == "layout" and x[1] == "Kept Sharp" for x in log)


def test_panel_warnings_wrap_at_whole_words(panel_drawn):
    """A warning over several labels holds its words whole and in order (it
    was cut every 48 characters, mid-word)."""
    text = ("Turn Lock Interface on: the lens reads the scene while Blender renders (F12 in the window; "
            "command-line renders do not need it)")
    log = [x for x in panel_drawn["drawn"] if x[0] == "label"]
    at = next(i for i, x in enumerate(log) if x[1].startswith("Turn Lock"))
    lines = [log[at][1]]
    for x in log[at + 1:]:
        if x[2] != "BLANK1":
            break
        lines.append(x[1])
    assert len(lines) > 1 and " ".join(lines).split() == text.split(), lines


def test_the_status_describes_the_settings_as_they_are(panel_drawn):
    """The last job's "done in 5.9 s" and its PSF source show while the
    settings are those it ran with; after a change, not."""
    assert any("done in 5.9 s" in t for t in _labels(panel_drawn["done"]))
    assert any(t.startswith("PSFs from") for t in _labels(panel_drawn["done"]))
    changed = _labels(panel_drawn["changed"])
    assert not any("done in" in t or t.startswith("PSFs from") for t in changed), changed


def test_the_focus_tooltip_speaks_an_artists_words(panel_drawn):
    tip = panel_drawn["focus_tooltip"]
    assert "vertex" not in tip and "from the camera" in tip and "Depth of Field" in tip, tip


def test_a_cameras_aperture_is_never_refused():
    """logic.camera_aperture: Blender's F-Stop, Blades and Rotation as the
    artist set them: stopped down, or wide open with a note where the
    F-Stop is wider than the lens's; blades below 3 round; far stops at
    f/128."""
    lens = logic.load_lens_cached(dict((e.id, e.path) for e in logic.lens_catalogue())["mos-s1"])
    stopped, note = logic.camera_aperture(lens, 8.0, 6, math.radians(15.0))
    assert stopped.iris == "f/8, 6 blades turned 15 deg" and note == ""
    stop = stopped.surfaces[stopped.stop_index]
    assert stop.blades == 6 and stop.blade_rotation_deg == pytest.approx(15.0)
    assert logic.camera_aperture(lens, 2.8, 0, 0.0) == (lens, "F-Stop 2.8 is wider than this lens's widest, "
                                                               "f/5: the lens wide open")
    assert logic.camera_aperture(lens, 5.0, 0, 0.0) == (lens, "")
    assert logic.camera_aperture(lens, 8.0, 2, 1.0)[0].iris == "f/8"
    assert logic.camera_aperture(lens, 1e6, 5, 0.0)[0].iris == "f/128, 5 blades"
    for bad in (math.nan, math.inf, 0.0, -1.0):
        assert logic.camera_aperture(lens, bad, 6, math.nan)[0].iris in ("", "f/5, 6 blades")


def test_a_wide_blur_gets_a_coarser_thumbnail_not_a_flat_square():
    """The Nikkor 85mm f/1.4 as prescribed (focused at infinity) blurs a point
    at 1 m far over a 31-px tile at a 600-px diagonal's pitch: its thumbnail
    is drawn at the pitch that holds the widest, so each tile shows a disc
    with dark corners (not a clipped, flat square) and the far point stays
    a small spot."""
    lens = logic.load_lens_cached(dict((e.id, e.path) for e in logic.lens_catalogue())["nikkor-85mm-f1-4"])
    t = logic.THUMBNAIL_TILE_PX
    img = logic.psf_thumbnail(lens)
    near, far = img[:t, :t], img[:t, 2 * (t + 1):2 * (t + 1) + t]        # field 0: 1 m and infinity
    assert near[t // 2, t // 2].max() > 0.3 and near[:3, :3].max() < 0.05 and near[-3:, -3:].max() < 0.05
    assert (far.max(axis=-1) > 0.5).sum() < 0.05 * t * t


def test_a_wide_balls_thumbnail_is_smooth_not_the_ray_grids_moire():
    """The Nikkor 85mm's ball of a light at 1 m fills its tile: with four
    pupil rays a pixel across it its inside is smooth (two a pixel left the
    ray grid's lines in it: 0.077 mean deviation from the 3 x 3 mean, now
    0.023); the list's icon is the ball toward the corner (field 0.9, 1 m)."""
    from scipy.ndimage import uniform_filter
    lens = logic.load_lens_cached(dict((e.id, e.path) for e in logic.lens_catalogue())["nikkor-85mm-f1-4"])
    t = logic.THUMBNAIL_TILE_PX
    img = logic.psf_thumbnail(lens)
    near = img[:t, :t].mean(axis=-1)
    inside = uniform_filter((near > 0.2).astype(float), 5) > 0.99
    assert inside.sum() > 200
    assert np.abs(near - uniform_filter(near, 3))[inside].mean() < 0.04
    ball = logic.thumbnail_ball(img)
    assert ball.shape == (t, t, 3) and np.array_equal(ball, img[2 * (t + 1):2 * (t + 1) + t, :t])
    assert ball.max() == pytest.approx(1.0)
