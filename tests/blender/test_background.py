"""The headless add-on scripts of tests/addon (pip bpy) run again in a real
Blender binary in the background, and the same assertions made on what
they saw: Apply Lens Bokeh, Lens in Renders (a still and animations, with
Cycles and with EEVEE as the scene's engine, each frame equal to `dcdi
bokeh` of its own passes), the round trip Simulate -> Correct, the scene
left as it was."""
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "addon"))

import test_addon as _addon  # noqa: E402
import test_render_hook as _hook  # noqa: E402
from headless_run import run_headless  # noqa: E402
# the fixtures by import: a conftest.py here would shadow tests/conftest.py's helpers
from realblender_support import addon_zip, blender  # noqa: E402,F401

pytestmark = pytest.mark.realblender

# the assertions of the pip bpy suite, on what the real Blender's runs saw
for _mod, _names in ((_hook, [n for n in dir(_hook) if n.startswith("test_")]),
                     (_addon, ["test_zip_installs_into_a_temporary_user_folder_and_enables",
                               "test_result_equals_the_render_in_the_kept_range_and_is_blurred_outside",
                               "test_scene_render_settings_and_camera_are_as_before",
                               "test_a_focus_on_empty_space_renders_everything_out_of_focus",
                               "test_what_cannot_work_says_why", "test_disable_leaves_nothing_registered",
                               "test_numpy_exr_reader_matches_openimageio",
                               "test_first_apply_on_a_shipped_lens_traces_nothing",
                               "test_camera_aperture_stops_the_lens_down_to_the_cameras_f_stop",
                               "test_a_catalogue_lens_stopped_down_and_refocused_traces_nothing"])):
    for _n in _names:
        globals()[_n] = getattr(_mod, _n)


@pytest.fixture(scope="module", params=["CYCLES", "BLENDER_EEVEE"])
def rendered(request, blender, addon_zip, tmp_path_factory, monkeypatch_module):
    monkeypatch_module.setenv("DCDI_TEST_RENDER_ENGINE", request.param)
    return run_headless("addon_headless_render.py", addon_zip, tmp_path_factory.mktemp(f"render-{request.param}"),
                        blender=blender)


@pytest.fixture(scope="module")
def headless(blender, addon_zip, tmp_path_factory):
    return run_headless("addon_headless.py", addon_zip, tmp_path_factory.mktemp("addon-run"), blender=blender)


@pytest.fixture(scope="module")
def monkeypatch_module():
    mp = pytest.MonkeyPatch()
    yield mp
    mp.undo()
