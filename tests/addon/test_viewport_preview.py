"""The viewport preview under the pip bpy module (in a subprocess; its
refresh stepped by hand, background Blender has no timers or GPU): the
toggle's first result is the lens stage on a low-sample render, a focus
change reruns the lens stage only, a scene change renders again, a newer
change drops a running job, and the toggle off removes the handler. The
GPU drawing itself needs Blender with a window (not tested here)."""
import numpy as np
import pytest

from headless_run import run_headless
from test_addon import ROOT, addon_zip  # noqa: F401  (the zip fixture)


@pytest.fixture(scope="module")
def preview(addon_zip, tmp_path_factory):  # noqa: F811
    pytest.importorskip("bpy")
    return run_headless("addon_headless_preview.py", addon_zip, tmp_path_factory.mktemp("preview"))


def _pupil_m(preview) -> float:
    """The 6P's entrance pupil behind its first vertex, metres: the panel's
    Distance 1.0 (from the camera, as Blender measures) is the lens's focus
    1.0 - this from its front."""
    return 1.0 - preview["first"]["focus_m"]


def test_the_first_result_is_the_lens_on_a_preview_render(preview):
    from blender_addon import logic
    first = preview["first"]
    assert preview["handler_on"] and first["error"] == "" and first["render_s"] > 0 and first["refreshes"] == 1
    img = np.load(preview["dir"] / "first.npy")
    rgb, depth = np.load(preview["dir"] / "sharp_rgb.npy"), np.load(preview["dir"] / "sharp_depth.npy")
    assert img.shape == rgb.shape == (120, 160, 3)             # Preview Size 160 of a 640 x 480 render
    lens = logic.load_lens_cached(str(ROOT / "lenses" / "6p.toml"))
    want, _ = logic.run_bokeh(rgb, depth, lens, focus_m=first["focus_m"], keep=tuple(first["keep_m"]))
    assert np.abs(img - want).max() <= 1e-6 * max(1.0, float(want.max()))
    assert np.abs(img - rgb).mean() > 1e-3                     # blurred, not the render


def test_a_focus_change_reruns_the_lens_stage_only(preview):
    f = preview["focus"]
    assert preview["focus_pending"] and f["render_s"] == 0.0 and f["focus_m"] == pytest.approx(2.5 - _pupil_m(preview)) and f["refreshes"] == 2
    assert not np.array_equal(np.load(preview["dir"] / "focus.npy"), np.load(preview["dir"] / "first.npy"))
    assert preview["idle_refreshes"] == 2                      # an update that changes nothing: no refresh


def test_a_focus_seen_before_comes_back_from_memory(preview):
    """Back to the first focus on the same render: the result kept, no lens stage."""
    r = preview["recalled"]
    assert r["log"] is True and r["lens_s"] == 0.0 and r["focus_m"] == preview["first"]["focus_m"]
    assert np.array_equal(np.load(preview["dir"] / "recalled.npy"), np.load(preview["dir"] / "first.npy"))


def test_a_scene_change_renders_again(preview):
    sc = preview["scene"]
    assert preview["scene_pending"] and sc["render_s"] > 0 and sc["refreshes"] == 5


def test_a_newer_change_drops_the_running_job(preview):
    c = preview["cancel"]
    assert c["generation"] > c["started_generation"] and c["focus_m"] == pytest.approx(6.0 - _pupil_m(preview))
    assert c["refreshes"] == 6                                # the dropped job's result was never shown


def test_the_toggle_off_removes_the_handler_and_the_result(preview):
    assert not preview["handler_off"] and not preview["result_after_off"]


def test_focus_on_a_clicked_point_and_on_the_active_object(preview):
    # the camera looks down -Z from the origin: a point 3 m away is the Distance 3 m, as Blender measures it
    assert preview["pick"] == ["FINISHED"] and preview["pick_focus"]["mode"] == "DISTANCE"
    assert preview["pick_focus"]["distance"] == pytest.approx(3.0, abs=1e-6)
    assert "behind the camera" in preview["pick_behind"]
    assert preview["active"] == ["FINISHED"] and preview["active_focus"] == {"mode": "OBJECT", "object": "Cube"}


def test_every_lens_gets_a_psf_grid_thumbnail(preview):
    t = preview["thumbnails"]
    assert t["lenses"] >= 4 and t["first"] == [0] * t["lenses"]         # made on a thread, not while drawing
    assert t["made"] == t["lenses"] and t["sizes"] == [[95, 95]] * t["lenses"]
    assert len(t["made_calls"]) == t["lenses"] == len(set(t["made_calls"]))   # each made once
    assert t["lens_after"] == "mos-s1"


@pytest.fixture(scope="module")
def lens_changes(addon_zip, tmp_path_factory):  # noqa: F811
    pytest.importorskip("bpy")
    return run_headless("addon_headless_preview_lens.py", addon_zip, tmp_path_factory.mktemp("preview-lens"))


def test_a_lens_change_reruns_the_lens_stage_on_the_same_render(lens_changes):
    """The sharp render keeps its planar Z; a lens change (a switch: its
    refresh starts without the debounce) converts it with the new lens's
    entrance pupil and renders nothing (the pupils differ, so a depth kept
    from the first lens would show)."""
    from blender_addon import logic
    from dcdi_core.render.camera import depth_from_planar_z
    r, d = lens_changes, lens_changes["dir"]
    first = r["first"]
    assert first["error"] == "" and first["render_calls"] == 1 and first["renders"] == 1 and first["lens"] == "6p"
    rgb, z = np.load(d / "sharp_rgb.npy"), np.load(d / "sharp_z.npy")
    for name, lens_id in (("mos", "mos-s1"), ("back", "6p")):
        c = r[name]
        assert r[f"{name}_pending"] and r[f"{name}_at_once"] and c["error"] == "" and c["lens"] == lens_id, c
        assert c["render_calls"] == 1 and c["renders"] == 1 and c["version"] == 0 and c["render_s"] == 0.0, c
        lens = logic.load_lens_cached(str(ROOT / "lenses" / f"{lens_id}.toml"))
        ep = logic.lens_readout(str(ROOT / "lenses" / f"{lens_id}.toml"))["entrance_pupil_mm"]
        depth = depth_from_planar_z(z, ep, 1.0)
        assert np.array_equal(np.load(d / f"{name}_depth.npy"), depth)
        want, _ = logic.run_bokeh(rgb, depth, lens, focus_m=c["focus_m"], keep=tuple(c["keep_m"]), refocus=False,
                                  preview=True)
        assert np.abs(np.load(d / f"{name}.npy") - want).max() <= 1e-6 * max(1.0, float(want.max()))
    assert r["mos"]["refreshes"] == 2 and r["back"]["refreshes"] == 3

    pupils = [logic.lens_readout(str(ROOT / "lenses" / f"{x}.toml"))["entrance_pupil_mm"] for x in ("6p", "mos-s1")]
    assert abs(pupils[0] - pupils[1]) > 0.1, pupils                  # the lenses' pupils differ
    assert not np.array_equal(np.load(d / "mos_depth.npy"), np.load(d / "first_depth.npy"))


def test_apply_uses_the_preview_render_while_it_is_the_scene_s(lens_changes):
    """Apply Lens Bokeh with the preview on and nothing changed since its
    render runs the lens stage on that render (no render on the main
    thread); after an object moved it renders its own."""
    r, d = lens_changes, lens_changes["dir"]
    assert r["apply_kept"]["render_calls"] == 0, r["apply_kept"]
    assert r["apply_moved"]["render_calls"] == 1, r["apply_moved"]
    assert np.isfinite(np.load(d / "apply.npy")).all()


@pytest.fixture(scope="module")
def placed(addon_zip, tmp_path_factory):  # noqa: F811
    pytest.importorskip("bpy")
    return run_headless("addon_headless_placements.py", addon_zip, tmp_path_factory.mktemp("placements"))


def test_moved_objects_reach_the_workers_copy_as_placements(placed):
    """A copy written before a move, with the placements applied, is the copy
    written after it: every object (a child and a constrained one
    follow their moved parent and target), the camera's data, the render."""
    assert placed["missing"] is None and placed["names"] and placed["camera_data"]
    assert placed["camera_lens"] == 42.0
    assert placed["world_moved"] > 0.05                 # the move is seen: the test can fail
    assert placed["world_error"] <= 1e-6
    assert placed["z_error"] <= 1e-5
    d = placed["dir"]
    after, moved, before = (np.load(d / f"rgb_{n}.npy") for n in ("after", "moved", "before"))
    assert np.abs(after - moved).max() <= 1e-5 and np.abs(after - before).max() > 1e-2


def test_a_copy_without_a_moved_object_names_it(placed):
    assert placed["ghost"] == "ghost"


@pytest.fixture(scope="module")
def settings_run(addon_zip, tmp_path_factory):  # noqa: F811
    pytest.importorskip("bpy")
    return run_headless("addon_headless_settings.py", addon_zip, tmp_path_factory.mktemp("settings"))


def test_apply_at_render_size_gives_the_renders_resolution(settings_run):
    """Apply at Render Size: the result at the scene's resolution times its
    percentage (640 x 480 at 50 %), not the Preview Size (64)."""
    r = settings_run
    assert r["apply_render_size"] == ["FINISHED"]
    assert r["apply_image"] == [r["render_size"][0] // 2, r["render_size"][1] // 2], r


def test_the_focus_distance_is_measured_as_blenders_camera_measures_it(settings_run):
    """The panel's Distance 2.0, the camera's own Depth of Field distance 2.0
    and an object 2.0 in front of the camera focus alike: 2.0 from the
    camera (the entrance pupil), the lens's front that much nearer."""
    a = settings_run["agree"]
    assert a["pupil_mm"] > 10.0                               # the Tessar's: the test can tell the two apart
    for mode in ("distance", "camera", "object"):
        assert a[mode] == pytest.approx(2.0 - a["pupil_mm"] / 1000.0, abs=1e-9), (mode, a)


def test_every_setting_that_changes_the_picture_refreshes_the_preview(settings_run):
    """Each property of the panel and of the camera's Depth of Field changes
    what the preview shows (its keys, ``viewport.wanted``), except those
    ``viewport`` documents as not in the preview; a property added to the
    panel without a decision fails here. Blade Rotation included."""
    r = settings_run
    tried = set(r["panel"])
    assert tried == set(r["panel_properties"]), set(r["panel_properties"]) ^ tried
    for name, moved in r["panel"].items():
        assert moved == (name not in r["not_in_preview"]), name
    for name, moved in r["camera"].items():
        assert moved == (name not in r["camera_not_in_preview"]), name
    assert r["camera"]["aperture_rotation"]
    shaping = {"focus_distance", "focus_object", "aperture_fstop", "aperture_blades", "aperture_rotation",
               "use_dof", "aperture_ratio"}
    assert shaping <= set(r["camera_properties"])
