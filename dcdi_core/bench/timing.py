"""Timing helpers of the benchmarks: the best of a few runs in process, and
whole processes (wall and CPU seconds) printed as rows."""
from __future__ import annotations

import math
import time


def _best(fn, repeat):
    best = math.inf
    out = None
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t)
    return best, out



def _process(cmd: list[str]) -> tuple[float, float]:
    """Wall and CPU seconds (the child's user + system) of one whole process."""
    import resource
    import subprocess
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t = time.perf_counter()
    p = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if p.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed: {p.stderr[-800:]}")
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)



def _run_rows(jobs: dict, repeat: int, quick: bool, base: float | None = None) -> None:
    """Each job once to warm the caches, then the best of ``repeat``: one line each, its goal beside."""
    for name, (cmd, goal) in jobs.items():
        _process(cmd)
        wall, cpu = min(_process(cmd) for _ in range(repeat))
        base = base or wall
        aim = "" if goal is None or quick else f"  goal <= {goal:.1f} s: {'met' if wall <= goal else 'NOT met'}"
        print(f"  {name:36s} {wall:6.2f} s ({cpu:6.2f} s CPU)  x{wall / base:5.1f} the start-up{aim}", flush=True)


