"""`python -m lab walk`: follow a job from its front end down through the
layers of docs/design.md and count where it crosses them.

Every Python call between two modules of the project is one step of the
walk, placed by the layer of each module (``lab.layers``). Two figures say
whether a front end hands a job over whole:

- **into app**: calls from a front end (the `dcdi` command, the add-on) into
  the application layer. A job handed over whole crosses once.
- **climbs**: calls from a lower layer into a higher one. The engine never
  imports upward, so a climb is a function a higher layer handed down: the
  job's ``Control`` (progress, notes, cancel: partial results, reported as
  they come) or anything else, which would be a decision taken back up.

Returns are the other way back up: a result returning is not a climb.

The two walks measured, on a 48 x 64 synthetic RGB-D scene:

- ``dof``: ``dcdi dof`` from the command line (``cli.main``), the capture
  given with its depth, the camera MOS-S1 corrected, the 6P's depth of field;
- ``bokeh``: the add-on's Apply Lens Bokeh below Blender (its render read;
  ``blender_addon.logic.run_bokeh``, what the operator calls with the
  render's pixels), the 6P focused at 2 m.

    python -m lab walk [--job dof|bokeh] [--json]
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

from .layers import TOP, layer_of, layers

APP = 5              # the application layer's number in docs/design.md
FRONT_ENDS = ("dcdi_core.cli", "blender_addon")


@dataclass
class Walk:
    """The steps of one job: ``into_app`` ((kind, caller -> callee) of each
    call from a front end into app; kind 'job', 'request' or 'result'), ``climbs`` ({caller -> callee: calls}),
    ``past_app`` ({engine function below app: calls from a front end}:
    its own input, files read and request parts made),
    ``crossings`` (calls between two layers, either way down or up),
    ``down`` ({(from layer, to layer): calls})."""

    job: str
    into_app: list = field(default_factory=list)
    past_app: Counter = field(default_factory=Counter)
    climbs: Counter = field(default_factory=Counter)
    crossings: int = 0
    down: Counter = field(default_factory=Counter)

    def count(self, kind: str) -> int:
        return sum(1 for k, _ in self.into_app if k == kind)

    def as_dict(self) -> dict:
        return {"job": self.job, "into_app": self.into_app,
                "into_app_count": {k: self.count(k) for k in ("job", "request", "result")},
                "past_app": dict(self.past_app), "climbs": dict(self.climbs), "climb_count": sum(self.climbs.values()), "crossings": self.crossings,
                "down": {f"{a}->{b}": n for (a, b), n in sorted(self.down.items())}}


def _kind(frame) -> str | None:
    """What a call into app is: 'job' (a module's function: the job, or a
    question it answers), 'request' (making or checking a request object),
    'result' (reading a result object); None for a module run on import."""
    if frame.f_code.co_name == "<module>":
        return None
    owner = type(frame.f_locals["self"]).__name__ if "self" in frame.f_code.co_varnames[:1] else ""
    if owner.endswith("Request"):
        return "request"
    if owner.endswith("Result"):
        return "result"
    return "job"


def _name(frame) -> str:
    return frame.f_globals.get("__name__", "")


def _ours(name: str) -> bool:
    return name.split(".")[0] in TOP


def follow(job: str, run) -> Walk:
    """The :class:`Walk` of ``run()`` (a callable), every call between two
    modules of the project counted (the caller: the nearest frame of the
    project's, past numpy's and the standard library's)."""
    table = layers()
    walk = Walk(job)
    placed: dict[str, int | None] = {}

    def layer(name):
        if name not in placed:
            placed[name] = layer_of(name, table)
        return placed[name]

    def profile(frame, event, arg):
        if event != "call":
            return
        callee = _name(frame)
        if not _ours(callee):
            return
        back = frame.f_back
        while back is not None and not _ours(_name(back)):
            back = back.f_back
        if back is None:
            return
        caller = _name(back)
        if caller == callee:
            return
        a, b = layer(caller), layer(callee)
        if a is None or b is None or a == b:
            return
        walk.crossings += 1
        where = f"{caller}.{back.f_code.co_name} -> {callee}.{frame.f_code.co_name}"
        if b > a:
            walk.climbs[where] += 1
            return
        walk.down[a, b] += 1
        if b == APP and any(caller == f or caller.startswith(f + ".") for f in FRONT_ENDS):
            kind = _kind(frame)
            if kind is not None:
                walk.into_app.append((kind, where))
        elif b < APP and a > APP and any(caller == f or caller.startswith(f + ".") for f in FRONT_ENDS):
            if frame.f_code.co_name != "<module>":
                walk.past_app[f"{callee}.{frame.f_code.co_qualname.split('.<locals>')[0]}"] += 1

    sys.setprofile(profile)
    try:
        run()
    finally:
        sys.setprofile(None)
    return walk


def _scene(folder: Path):
    from dcdi_core.io.images import write_depth, write_image
    from dcdi_core.render.synthetic import synthetic_rgbd
    img, depth = synthetic_rgbd(48, 64, seed=1)
    write_image(folder / "aif.exr", img)
    write_depth(folder / "depth.exr", depth)
    return img, depth


def walk_dof(folder: Path) -> Walk:
    """`dcdi dof` from the command line, in this process."""
    from dcdi_core.cli import main
    _scene(folder)
    argv = ["dof", "--image", str(folder / "aif.exr"), "--depth", str(folder / "depth.exr"), "--camera", "mos-s1",
            "--lens", "6p", "--keep", "0.7", "1.5", "--method", "deconv", "-o", str(folder / "dof.exr")]
    import contextlib
    import io
    codes = []
    with contextlib.redirect_stdout(io.StringIO()):          # the command's JSON: not the walk's
        w = follow("dcdi dof", lambda: codes.append(main(argv)))
    if codes != [0]:
        raise RuntimeError(f"dcdi dof failed (exit {codes})")
    return w


def walk_bokeh(folder: Path) -> Walk:
    """Apply Lens Bokeh below Blender: ``logic.run_bokeh`` with a render's pixels."""
    from blender_addon import logic
    img, depth = _scene(folder)
    lens = logic.load_lens_cached(logic.lens_file("6p"))
    return follow("Apply Lens Bokeh", lambda: logic.run_bokeh(img, depth, lens, focus_m=2.0, keep=(1.8, 2.2)))


JOBS = {"dof": walk_dof, "bokeh": walk_bokeh}


def table(walks: list[Walk]) -> str:
    """A markdown table of the walks."""
    rows = ["| walk | calls between layers | into app: jobs / requests made / results read | climbs | what climbs |",
            "|---|---|---|---|---|"]
    for w in walks:
        what = "; ".join(f"{k.split(' -> ')[1]} ({n})" for k, n in w.climbs.most_common()) or "none"
        rows.append(f"| {w.job} | {w.crossings} | {w.count('job')} / {w.count('request')} / {w.count('result')} "
                    f"| {sum(w.climbs.values())} | {what} |")
    return "\n".join(rows)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m lab walk", description=__doc__.split("\n\n")[0])
    p.add_argument("--job", choices=sorted(JOBS), action="append", default=None,
                   help="the walk to follow (repeatable; default both)")
    p.add_argument("--json", action="store_true", help="print the walks as JSON")
    a = p.parse_args(argv)
    import os
    walks = []
    with tempfile.TemporaryDirectory(prefix="dcdi-walk-") as tmp:
        os.environ.setdefault("DCDI_CACHE_DIR", str(Path(tmp) / "cache"))
        for name in a.job or sorted(JOBS, reverse=True):
            folder = Path(tmp) / name
            folder.mkdir()
            walks.append(JOBS[name](folder))
    if a.json:
        print(json.dumps([w.as_dict() for w in walks], indent=1))
    else:
        print(table(walks))
        for w in walks:
            print(f"\n{w.job}: into app: " + "; ".join(f"{where} ({kind})" for kind, where in w.into_app))
            print(f"{w.job}: below app, from the front end: "
                  + "; ".join(f"{k} ({n})" for k, n in sorted(w.past_app.items())))
            print(f"{w.job}: climbs: " + "; ".join(f"{k} ({n})" for k, n in w.climbs.most_common()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
