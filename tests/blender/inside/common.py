"""Shared by the scripts run inside a real Blender (tests/blender/inside/*.py):
their arguments, the add-on installed from its zip as a user does, the
test scene, and a timer-driven runner for the UI (a window's event loop
runs only between timer calls, so each step yields the seconds to wait)."""
import json
import os
import sys
import time
import traceback
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parents[1] / "addon"))          # tests/addon: the test scene, snapshots

import bpy  # noqa: E402

from addon_scene import MODULE, build_scene, data_counts, diff, install, snapshot  # noqa: E402,F401

ARGS = json.loads(os.environ["DCDI_TEST_ARGS"])
OUT = Path(ARGS["out"])
RESULT: dict = {"blender": bpy.app.version_string, "python": sys.version.split()[0]}


def write_result() -> None:
    (OUT / "result.json").write_text(json.dumps(RESULT, indent=1, default=str))


def quit_blender(code: int = 0) -> None:
    write_result() if code == 0 else None
    sys.stdout.flush()
    if bpy.app.background:
        sys.exit(code)
    os._exit(code) if code else bpy.ops.wm.quit_blender()


def run_steps(gen, first_interval: float = 1.0) -> None:
    """Drive the generator ``gen`` (it yields seconds to wait) from a timer;
    write the result and quit when it ends, exit 1 with its traceback when it
    raises."""
    def tick():
        try:
            return next(gen)
        except StopIteration:
            quit_blender(0)
        except Exception:
            traceback.print_exc()
            print("inside: failed", flush=True)
            quit_blender(1)
        return None
    bpy.app.timers.register(tick, first_interval=first_interval)


def wait_until(cond, limit_s: float, poll_s: float = 0.02):
    """A sub-generator: yields until ``cond()`` holds or ``limit_s`` passed;
    its value is the seconds waited (None when the limit passed)."""
    t = time.perf_counter()
    while not cond():
        if time.perf_counter() - t > limit_s:
            return None
        yield poll_s
    return time.perf_counter() - t
