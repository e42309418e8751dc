"""Run by tests/addon/test_addon.py in a fresh interpreter, like addon_headless.py:
installs the built zip, then on the same small scene runs Simulate
Minimalist Lens and Correct Simulation (the DCDI round trip), first with
torch blocked by an import hook (Network refuses, saying what to install;
Auto and Deconvolution run the numpy deconvolution), then with torch and a
tiny exported DACN as the lens's shipped network (Network, and Auto by the
engine's rule), then with the lens's real shipped DACN (a refining one), then
with Sensor Noise; records every message Correct shows (its errors, its info
reports, the panel's lines); writes what it saw to a JSON file (pixels as
.npy beside it).

    python tests/addon/addon_headless_roundtrip.py ZIP OUT_DIR DACN_NPZ LENS
"""
import importlib
import importlib.abc
import json
import shutil
import sys
import time
from pathlib import Path

from headless_start import BLENDERS_PYTHON_LACKS, start

ZIP, OUT = start(block=[m for m in BLENDERS_PYTHON_LACKS if m != "torch"])     # torch: blocked by NoTorch below
DACN, LENS = Path(sys.argv[3]), sys.argv[4]


class NoTorch(importlib.abc.MetaPathFinder):
    """torch as absent as in Blender's own Python, until removed."""

    def find_spec(self, name, path=None, target=None):
        if name == "torch" or name.startswith("torch."):
            raise ImportError("torch is blocked: Blender's Python has none")
        return None


import bpy  # noqa: E402
import numpy as np  # noqa: E402
from addon_scene import MODULE, StubLayout, build_scene, data_counts, diff, error_of, install, snapshot  # noqa: E402

res: dict = {}
scene, cam, cube = build_scene()
res["install"], _ = install(ZIP)
SESSION = sys.modules[f"{MODULE}.session"].SESSION
logic = sys.modules[f"{MODULE}.logic"]
registry = importlib.import_module("dcdi_core.shipped")
# every info report of a finished Correct (the operator's report goes to Blender's log, not to Python)
reports = []
_correction_report = logic.correction_report


def _recorded_report(*args, **kwargs):
    reports.append(_correction_report(*args, **kwargs))
    return reports[-1]


logic.correction_report = _recorded_report
s = scene.dcdi_lens_bokeh
s.lens = LENS
s.preview_size = 128
s.samples = 4
bpy.ops.dcdi.match_camera_to_lens()


def state():
    return {"scene": snapshot(scene), "camera": snapshot(cam), "camera_data": snapshot(cam.data),
            "frame": scene.frame_current, "objects": sorted(o.name for o in bpy.data.objects)}


def images():
    return sorted(i.name for i in bpy.data.images)


def save(name, key):
    np.save(OUT / f"{key}.npy", sys.modules[f"{MODULE}.bpy_render"].get_image(name))


def draw_panel():
    """What the panel draws: [(kind, text or id, icon)]."""
    layout = StubLayout()
    sys.modules[f"{MODULE}.panel"].draw_lens_bokeh(layout, bpy.context)
    return layout.log


# Correct before any simulation: disabled, and says why
res["correct_first"] = error_of(lambda: bpy.ops.dcdi.correct_lens_simulation())
st = bpy.context.window_manager.dcdi_lens_bokeh_status


def choice(method="auto"):
    c = logic.choose_correction(method, LENS, sim["pixel_pitch_mm"])
    return [c.method, c.reason]


def correct(method, key):
    """Correct Simulation with ``method``: its result, the panel's last-method line, the image."""
    s.correction_method = method
    t = time.perf_counter()
    res[key] = sorted(bpy.ops.dcdi.correct_lens_simulation())
    res[f"{key}_s"] = time.perf_counter() - t
    res[f"{key}_line"] = st.correction
    save("Lens Corrected", f"rt-{key}")


# ------------------------------------------------------------ torch blocked
hook = NoTorch()
sys.meta_path.insert(0, hook)
before, counts, imgs = state(), data_counts(), images()
t = time.perf_counter()
res["simulate"] = sorted(bpy.ops.dcdi.simulate_lens())
res["simulate_s"] = time.perf_counter() - t
res["simulate_report_status"] = st.psf_source
res["images_after_simulate"] = images()
after_sim, imgs_sim = state(), images()
s.correction_method = "NETWORK"
res["no_torch_error"] = error_of(lambda: bpy.ops.dcdi.correct_lens_simulation())
sim = SESSION.simulation
try:                                    # the worker's path (execute after poll) says the same
    logic.choose_correction("network", LENS, sim["pixel_pitch_mm"])
    res["no_torch_run"] = None
except logic.BokehInputError as e:
    res["no_torch_run"] = str(e)
res["panel_no_torch"] = draw_panel()
s.correction_method = "AUTO"
res["no_torch_changed"] = diff(after_sim, state()) + ([] if images() == imgs_sim else [f"images: {images()}"])
res["auto_choice_no_torch"] = choice()
correct("AUTO", "deconv_auto")                   # no torch: the deconvolution
res["panel_after_deconv"] = draw_panel()
correct("DECONVOLUTION", "deconv")
s.correction_model = str(DACN)           # a network given: Auto's rule picks it, but there is no torch
correct("AUTO", "deconv_auto_given")
s.correction_model = ""
res["torch_imported_while_blocked"] = "torch" in sys.modules
res["install_command"] = logic.torch_install_command()
sys.meta_path.remove(hook)
for k, v in (("rgb", sim["rgb"]), ("depth", sim["depth"]), ("sim", sim["image"]),
             ("sensor_depth", sim["sensor_depth"])):
    np.save(OUT / f"rt-{k}.npy", v)
save("Lens Simulation", "rt-sim-image")
res["pixel_pitch_mm"] = sim["pixel_pitch_mm"]
res["geometry"] = {"height": sim["geometry"].height, "width": sim["geometry"].width,
                   "pixel_pitch_mm": sim["geometry"].pixel_pitch_mm}

# ------------------------------------------------------------ torch, the tiny DACN as the shipped one
empty, shipped = OUT / "no-weights", OUT / "weights"
empty.mkdir()
shipped.mkdir()
shutil.copy(DACN, shipped / f"dacn-{LENS}.npz")
real_weights = registry.WEIGHTS_DIR
registry.WEIGHTS_DIR = empty
s.correction_method = "NETWORK"
res["no_shipped_error"] = error_of(lambda: bpy.ops.dcdi.correct_lens_simulation())
res["panel_no_shipped"] = draw_panel()
res["auto_choice_no_network"] = choice()
registry.WEIGHTS_DIR = shipped
for run in ("cold", "warm"):
    correct("NETWORK", f"correct_{run}")
res["panel_with_torch"] = draw_panel()
res["auto_choice_with_torch"] = choice()
correct("AUTO", "auto_with_torch")
registry.WEIGHTS_DIR = empty
s.correction_model = str(DACN)           # a user's own file, no shipped one
correct("NETWORK", "correct_model_file")
correct("AUTO", "auto_given")            # with torch, Auto runs the network given
s.correction_model = str(OUT / "missing.npz")
res["missing_model_error"] = error_of(lambda: bpy.ops.dcdi.correct_lens_simulation())
res["panel_missing_model"] = draw_panel()
s.correction_model = ""
s.correction_method = "AUTO"
registry.WEIGHTS_DIR = real_weights
# the lens's real shipped network: a refining DACN (it reads the capture's deconvolution, depth and field)
res["shipped_network_error"] = error_of(lambda: correct("NETWORK", "correct_shipped"))
res["panel_shipped"] = draw_panel()
# what Correct says where it cannot run: a file that is no DACN, a lens without a shipped network
(OUT / "junk.npz").write_bytes(b"not a network")
s.correction_model = str(OUT / "junk.npz")
res["junk_model_error"] = error_of(lambda: bpy.ops.dcdi.correct_lens_simulation())
res["panel_junk_model"] = draw_panel()
s.correction_model = ""
try:
    logic.choose_correction("network", "6p", sim["pixel_pitch_mm"])
    res["no_shipped_6p"] = None
except logic.BokehInputError as e:
    res["no_shipped_6p"] = str(e)
s.correction_method = "AUTO"
res["round_trip_diff"] = diff(before, state())
res["new_data"] = {k: v - counts[k] for k, v in data_counts().items() if v != counts[k]}
res["images_before"], res["images"] = imgs, images()

# sensor noise (off by default) changes the simulation; settings again as they were
# and Correct then weighs the prior by the sensor's noise model
s.sensor_noise = True
res["simulate_noise"] = sorted(bpy.ops.dcdi.simulate_lens())
res["line_after_new_simulation"] = st.correction
save("Lens Simulation", "rt-sim-noise")
for k in ("rgb", "depth", "sensor_depth"):
    np.save(OUT / f"rt-noise-{k}.npy", SESSION.simulation[k])
correct("DECONVOLUTION", "deconv_noise")
s.sensor_noise = False
s.correction_method = "AUTO"

# disable: nothing of the add-on stays registered, the last simulation is dropped
res["disable"] = sorted(bpy.ops.preferences.addon_disable(module=MODULE))
res["leftovers"] = [n for n in dir(bpy.types) if n.startswith("DCDI_")]
res["operators_left"] = [n for n in ("simulate_lens", "correct_lens_simulation") if n in dir(bpy.ops.dcdi)]
res["simulation_kept"] = bool(SESSION.simulation)
res["correct_reports"] = reports
(OUT / "result.json").write_text(json.dumps(res, indent=1, default=str))
