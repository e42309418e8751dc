"""`dcdi bench cli`, `memory` and `depth`: the commands a user runs, as whole
processes (start-up, reading, PSFs, the job, writing): times beside their
goals, peak memory beside the estimate that refuses images too large."""
from __future__ import annotations

import os
import time

from .timing import _process, _run_rows


def _cli_inputs(d: str, quick: bool):
    """The bench's synthetic RGB-D written to folder ``d``: (python command, numpy-only command, image args
    of the 6P, of MOS-S1)."""
    import sys
    from ..io.images import write_depth, write_image
    from ..render.synthetic import synthetic_rgbd
    h, w = (320, 480) if quick else (1280, 1920)
    img, depth = synthetic_rgbd(h, w, seed=0)
    write_image(f"{d}/aif.exr", img)
    write_depth(f"{d}/depth.exr", depth)
    py = [sys.executable, "-m", "dcdi_core"]
    # Blender's own Python: numpy only (no scipy, no threadpoolctl)
    numpy_only = [sys.executable, "-c", "import sys, runpy; sys.modules['scipy'] = None; "
                  "sys.modules['threadpoolctl'] = None; sys.argv = ['dcdi'] + sys.argv[1:]; "
                  "runpy.run_module('dcdi_core', run_name='__main__')"]
    rgbd = ["--image", f"{d}/aif.exr", "--depth", f"{d}/depth.exr"]
    return py, numpy_only, rgbd + ["--lens", "6p"], rgbd + ["--lens", "mos-s1"]


def _goal_jobs(d: str, inputs) -> dict:
    """{row: (command, goal s)} of the rows the speed goals are set on; ``inputs``: ``_cli_inputs``'s."""
    py, numpy_only, io, mos = inputs
    keep = ["--keep", "1.0", "2.0"]
    planar = [*io[:-2], "--lens", "zeiss-planar-50mm-f1-4"]
    return {"dcdi simulate --lens mos-s1": (py + ["simulate", *mos, "-o", f"{d}/sim.exr"], GOALS["simulate"]),
            "dcdi bokeh --keep 1.0 2.0": (py + ["bokeh", *io, *keep, "-o", f"{d}/b.exr"], GOALS["bokeh"]),
            "dcdi bokeh --focus 1.5 (6P refocused: its OLF)": (py + ["bokeh", *io, "--focus", "1.5", "-o",
                                                                     f"{d}/f.exr"], GOALS["bokeh"]),
            "  the same, --quality full (no plan)": (py + ["bokeh", *io, "--focus", "1.5", "--quality", "full",
                                                          "-o", f"{d}/f.exr"], None),
            "dcdi bokeh --focus 1.5 --lens zeiss-planar-50mm-f1-4 (wide open)": (
                py + ["bokeh", *planar, "--focus", "1.5", "-o", f"{d}/p.exr"], GOALS["bokeh"]),
            "  the same, --quality full (no plan) ": (py + ["bokeh", *planar, "--focus", "1.5", "--quality", "full",
                                                          "-o", f"{d}/p.exr"], None),
            "  the same, numpy only": (numpy_only + ["bokeh", *io, *keep, "-o", f"{d}/b.exr"],
                                       GOALS["bokeh, numpy only"])}



def goal_rows(repeat: int = 2) -> int:
    """The whole-process rows the speed goals are set on (1280 x 1920, warm), each beside its goal."""
    import sys
    from ..outputs import scratch_folder
    with scratch_folder() as d:
        base, _ = min(_process([sys.executable, "-m", "dcdi_core", "--help"]) for _ in range(2))
        _run_rows(_goal_jobs(d, _cli_inputs(d, False)), repeat, False, base)
    return 0


def bench_cli(quick: bool = False, repeat: int = 2) -> int:
    """The CLI's whole processes (start-up, reading, PSFs, the job, writing)
    on a synthetic RGB-D image (seed 0) of 1280 x 1920 (320 x 480 with
    --quick), the 6P lens, PSFs from the shipped OLF: `dcdi simulate` and
    `dcdi bokeh --focus 1.5`, each run once to warm the caches, then
    ``repeat`` times (best kept). Baseline: `dcdi --help` (Python and the
    CLI's own start-up)."""
    from ..outputs import scratch_folder
    h, w = (320, 480) if quick else (1280, 1920)
    print(f"whole processes on a {h} x {w} synthetic RGB-D (seed 0), 6P, {os.cpu_count()} CPU(s), "
          f"load average {os.getloadavg()[0]:.1f}; wall (CPU) seconds, best of {repeat} after a warm-up run")
    with scratch_folder() as d:
        inputs = _cli_inputs(d, quick)
        py, io = inputs[0], inputs[2]
        jobs = {"dcdi --help (start-up)": (py + ["--help"], None),
                "dcdi simulate": (py + ["simulate", *io, "-o", f"{d}/sim.exr"], None),
                "dcdi bokeh --focus 1.5": (py + ["bokeh", *io, "--focus", "1.5", "-o", f"{d}/bokeh.exr"], None),
                **_goal_jobs(d, inputs),
                "dcdi bokeh --keep 1.0 2.0 --plain": (py + ["bokeh", *io, "--keep", "1.0", "2.0", "--plain", "-o",
                                                            f"{d}/b.exr"], None)}
        _run_rows(jobs, repeat, quick)
    return 0


# whole processes at 1280 x 1920 on 2 cores, caches warm (`dcdi bench cli`)
GOALS = {"simulate": 2.0, "bokeh": 3.0, "bokeh, numpy only": 4.5}


# Linux counts a forked child's peak from its parent's size at the fork (and
# keeps it across exec): the job is started by a small helper process, so its
# peak is its own
_PEAK_HELPER = """
import os, subprocess, sys
p = subprocess.Popen(sys.argv[1:], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
_, status, usage = os.wait4(p.pid, 0)
err = p.stderr.read().decode(errors="replace")
code = os.waitstatus_to_exitcode(status)
print(usage.ru_maxrss if code == 0 else "failed " + err[-800:])
"""


def _peak_rss_bytes(cmd: list[str]) -> int:
    """The peak resident memory (bytes) of one whole process ``cmd``."""
    import subprocess
    import sys
    out = subprocess.run([sys.executable, "-S", "-c", _PEAK_HELPER, *cmd], capture_output=True, text=True).stdout
    if out.startswith("failed"):
        raise RuntimeError(f"{' '.join(cmd)} failed: {out[7:]}")
    return int(out) * 1024                      # Linux reports KiB


def bench_memory(quick: bool = False) -> int:
    """Peak RSS of `dcdi simulate`, `bokeh --keep 0.9 1.1` and `correct
    --method deconv` (MOS-S1, its PSF basis) on the synthetic scene at two
    sizes; their growth per pixel is what the job needs per pixel, printed
    beside ``memory.JOB_BYTES_PER_PIXEL`` (the estimate that refuses an image
    too large before it is read)."""
    import sys
    from ..outputs import scratch_folder
    from ..io.images import write_depth, write_image
    from ..memory import JOB_BYTES_PER_PIXEL, gib
    from ..render.synthetic import synthetic_rgbd
    sizes = [(160, 240), (640, 960)] if quick else [(320, 480), (1280, 1920)]
    jobs = {"simulate": ["--psf-source", "basis"], "bokeh": ["--keep", "0.9", "1.1", "--psf-source", "basis"],
            "correct": ["--method", "deconv", "--psf-source", "basis"]}
    print(f"peak RSS (wait4) of whole processes, MOS-S1 and its PSF basis, synthetic scene (seed 1) at "
          f"{sizes[0][0]} x {sizes[0][1]} and {sizes[1][0]} x {sizes[1][1]}")
    print("| job | small | large | bytes per pixel (growth) | estimate used |")
    print("|---|---|---|---|---|")
    with scratch_folder() as d:
        for h, w in sizes:
            img, depth = synthetic_rgbd(h, w, seed=1)
            write_image(f"{d}/{h}.exr", img)
            write_depth(f"{d}/{h}_d.exr", depth)
        for job, extra in jobs.items():
            peaks = [_peak_rss_bytes([sys.executable, "-m", "dcdi_core", job, "--image", f"{d}/{h}.exr", "--depth",
                                      f"{d}/{h}_d.exr", "--lens", "mos-s1", *extra, "-o", f"{d}/out.exr"])
                     for h, w in sizes]
            per_px = (peaks[1] - peaks[0]) / (sizes[1][0] * sizes[1][1] - sizes[0][0] * sizes[0][1])
            print(f"| {job} | {gib(peaks[0])} | {gib(peaks[1])} | {per_px:.0f} | {JOB_BYTES_PER_PIXEL[job]} |")
    return 0


DEPTH_GOAL_S = 10.0       # `dcdi depth estimate` at 1280 x 1920, whole process


def bench_depth(quick: bool = False, repeat: int = 2) -> int:
    """`dcdi depth estimate` (the depth from a capture's own blur, MOS-S1):
    whole processes on a synthetic capture (the bench's RGB-D simulated
    through MOS-S1 at 12.2 um with sensor noise) of 1280 x 1920 (320 x 480
    with --quick), once to warm the caches then the best of ``repeat``,
    beside its goal and the start-up; then one run in process, its stages."""
    import sys
    from ..outputs import scratch_folder

    from ..dfd import estimate_depth
    from ..io.images import write_image
    from ..optics.lens import load_lens
    from ..render.geometry import ImageGeometry
    from ..render.noise import add_sensor_noise
    from ..render.simulate import SimulateOptions, simulate
    from ..render.synthetic import synthetic_rgbd
    from ..app import PSFRequest, open_source
    h, w = (320, 480) if quick else (1280, 1920)
    lens = load_lens("mos-s1")
    g = ImageGeometry.from_pixel_pitch(lens, h, w, 0.0122)
    library = open_source(lens, g, PSFRequest()).library
    img, depth = synthetic_rgbd(h, w, seed=0)
    capture = add_sensor_noise(simulate(img, depth, lens, SimulateOptions(geometry=g), library=library).image, seed=1)
    print(f"bench depth: dcdi depth estimate, MOS-S1, a {h} x {w} synthetic capture at 12.2 um with noise, "
          f"{os.cpu_count()} CPU(s), load average {os.getloadavg()[0]:.1f}; wall (CPU) seconds, best of {repeat} "
          "after a warm-up run")
    with scratch_folder() as d:
        write_image(f"{d}/cap.exr", capture)
        py = [sys.executable, "-m", "dcdi_core"]
        base, _ = min(_process(py + ["--help"]) for _ in range(2))
        cmd = py + ["depth", "estimate", "--image", f"{d}/cap.exr", "--camera", "mos-s1", "--pixel-pitch",
                    "0.0122", "-o", f"{d}/d.exr"]
        _run_rows({"dcdi --help (start-up)": (py + ["--help"], None),
                   "dcdi depth estimate": (cmd, None if quick else DEPTH_GOAL_S)}, repeat, quick, base)
    t, c = time.perf_counter(), time.process_time()
    est = estimate_depth(capture, library, g)
    stages = ", ".join(f"{k} {v:.2f}" for k, v in est.info["seconds"].items())
    print(f"  in process: {time.perf_counter() - t:.2f} s ({time.process_time() - c:.2f} s CPU): {stages}")
    return 0


