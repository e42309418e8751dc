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


class Heartbeat:
    """A timer on the main thread every PERIOD_S that records the gaps
    between its calls: a gap much longer than the period is a time the main
    thread ran no timers (it computed, or waited: on a lock, on the
    software rasteriser's threads, for a CPU). Each gap keeps the main
    thread's own CPU time in it and, where Linux tells (schedstat), the time
    it waited for a CPU: what is left of the gap it slept or was blocked."""

    PERIOD_S = 0.02

    def __init__(self):
        self.last = None            # (time, cpu, run-queue wait) at the last beat
        self.gaps: list = []        # (start, end, cpu_s, runq_s)
        self.tid = None

    def start(self) -> None:
        bpy.app.timers.register(self._beat, first_interval=self.PERIOD_S, persistent=True)

    def _clock(self):
        t = time.perf_counter()
        if self.tid is None:
            import threading
            self.tid = threading.get_native_id()
        try:
            run_ns, wait_ns = open(f"/proc/self/task/{self.tid}/schedstat").read().split()[:2]
            return t, int(run_ns) / 1e9, int(wait_ns) / 1e9
        except (OSError, ValueError):
            return t, time.thread_time(), 0.0

    def _beat(self):
        now = self._clock()
        if self.last is not None:
            self.gaps.append((self.last[0], now[0], now[1] - self.last[1], now[2] - self.last[2]))
        self.last = now
        return self.PERIOD_S

    def longest(self, t0: float, t1: float | None = None) -> dict:
        """The longest gap that began in [t0, t1) (from the beat before t0:
        the gap a change made at t0 falls in; not one the caller's own work
        made before it): its seconds, when it began (seconds after t0), the
        main thread's CPU and run-queue wait in it; and how many gaps
        exceeded 0.25 s."""
        t1 = time.perf_counter() if t1 is None else t1
        gaps = [g for g in self.gaps if t0 - 2 * self.PERIOD_S <= g[0] < t1]
        if not gaps:
            return {"gap_s": 0.0, "at_s": 0.0, "cpu_s": 0.0, "runq_s": 0.0, "over_025": 0, "beats": 0}
        g = max(gaps, key=lambda g: g[1] - g[0])
        return {"gap_s": round(g[1] - g[0], 3), "at_s": round(g[0] - t0, 3), "cpu_s": round(g[2], 3),
                "runq_s": round(g[3], 3), "over_025": sum(1 for x in gaps if x[1] - x[0] > 0.25),
                "beats": len(gaps)}


class CallTimer:
    """Wraps functions the add-on registers (timers, handlers, draw
    callbacks) and those they call that are to be seen apart: each call's
    seconds, and its own seconds (less the wrapped calls made inside it)."""

    def __init__(self):
        self.calls: list = []       # (start, seconds, name, own seconds)
        self._inner: list = []      # per wrapped call in progress: the seconds of the wrapped calls inside it

    def wrap(self, fn, name: str):
        def timed(*a, **k):
            t = time.perf_counter()
            self._inner.append(0.0)
            try:
                return fn(*a, **k)
            finally:
                d = time.perf_counter() - t
                inner = self._inner.pop()
                if self._inner:
                    self._inner[-1] += d
                self.calls.append((t, d, name, d - inner))
        timed.__name__ = getattr(fn, "__name__", name)
        return timed

    def longest(self, t0: float, t1: float | None = None, names=None) -> dict:
        """The call (of ``names``, else any) with the longest own seconds that began in [t0, t1)."""
        t1 = time.perf_counter() if t1 is None else t1
        calls = [c for c in self.calls if t0 <= c[0] < t1 and (names is None or c[2] in names)]
        if not calls:
            return {"call_s": 0.0, "name": None}
        c = max(calls, key=lambda c: c[3])
        return {"call_s": round(c[3], 3), "name": c[2], "with_inner_s": round(c[1], 3), "at_s": round(c[0] - t0, 3)}
