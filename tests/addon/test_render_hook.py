"""Lens in Renders under the pip bpy module (in a subprocess): a rendered
frame equals `dcdi bokeh` of the same passes, an animation's frames follow
their focus, a fixed focus builds its PSFs once, the scene's settings are
left as they were, movie outputs are refused, and disabling the add-on
removes the handlers."""
import os
import subprocess
import sys

import numpy as np
import pytest

from headless_run import run_headless
from test_addon import ROOT, addon_zip  # noqa: F401  (the zip fixture)
from blender_addon import logic


@pytest.fixture(scope="module")
def rendered(addon_zip, tmp_path_factory):  # noqa: F811
    pytest.importorskip("bpy")
    return run_headless("addon_headless_render.py", addon_zip, tmp_path_factory.mktemp("render-hook"))


def test_handlers_are_registered_with_the_add_on(rendered):
    assert rendered["install"] == ["FINISHED"]
    assert rendered["handlers_registered"] == sorted(["render_init", "frame_change_post", "render_post",
                                                      "render_write", "render_complete", "render_cancel"])


def test_a_rendered_still_equals_dcdi_bokeh_of_its_passes(rendered, tmp_path):
    from dcdi_core.io.images import read_image, write_depth, write_image
    from dcdi_core.render.camera import depth_from_planar_z
    out = rendered["dir"]
    assert rendered["still"]["error"] is None and rendered["still"]["image"]
    (frame,) = rendered["still"]["frames"]
    rgb, z = np.load(out / "still_rgb.npy"), np.load(out / "still_z.npy")
    assert rgb.shape == (120, 160, 3) and np.isfinite(rgb).all() and (z > 0).all()
    write_image(tmp_path / "aif.exr", rgb)
    write_depth(tmp_path / "depth.exr", depth_from_planar_z(z, rendered["entrance_pupil_mm"]))
    near, far = frame["keep_m"]
    cmd = [sys.executable, "-m", "dcdi_core", "bokeh", "--image", str(tmp_path / "aif.exr"), "--depth",
           str(tmp_path / "depth.exr"), "--lens", "6p", "--focus", repr(frame["focus_m"]), "--keep", repr(near),
           repr(far), "--field-step", repr(logic.FIELD_STEP_PX), "--focus-tolerance", repr(logic.FOCUS_TOLERANCE_PX),
           "-o", str(tmp_path / "cli.exr")]
    p = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT,
                       env=dict(os.environ, DCDI_CACHE_DIR=str(out / "psf-cache")))
    assert p.returncode == 0, p.stderr[-2000:]
    cli = read_image(tmp_path / "cli.exr")
    hook = read_image(out / "still.exr")                 # the file Blender wrote, replaced by the lens's frame
    assert hook.shape == cli.shape == rgb.shape
    assert np.abs(hook - cli).max() <= 1e-5 * max(1.0, float(cli.max()))
    # and it is a blur of the render, not the render itself
    assert np.abs(hook - rgb).mean() > 1e-3


def test_the_scenes_compositor_is_applied_to_the_lenss_frame(rendered):
    """An Invert node in the scene's compositor inverts the frame through
    the lens (not the plain render), and the user's File Output of the Depth
    pass writes its file; the scene's tree is the user's again afterwards,
    and the add-on's copies are gone."""
    from dcdi_core.io.images import read_image
    from dcdi_core.io import rawexr
    comp = rendered["comp"]
    assert comp["error"] is None and comp["frames"][0]["compositor"] == "applied"
    lens = read_image(rendered["dir"] / "still.exr")
    got = rawexr.read_exr_channels(rendered["dir"] / "still_comp.exr")
    got = np.stack([got[c] for c in "RGB"], axis=-1)
    inside = (lens >= 0) & (lens <= 1)
    assert inside.mean() > 0.9
    assert np.abs(got - (1 - lens))[inside].max() < 1e-4
    assert comp["tree_kept"] and comp["groups"] == ["user compositor"]
    assert not [n for n in comp["images"] if n.startswith("dcdi-pass")]
    assert len(comp["user_files"]) == 1 and comp["user_files"][0].startswith("depth")
    # the Depth the user's File Output wrote is the render's (no lens on it)
    (depth_file,) = (rendered["dir"] / "user-files").glob("*")
    ch = rawexr.read_exr_channels(depth_file)
    z = np.load(rendered["dir"] / "still_z.npy")
    written = next(v for k, v in ch.items())
    assert np.allclose(written, z, rtol=1e-5)


def test_a_compositor_that_cannot_be_kept_is_said(rendered):
    nested = rendered["nested"]
    assert nested["error"] is None
    assert "not applied" in nested["frames"][0]["compositor"] and "'inner'" in nested["frames"][0]["compositor"]


def test_an_animated_focus_object_is_followed_frame_by_frame(rendered):
    mv = rendered["moving"]
    assert mv["error"] is None and mv["files"] == ["f_0001.exr", "f_0002.exr", "f_0003.exr"]
    got = {f["frame"]: f["focus_m"] for f in mv["frames"]}
    want = {int(k): v for k, v in mv["want_focus"].items()}
    assert got.keys() == want.keys() == {1, 2, 3}
    assert all(abs(got[f] - want[f]) < 1e-6 for f in want)
    assert want[3] - want[1] == pytest.approx(1.0, abs=1e-6)         # the cube moved 1 m away
    # each new focus builds its PSFs, those of a focus within the blur tolerance shared (logic.FOCUS_TOLERANCE_PX;
    # frame 1's focus was the still's: kept); a source planned by the error budget is chosen for the request as
    # given and as planned
    used = {f["frame"]: f["focus_used_m"] for f in mv["frames"]}
    assert all(used[f] >= want[f] for f in want) and used[3] > used[1]
    assert sorted(set(mv["builds"])) == sorted({used[2], used[3]} - {used[1]})


def test_a_fixed_focus_builds_its_psfs_once_for_every_frame(rendered):
    fx = rendered["fixed"]
    assert fx["error"] is None and [f["frame"] for f in fx["frames"]] == [1, 2, 3]
    used = {f["focus_used_m"] for f in fx["frames"]}
    assert len(used) == 1 and 1.0 <= used.pop() < 1.1
    assert len(fx["builds"]) <= 1                  # once (none if an earlier job's PSFs serve 1 m)


def test_the_scenes_settings_are_left_as_the_user_set_them(rendered):
    # the Z pass, the camera's own depth of field, the compositor, lock interface: all restored
    assert rendered["settings_diff"] == []
    assert rendered["new_data"] == {"images": 1} and "Lens Render" in rendered["images"]


def test_a_movie_output_is_refused_with_what_to_do(rendered):
    msg = rendered["movie_blocker"]
    assert "image sequence" in msg or msg.startswith("no movie format in this build")


def test_the_add_ons_own_render_is_not_put_through_the_lens(rendered):
    """The preview's and Apply's all-in-focus render (a copy of the scene,
    which copies Lens in Renders) runs no lens stage: the user's last lens
    render, its result image and the session's record are left as they were."""
    own = rendered["own_render"]
    assert own["shape"] == [24, 32, 3]
    # the hook is called for the internal scene, and sees the switch off there
    assert [tuple(c) for c in rendered["own_render_calls"]] == [("dcdi-lens-bokeh-render", False)]
    assert own["last_unchanged"] and not own["run"]
    before, after = own["lens_render_size"]
    assert before == after


def test_disabling_the_add_on_removes_its_handlers(rendered):
    assert rendered["handlers_after_disable"] == []


def test_the_panel_offers_the_switch_and_asks_for_lock_interface(rendered):
    props = {t for kind, t, _ in rendered["panel_locked"] if kind == "prop"}
    assert {"lens_in_renders", "render_effect"} <= props and "use_lock_interface" not in props
    unlocked = rendered["panel_unlocked"]
    assert any(kind == "prop" and t == "use_lock_interface" for kind, t, _ in unlocked)
    assert any(kind == "label" and "Lock Interface" in t for kind, t, _ in unlocked)


def test_focus_on_click_is_offered_only_in_the_3d_view(rendered):
    """Properties > Camera has no viewport to click in: the panel there leaves
    Focus on Click out; the sidebar offers it."""
    ops = rendered["panel_operators"]
    assert "dcdi.focus_pick" in ops["sidebar"] and "dcdi.focus_pick" not in ops["properties"]
    assert "dcdi.focus_active_object" in ops["properties"]
    assert rendered["panel_in_viewport"] == {"DCDI_PT_lens_bokeh_camera": False, "DCDI_PT_lens_bokeh_sidebar": True}
