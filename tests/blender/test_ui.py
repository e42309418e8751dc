"""The add-on's UI in a real Blender with a window (Xvfb, software OpenGL):
the viewport preview follows every change and draws the engine's result."""
import os
import warnings

import numpy as np
import pytest

# the fixtures by import: a conftest.py here would shadow tests/conftest.py's helpers
from realblender_support import addon_zip, blender, run_inside  # noqa: F401
from dcdi_core.io.images import linear_to_srgb, read_image

pytestmark = pytest.mark.realblender

# the drawn preview against the engine's result, sRGB-encoded in [0, 1]: the
# texture is drawn scaled to the camera frame with linear filtering, then
# stored in 8 bits, so edges differ by up to a pixel's blend and every value by
# up to half a level
SCREEN_MEAN_TOL = 0.02
SCREEN_P99_TOL = 0.12
# the longest a refresh may take after a change (a refocused minimalist lens traces its PSFs: about 10 s on
# 2 busy cores); $DCDI_TEST_REFRESH_LIMIT_S shortens it to show the test failing on a build that never refreshes
REFRESH_LIMIT_S = float(os.environ.get("DCDI_TEST_REFRESH_LIMIT_S", 60))
# the 3D view's shading through the preview's changes ($DCDI_TEST_PREVIEW_SHADING: MATERIAL to measure
# Blender's EEVEE drawing on software OpenGL)
PREVIEW_SHADING = os.environ.get("DCDI_TEST_PREVIEW_SHADING", "SOLID")


def _resample(img: np.ndarray, h: int, w: int) -> np.ndarray:
    """Bilinear resampling of (H, W, 3) to (h, w, 3), pixel centres aligned (as a scaled texture is drawn)."""
    H, W = img.shape[:2]
    y = np.clip((np.arange(h) + 0.5) * H / h - 0.5, 0, H - 1)
    x = np.clip((np.arange(w) + 0.5) * W / w - 0.5, 0, W - 1)
    y0, x0 = np.floor(y).astype(int), np.floor(x).astype(int)
    y1, x1 = np.minimum(y0 + 1, H - 1), np.minimum(x0 + 1, W - 1)
    fy, fx = (y - y0)[:, None, None], (x - x0)[None, :, None]
    top = img[y0][:, x0] * (1 - fx) + img[y0][:, x1] * fx
    bot = img[y1][:, x0] * (1 - fx) + img[y1][:, x1] * fx
    return top * (1 - fy) + bot * fy


def screen_error(work, cap) -> tuple[float, float]:
    """(mean, 99th percentile) |screen - the preview's texture| inside the
    camera frame (3 px in from its border: the frame's outline), display
    values in [0, 1]. The texture holds the engine's result as the add-on
    encodes it for display (read back from the GPU); a capture without it
    (an older build) is compared with the result sRGB-encoded."""
    shot = linear_to_srgb(read_image(work / cap["png"]))
    left, top, right, bottom = cap["box"]
    l, t, r, b = int(np.ceil(left)) + 3, int(np.ceil(top)) + 3, int(np.floor(right)) - 3, int(np.floor(bottom)) - 3
    drawn = shot[t:b, l:r]
    engine = np.load(work / cap["texture"]) if cap.get("texture") else \
        linear_to_srgb(np.clip(np.load(work / cap["npy"]), 0.0, None))
    # the engine's image over the whole frame, then the same inset
    full = _resample(engine, int(round(bottom - top)), int(round(right - left)))
    ref = full[t - int(round(top)):b - int(round(top)), l - int(round(left)):r - int(round(left))]
    h, w = min(drawn.shape[0], ref.shape[0]), min(drawn.shape[1], ref.shape[1])
    err = np.abs(drawn[:h, :w] - ref[:h, :w])
    return float(err.mean()), float(np.percentile(err, 99))


@pytest.fixture(scope="module")
def preview_run(blender, addon_zip, tmp_path_factory):
    work = tmp_path_factory.mktemp("ui-preview")
    return work, run_inside(blender, "ui_preview.py", work, {"zip": str(addon_zip), "lens": "6p",
                                                             "preview_size": 480, "resolution": [1920, 1080],
                                                             "refresh_limit_s": REFRESH_LIMIT_S,
                                                             "shading": PREVIEW_SHADING}, ui=True)


def test_preview_follows_every_change(preview_run):
    _, res = preview_run
    changes = res["changes"]
    assert len(changes) >= 25, changes
    for c in changes:
        assert c["refreshed"], f"the preview did not refresh after: {c['change']} ({c['via']}); {c}"
        assert c["current"], f"after {c['change']} the preview shows another request: {c}"
        assert not c["error"], c


def test_preview_lens_only_changes_do_not_render(preview_run):
    _, res = preview_run
    by = {(c["via"], c["change"]): c for c in res["changes"]}
    lens_only = [("python", n) for n in ("focus distance", "focus distance again", "camera focus distance",
                                         "kept range", "refocus off", "refocus on", "lens", "lens again",
                                         "frame change")]
    lens_only += [("ui", n) for n in ("focus distance", "kept range", "refocus off", "lens", "focus mode next",
                                      "focus mode next again", "frame change")]
    for key in lens_only:
        assert not by[key]["rendered"], f"{key} rendered the scene anew: {by[key]}"
    for key in [("python", "toggle"), ("python", "object moved"), ("python", "preview size"), ("ui", "object moved"),
                ("ui", "preview size")]:
        assert by[key]["rendered"], by[key]
    py = {n: c for (v, n), c in by.items() if v == "python"}
    assert _from_camera(py["frame change"]) == pytest.approx(4.0, abs=1e-3)
    assert _from_camera(py["keyframed focus, frame 1"]) == pytest.approx(1.0, abs=1e-3)
    assert _from_camera(py["focus distance"]) == pytest.approx(2.5, abs=1e-6)
    assert py["kept range"]["shown"]["keep_m"][1] == pytest.approx(py["kept range"]["shown"]["focus_m"] + 1.5)
    assert py["refocus off"]["shown"]["refocus"] is False
    assert py["preview size"]["shown"]["shape"][1] == 240


# the preview's steps the main thread's heartbeat is judged in
PREVIEW_STEPS = [("python", n) for n in ("toggle", "focus distance", "focus distance again", "lens", "lens again",
                                         "object moved", "preview size")]
PREVIEW_STEPS += [("ui", n) for n in ("focus distance", "lens", "object moved", "preview size")]
BLOCK_GOAL_S = 0.25          # the longest the main thread may stop during the preview's steps (a goal)
# what the heartbeat test fails on: Blender not answering for a second (before the render worker: 1.1-3.5 s
# at every step). The goal above is a benchmark (measured 0.15-0.25 s, one drawing of the 3D view alone on
# llvmpipe taking 0.14-0.18 s of it): a step over it is reported as a warning, not a failure, since a
# redraw on a shared 2-core machine passes it by a few milliseconds at random
FREEZE_LIMIT_S = 1.0
FIRST_GOAL_S = 1.0           # the toggle to the first result drawn; a lens change to its result drawn


def _from_camera(change) -> float:
    """The shown focus (m from the lens's front) as the panel's Distance measures it: from the camera (the
    entrance pupil, ``pupil_mm`` behind the lens's front), as Blender's depth of field does."""
    shown = change["shown"]
    return shown["focus_m"] + shown["pupil_mm"] / 1000.0


def _steps(res, keys):
    by = {(c["via"], c["change"]): c for c in res["changes"]}
    return [by[k] for k in keys]


def test_the_add_on_holds_the_main_thread_briefly(preview_run):
    """Every call of the add-on's timers, handlers and draw callbacks
    returned within the goal (its own time: the result's texture, made
    inside one, is judged below), through every change, and no sharp render
    ran on the main thread (the render worker made them all)."""
    _, res = preview_run
    for c in res["changes"]:
        if "the worker failing" in c["change"] or c["change"] == "object moved after":
            continue                         # the main thread renders (test_the_preview_renders_itself_...)
        assert c["addon_call"]["call_s"] <= BLOCK_GOAL_S, (c["via"], c["change"], c["addon_call"])
        if c.get("rendered"):
            assert c["source"] == "worker" and c["main_render"] is False and c["main_s"] <= 0.1, c


def test_the_preview_accumulates_passes_while_nothing_changes(preview_run):
    """Left alone after a change, the preview renders the same view again
    with other seeds (ACCUMULATE_PASSES in all) and shows the lens on their
    mean, nearer a render of as many samples than the first pass; the
    passes are not counted as renders, the main thread answers meanwhile."""
    _, res = preview_run
    acc = res["accumulation"]
    assert acc["first_pass_kept"] and acc["seconds"] is not None, acc
    assert acc["passes"] == acc["wanted"] >= 4 and acc["shown_passes"] == acc["wanted"], acc
    assert acc["mean_rms"] < acc["first_rms"] / 1.5, acc
    assert acc["heartbeat"]["gap_s"] < 0.5, acc


def test_blade_rotation_refreshes_the_preview(preview_run):
    """Turning the camera's blades (Camera Aperture on, a catalogue lens at
    f/8 with six blades) refreshes the preview with the lens stage alone."""
    _, res = preview_run
    stopped, turned = _steps(res, [("python", "camera aperture, 6 blades"), ("python", "blade rotation")])
    assert stopped["refreshed"] and stopped["error"] == "", stopped
    assert turned["refreshed"] and turned["current"] and not turned["rendered"] and turned["lens_s"] > 0, turned


def test_a_move_reaches_the_worker_as_placements(preview_run):
    """The toggle's render writes the scene's copy for the render worker; an
    object moved, or the camera's framing (the preview size), sends
    placements to that copy instead of writing it again (a production
    scene's copy takes seconds to write: docs/addon.md)."""
    _, res = preview_run
    toggle, moved = _steps(res, [("python", "toggle"), ("python", "object moved")])
    assert toggle["rendered"] and toggle["render_steps"]["wrote"] is True, toggle
    assert moved["rendered"] and moved["render_steps"]["wrote"] is False, moved
    assert moved["shown"] and moved["error"] == "", moved


def test_the_preview_renders_itself_when_the_worker_fails(preview_run):
    _, res = preview_run
    by = {c["change"]: c for c in res["changes"] if c["via"] == "python"}
    for name in ("object moved, the worker failing", "object moved after"):
        c = by[name]
        assert c["refreshed"] and c["current"] and c["rendered"] and c["source"] == "main" and c["main_render"], c
    assert res["worker_failed"] == "a failure made by the test"


def test_the_result_texture_is_made_briefly(preview_run):
    """The result's display values (the scene's view transform applied: 0.1-0.3
    s at 480 x 270 on these 2 cores) are made on the lens stage's thread with
    the table kept; the main thread makes the texture alone. The view-transform
    table is baked by the render worker, not here (it was 0.41-0.57 s on the
    main thread at the toggle). The texture call's time over the 0.25 s goal is
    a warning: it varies with the machine's load (0.29 s once on CI when this
    test timed the whole display on the main thread)."""
    _, res = preview_run
    lens_steps = [c for c in res["changes"] if c.get("refreshed") and c.get("lens_s", 0) > 0]
    assert lens_steps, res["changes"]
    made_here = {f"{c['via']} {c['change']}": c.get("display_ahead") for c in lens_steps if not c.get("display_ahead")}
    assert not made_here, made_here
    slow = {f"{c['via']} {c['change']}": c["texture_call"] for c in res["changes"]
            if c["texture_call"]["call_s"] > BLOCK_GOAL_S}
    if slow:
        warnings.warn(f"the result's texture took over the {BLOCK_GOAL_S} s goal: {slow}")


def test_the_main_thread_never_stops_during_the_preview(preview_run):
    """The heartbeat (a 20 ms timer on the main thread) never waited a
    second from a change to its result drawn (the freeze this replaced:
    1.1-3.5 s). Gaps over the 0.25 s goal are reported as a warning with
    Blender's own drawing time beside them. (The Solid view's anti-aliasing,
    which draws the view 8 more times after each change, is off:
    ui_preview.py.)"""
    _, res = preview_run
    gaps = {f"{c['via']} {c['change']}": c["heartbeat"] for c in _steps(res, PREVIEW_STEPS)}
    context = {"idle": res["idle_heartbeat"], "one 3D view drawing": res["redraw_heartbeat"]}
    frozen = {k: g for k, g in gaps.items() if g["gap_s"] > FREEZE_LIMIT_S}
    assert not frozen, (frozen, context)
    over = {k: g["gap_s"] for k, g in gaps.items() if g["gap_s"] > BLOCK_GOAL_S}
    if over:
        warnings.warn(f"main-thread gaps over the {BLOCK_GOAL_S} s goal: {over}; "
                      f"one 3D view drawing: {res['redraw_heartbeat']['gap_s']} s")


def test_the_toggle_finds_the_worker_warm(preview_run):
    """Drawn, the panel starts the render worker (viewport.warm_up), which
    bakes the view-transform table ahead: the toggle's first render asks
    for no bake and no start."""
    _, res = preview_run
    assert res["warm_table"], res.get("warm_s")
    toggle = _steps(res, [("python", "toggle")])[0]
    assert toggle["source"] == "worker" and toggle["render_steps"]["baked"] is False, toggle


@pytest.mark.xfail(strict=False, reason="measured in Debian's Blender 5.2.2 on llvmpipe, 2 cores: the first result "
                                        "drawn 1.9-2.4 s after the toggle (the render worker's start 0.8 s, the "
                                        "lens 0.4-0.5 s, the view-transform bake there 0.4 s); a lens change "
                                        "0.4-0.8 s through Python, 2.6-3.0 s through the panel (the new lens's "
                                        "PSFs: its lens stage 2.2-2.6 s)")
def test_the_first_result_and_a_lens_change_within_a_second(preview_run):
    _, res = preview_run
    slow = {f"{c['via']} {c['change']}": c["drawn_s"] for c in _steps(res, [("python", "toggle"), ("python", "lens"),
                                                                          ("python", "lens again"), ("ui", "lens")])
            if c["drawn_s"] is None or c["drawn_s"] > FIRST_GOAL_S}
    assert not slow, slow


def test_the_gpu_planar_z_equals_the_cycles_z_pass(preview_run):
    """The planar Z drawn on the GPU (tests/blender/inside/gpu_capture.py)
    against Cycles's Z pass of the same camera, on the test scene with a
    subdivided sphere and a tilted plane: equal to float precision inside
    surfaces, apart only on silhouette pixels. (Solid shading's colour is
    nothing like the render: why the preview does not take its colour from
    the GPU.)"""
    _, res = preview_run
    d = res["depth_check"]
    assert d["background_mismatch"] == 0 and d["median_rel"] <= 1e-5 and d["interior_max_rel"] <= 1e-4, d
    assert d["over_1pct_interior"] == 0 and d["over_1pct"] <= 0.02 * d["edge_pixels"], d
    assert d["gpu_s"] < d["cycles_s"], d
    if d["shading"] == "SOLID":
        assert d["colour_mean_abs"] > 0.1, d


def test_changes_through_the_ui_took_effect(preview_run):
    """The widgets were really used: each change shows in what the preview drew."""
    _, res = preview_run
    ui = {c["change"]: c for c in res["changes"] if c["via"] == "ui"}
    assert _from_camera(ui["focus distance"]) == pytest.approx(3.0, abs=1e-6)
    kept = ui["kept range"]["shown"]
    assert kept["keep_m"][0] == pytest.approx(kept["focus_m"] - 0.4, abs=1e-6)
    assert ui["refocus off"]["shown"]["refocus"] is False
    assert ui["preview size"]["shown"]["shape"][1] == 300
    assert res["ui_lens"] != "mos-s2" and res["ui_focus_mode_1"] == "OBJECT" and res["ui_focus_mode"] == "CAMERA"
    assert res["ui_moved_by"] == pytest.approx(0.1, abs=1e-6) and res["ui_frame"] == 1
    assert _from_camera(ui["frame change"]) == pytest.approx(1.0, abs=1e-3)


def test_preview_drawn_pixels_equal_the_engine_result(preview_run):
    """The screen inside the camera frame shows the preview's texture, and
    that texture was made of the engine's result shown (its display
    encoding is tested with the view transform's own tests)."""
    work, res = preview_run
    for key in ("first_capture", "focus_capture"):
        mean, p99 = screen_error(work, res[key])
        assert mean <= SCREEN_MEAN_TOL and p99 <= SCREEN_P99_TOL, (key, mean, p99)
        assert res[key]["texture_of_result"], key


def _nearest(img: np.ndarray, h: int, w: int) -> np.ndarray:
    """Nearest-neighbour resampling of (H, W, 3) to (h, w, 3): a texture drawn unfiltered."""
    H, W = img.shape[:2]
    y = np.minimum(((np.arange(h) + 0.5) * H / h).astype(int), H - 1)
    x = np.minimum(((np.arange(w) + 0.5) * W / w).astype(int), W - 1)
    return img[y][:, x]


def test_the_preview_is_drawn_smoothly_upscaled(preview_run):
    """The 480 x 270 result drawn over a larger camera frame is interpolated
    (the texture's linear filter), not shown in blocks: the screen is nearer
    the bilinear upscale of the texture than its nearest-neighbour one,
    where the two differ (measured: 0.010-0.011 against 0.029-0.033)."""
    work, res = preview_run
    for key in ("first_capture", "focus_capture"):
        cap = res[key]
        shot = linear_to_srgb(read_image(work / cap["png"]))
        left, top, right, bottom = cap["box"]
        l, t, r, b = (int(np.ceil(left)) + 3, int(np.ceil(top)) + 3, int(np.floor(right)) - 3,
                      int(np.floor(bottom)) - 3)
        drawn = shot[t:b, l:r]
        tex = np.load(work / cap["texture"])
        size = (int(round(bottom - top)), int(round(right - left)))
        assert size[1] > 1.5 * tex.shape[1], size              # drawn larger than it is: the test can tell
        refs = {}
        for name, resample in (("bilinear", _resample), ("nearest", _nearest)):
            refs[name] = resample(tex, *size)[t - int(round(top)):b - int(round(top)),
                                              l - int(round(left)):r - int(round(left))]
        hh = min(drawn.shape[0], *(v.shape[0] for v in refs.values()))
        ww = min(drawn.shape[1], *(v.shape[1] for v in refs.values()))
        differ = np.abs(refs["bilinear"][:hh, :ww] - refs["nearest"][:hh, :ww]).max(-1) > 0.02
        assert differ.mean() > 0.01, differ.mean()
        err = {n: float(np.abs(drawn[:hh, :ww] - v[:hh, :ww])[differ].mean()) for n, v in refs.items()}
        assert err["bilinear"] < 0.5 * err["nearest"], (key, err)


def test_preview_off_removes_its_handlers(preview_run):
    _, res = preview_run
    assert res["after_off"] == {"enabled": False, "handlers": [False]}


@pytest.fixture(scope="module")
def operators_run(blender, addon_zip, tmp_path_factory):
    work = tmp_path_factory.mktemp("ui-operators")
    return work, run_inside(blender, "ui_operators.py", work, {"zip": str(addon_zip)}, ui=True,
                            extra=("--enable-event-simulate",))


def test_buttons_run_as_clicks_with_progress(operators_run):
    _, res = operators_run
    jobs = {j["job"]: j for j in res["jobs"]}
    assert set(jobs) == {"apply", "simulate", "correct auto", "correct deconvolution", "apply, render by the worker",
                         "apply, render by the main"}
    for j in jobs.values():
        assert j["started"] == ["RUNNING_MODAL"], j
        assert not j["running_after"] and j["workers_left"] == 0 and j["message"].startswith("done"), j
    assert res["bokeh_image"] == [240, 180] and res["bokeh_finite"]
    assert res["corrections"]["AUTO"].startswith("Deconvolution") and res["corrections"]["DECONVOLUTION"]
    assert res["new_images"] == ["Lens Bokeh", "Lens Corrected", "Lens Simulation"]


def test_a_click_returns_at_once_and_says_what_runs(operators_run):
    """A button's click returns before the job's render and checks: the
    status already says what runs (and the button is released), the job
    prepares at the modal timer's first event (it held the main thread for
    the render, 0.4-1.5 s, with no word said)."""
    _, res = operators_run
    for j in res["jobs"]:
        assert j["click_s"] <= BLOCK_GOAL_S, j
        assert j["after_click"]["running"] and j["after_click"]["message"].endswith("..."), j


def test_apply_renders_in_the_second_blender_while_the_main_thread_answers(operators_run):
    """With the render worker running (the panel starts it), Apply Lens
    Bokeh's sharp render at 640 px and 64 samples is made there: the main
    thread's longest gap stays under a second and under that of the same
    Apply rendered on the main thread (no worker), which holds it for the
    render."""
    _, res = operators_run
    by = res["apply_render"]
    assert by["worker"]["render"]["how"] == "worker" and by["main"]["render"]["how"] == "main", by
    jobs = {j["job"]: j for j in res["jobs"]}
    assert jobs["apply, render by the worker"]["message"].startswith("done"), jobs
    assert by["worker"]["heartbeat"]["gap_s"] < by["main"]["heartbeat"]["gap_s"], by
    assert by["worker"]["heartbeat"]["gap_s"] <= FREEZE_LIMIT_S, by


def test_esc_cancels_a_running_bokeh(operators_run):
    _, res = operators_run
    assert res["esc_started"] == ["RUNNING_MODAL"] and res["esc_workers_before"] == 1
    assert res["esc_running_before"], "the status said no job runs while one did (the last job's modal ran again)"
    before = res["esc_progress_before"]                      # the progress the status showed before Esc
    assert 0 < before["progress"] < 100 and "Esc cancels" in before["message"], before
    assert res["esc"]["running"] is False and res["esc"]["message"] == "cancelled"
    assert res["esc"]["workers_left"] == 0


def test_the_scene_is_as_before_the_clicks(operators_run):
    _, res = operators_run
    assert res["settings_diff"] == []
