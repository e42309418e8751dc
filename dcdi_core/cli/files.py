"""What each `dcdi` verb reads and writes, declared before any work
(``outputs.JobFiles``): the options that name its inputs, its output files,
the folders it writes into, and the paths derived from them (an image's
sidecar record, `dof`'s intermediates, `olf train`'s run folder).

Every option of every verb is in one of these lists or in
:data:`NOT_PATHS`; a test walks the parser and fails on an option in none
of them, so that a new option cannot write a file undeclared.
"""
from __future__ import annotations

import argparse
import os
from dataclasses import dataclass, field
from pathlib import Path


@dataclass(frozen=True)
class Spec:
    """A verb's paths by option ``dest``: ``reads`` (files or folders it
    reads), ``writes`` (files it writes), ``into`` (folders it writes into)
    and ``derived(args, files)``, which adds the paths the options imply;
    ``others``: options of this verb that are not paths although a path
    option of another verb has their name."""
    reads: tuple = ()
    writes: tuple = ()
    into: tuple = ()
    derived: object = None
    others: tuple = ()          # options that name a path elsewhere but not here (spot's --depth: metres)
    updates: tuple = ()         # input folders it records a file in (the pairs' split.json)


def _dof_intermediates(args, files):
    if getattr(args, "save_intermediates", None):
        folder = Path(args.save_intermediates)
        for name in ("corrected.exr", "depth.exr"):
            files.write(folder / name, f"--save-intermediates {args.save_intermediates}")


def _olf_run(args, files):
    if not args.run:
        files.write_into(f"{args.output}.run", "--run (default: -o's name + .run)")


RENDER_READS = ("image", "depth", "lens", "response", "basis", "olf")
PSF_SOURCE = ("response", "basis", "olf")

#: the verbs (their words after `dcdi`) and their paths
SPECS = {
    ("lens", "list"): Spec(),
    ("lens", "info"): Spec(reads=("lens",)),
    ("lens", "import"): Spec(reads=("file",), writes=("output",)),
    ("spot",): Spec(reads=("lens",), others=("depth",)),
    ("psf",): Spec(reads=("lens", *PSF_SOURCE), writes=("out", "png"), others=("depth",)),
    ("psflib", "build"): Spec(reads=("lens", "response"), writes=("output",)),
    ("psflib", "compress"): Spec(reads=("lens",), writes=("output",)),
    ("psflib", "raymap"): Spec(reads=("lens",), writes=("output",)),
    ("psflib", "show"): Spec(reads=("library", "response"), writes=("png",)),
    ("simulate",): Spec(reads=RENDER_READS, writes=("output", "sharp_out")),
    ("bokeh",): Spec(reads=RENDER_READS, writes=("output", "side_by_side")),
    ("correct",): Spec(reads=("image", "depth", "model", "lens", *PSF_SOURCE), writes=("output",)),
    ("dof",): Spec(reads=(*RENDER_READS, "camera", "dacn", "depth_checkpoint"), writes=("output", "side_by_side"),
                   into=("save_intermediates",), derived=_dof_intermediates),
    ("info",): Spec(reads=("file",)),
    ("olf", "train"): Spec(reads=("lens", "focus_lens"), writes=("output",), into=("run",), derived=_olf_run),
    ("olf", "points"): Spec(reads=("lens", "focus_lens"), writes=("output",)),
    ("olf", "info"): Spec(reads=("file",)),
    ("dacn", "pairs"): Spec(reads=("source", "lens", "lens_pool"), into=("output",)),
    ("dacn", "train"): Spec(reads=("data", "config"), into=("output",), others=("refine",), updates=("data",)),
    ("dacn", "export"): Spec(reads=("run",), writes=("output",)),
    ("dacn", "eval"): Spec(reads=("run", "data", "compare"), writes=("json",), into=("pictures",), updates=("data",)),
    ("dacn", "correct"): Spec(reads=("image", "depth", "model", "lens"), writes=("output",)),
    ("depth", "estimate"): Spec(reads=("image", "camera", "refine", *PSF_SOURCE), writes=("output", "confidence")),
    ("depth", "train"): Spec(reads=("data",), into=("output",), updates=("data",)),
    ("depth", "export"): Spec(reads=("run",), writes=("output",)),
    ("dataset", "stats"): Spec(reads=("dirs", "lens"), into=("out",)),
    ("dataset", "textures"): Spec(into=("out",)),
    ("bench",): Spec(reads=("optiland", "lens")),
    ("demo",): Spec(into=("out",)),
}

#: the options that never name a path
NOT_PATHS = frozenset("""
    wavelength json paraxial_only id field angle depth_channel kernel deposit_sigma rays wavelengths precision
    pixel_pitch focus psf_source fields depths near far no_cache rank n_fields n_depths pitch_factor kernel_size
    near_rays show_fields show_depths patch image_pixel_pitch sensor_size axis interpolation fixed_depth pinhole_focal_length
    no_distortion noise full_well read_noise seed perturb perturb_fraction accelerator keep distort plain multires
    max_level exact_layers method deconv_weight deconv_method noise_full_well noise_read one_depth tile overlap
    weights threads device depth_backend variant size iters batch lr checkpoint_every dtype offgrid held_out held_out_rays deposit_sigma psf_data
    focus_range focus_bins kind variants no_refocus baseline_depth no_noise no_saturate sensor_px placement
    no_deconvolved shard crop schedule warmup loss ema_decay crop_choice validate_every input rdicab d2cb racm
    depth_encoding condition channels groups blocks train_scenes name pictures_count lpips widths quick
    frames what repeat field_step focus_tolerance focus_slices f_number blades blade_rotation degree count uncertain_depth
    quality measure
""".split())


def _values(value):
    """The paths in an option's value: a path, a list of them, or LENS=PATH items."""
    if value is None or isinstance(value, bool):
        return []
    if isinstance(value, (list, tuple)):
        return [p for v in value for p in _values(v)]
    if not isinstance(value, (str, os.PathLike)):
        return []
    text = os.fspath(value)
    if not text:
        return []
    lens, sep, path = text.partition("=")
    return [path] if sep and lens and path and not os.path.exists(text) else [text]


def sidecar_of(path) -> Path:
    """Where a PNG's or JPEG's capture record lives (``io.capture_record``);
    ``path`` itself for other files (an EXR keeps it in its header)."""
    path = Path(path)
    if path.suffix.lower() not in (".png", ".jpg", ".jpeg"):
        return path
    from ..io.capture_record import sidecar_path
    return sidecar_path(path)


def label_of(parser: argparse.ArgumentParser, dest: str) -> str:
    """How the option ``dest`` is spelt (its first spelling, ``-o``), or the argument's name."""
    for a in parser._actions:
        if a.dest == dest:
            return (a.option_strings or [a.metavar if isinstance(a.metavar, str) else dest.upper()])[0]
    return dest


def job_files(args):
    """The ``outputs.JobFiles`` of a parsed command line (None for a verb
    without a declaration: a test makes sure there is none)."""
    from ..outputs import JobFiles
    spec, labels = getattr(args, "files", None), getattr(args, "files_labels", None) or {}
    if spec is None:
        return None
    files = JobFiles()
    for dest in spec.reads:
        for path in _values(getattr(args, dest, None)):
            files.read(path, labels.get(dest, dest))
            if sidecar_of(path) != Path(path):
                files.read(sidecar_of(path), f"{labels.get(dest, dest)}'s record")
    for dest in spec.writes:
        for path in _values(getattr(args, dest, None)):
            files.write(path, labels.get(dest, dest))
    for dest in spec.updates:
        for path in _values(getattr(args, dest, None)):
            files.add_to(path, labels.get(dest, dest))
    for dest in spec.into:
        for path in _values(getattr(args, dest, None)):
            files.write_into(path, labels.get(dest, dest))
    if spec.derived is not None:
        spec.derived(args, files)
    for o in list(files.outputs):               # a PNG's or JPEG's record is written (or removed) beside it
        side = sidecar_of(o.path)
        if side != o.path:
            files.write(side, f"{o.label}'s record")
    return files


def leaves(parser, words=()):
    """(words, parser) of every verb under ``parser``."""
    subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    if not subs:
        yield tuple(words), parser
        return
    for a in subs:
        for name, sub in a.choices.items():
            yield from leaves(sub, (*words, name))


def attach(parser) -> None:
    """Give every verb of ``parser`` its :data:`SPECS` entry (``files``) and
    the spellings of its path options (``files_labels``, for messages)."""
    for words, sub in leaves(parser):
        spec = SPECS.get(words)
        if spec is not None:
            sub.set_defaults(files=spec, files_labels={d: label_of(sub, d) for d in
                                                       (*spec.reads, *spec.writes, *spec.into)})
