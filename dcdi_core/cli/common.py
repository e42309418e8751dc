"""What every command group of `dcdi` shares: value types, the shared option
sets (PSF settings, PSF source, device), output and cache checks, JSON
printing, progress lines and training runs.

Imports of the engine are inside the functions: `dcdi --help` and the light
commands start without numpy's heavier modules, and torch stays optional.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time

from ..psf.rule import rule_text

UNITS = ("units: lens lengths in mm; depth D in metres from the lens's first vertex "
         "('inf' for infinity); wavelengths in nm; angles in degrees; field F is the "
         "normalised image height (1 = sensor semi-diagonal).")


# ------------------------------------------------------------------ value types
def depth_value(text: str) -> float:
    """A depth in metres (> 0) or 'inf'."""
    if text.strip().lower() in ("inf", "infinity"):
        return math.inf
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"depth must be a number of metres or 'inf', got {text!r}")
    if not v > 0:
        raise argparse.ArgumentTypeError(f"depth must be > 0 metres (or 'inf'), got {text!r}")
    return v


def focus_value(text: str):
    """A focus distance in metres, 'inf', or 'prescribed' (the lens as its prescription stands)."""
    if text.strip().lower() == "prescribed":
        return "prescribed"
    try:
        return depth_value(text)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(f"focus must be a distance in metres (> 0), 'inf' or 'prescribed', "
                                         f"got {text!r}") from None


def pixels(text: str) -> float:
    """A positive, finite number of pixels."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a number of pixels, got {text!r}") from None
    if not (v > 0 and math.isfinite(v)):
        raise argparse.ArgumentTypeError(f"must be > 0 pixels and finite, got {text!r}")
    return v


def quality_value(text: str):
    """An error budget: a PSNR in dB (``psf.budget.BUDGET_RANGE_DB``), or 'full' (no plan: None)."""
    from ..psf.budget import BUDGET_RANGE_DB
    if text.strip().lower() == "full":
        return None
    lo, hi = BUDGET_RANGE_DB
    try:
        v = float(text)
    except ValueError:
        v = math.nan
    if not (math.isfinite(v) and lo <= v <= hi):
        raise argparse.ArgumentTypeError(f"must be a PSNR in dB from {lo:g} to {hi:g}, or 'full', got {text!r}")
    return v


def positive_int(text: str) -> int:
    v = int(text)
    if v < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {v}")
    return v


def shard(text: str):
    """I/N: the items at positions i % N == I."""
    try:
        i, n = (int(v) for v in text.split("/"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}': expected I/N, e.g. 0/4") from None
    if not (n >= 1 and 0 <= i < n):
        raise argparse.ArgumentTypeError(f"'{text}': need 0 <= I < N")
    return i, n


def lens_map(items, what: str) -> dict:
    """{lens: path} from repeated LENS=PATH options (``what`` names the option)."""
    out = {}
    for item in items or []:
        lens, sep, path = item.partition("=")
        if not sep or not lens or not path:
            from ..errors import InputRangeError
            raise InputRangeError(what, item, "LENS=PATH, e.g. mos-s1=out/pairs-mos-s1")
        out[lens] = path
    return out


# ------------------------------------------------------------------ printing
def dump(obj) -> str:
    """JSON with infinities as 'inf' (JSON has none)."""
    def fix(o):
        if isinstance(o, float) and not math.isfinite(o):
            return "inf" if o > 0 else ("-inf" if o < 0 else None)
        if isinstance(o, dict):
            return {k: fix(v) for k, v in o.items()}
        if isinstance(o, (list, tuple)):
            return [fix(v) for v in o]
        return o
    return json.dumps(fix(obj), indent=2)


def print_table_or_json(res: dict, as_json: bool) -> None:
    print(dump(res) if as_json else "\n".join(f"{k:<22} {v}" for k, v in res.items()))


def one_line(text) -> str:
    return " ".join(str(text).split())


# The engine names what is wrong by the fields of its requests
# (``errors.field``); the command shows each by the option that sets it. A
# command whose options differ sets its own (``set_defaults(words=...)``).
WORDS = {
    "image": "--image", "capture": "--image", "depth_m": "--depth", "lens": "--lens", "method": "--method",
    "model": "--model", "deconv": "--deconv-weight / --deconv-method / --one-depth / --noise-full-well / --noise-read",
    "one_depth_m": "--one-depth", "weight": "--deconv-weight",
    "psf_source": "--psf-source", "basis": "--basis", "olf": "--olf", "keep": "--keep", "focus_m": "--focus",
    "image_pixel_pitch_mm": "--pixel-pitch", "pixel_pitch_mm": "--pixel-pitch",
    "sensor_size": "--sensor-size", "axis_px": "--axis", "patch": "--patch", "interpolation": "--interpolation",
    "pinhole_focal_length_mm": "--pinhole-focal-length",
    "seed": "--seed", "noise": "--noise", "perturb_fraction": "--perturb-fraction", "fixed_depth_m": "--fixed-depth",
    "wavelength_nm": "--wavelength", "multires": "--multires", "max_level": "--max-level",
    "interp_eps": "--exact-layers", "seam_tol": "--exact-layers",
    "full_well_electrons": "--full-well", "read_noise_electrons": "--read-noise", "kernel_size": "--kernel",
    "tile": "--tile", "device": "--device", "focus_distance_m": "--focus", "fraction": "--perturb-fraction",
    "field": "--field", "angle_deg": "--angle", "deposit_sigma_px": "--deposit-sigma", "pupil_samples": "--rays",
    "n_wavelengths": "--wavelengths", "n_fields": "--fields", "n_depths": "--depths", "near_m": "--near",
    "far_m": "--far", "field_step_px": "--field-step", "focus_tolerance_px": "--focus-tolerance",
    "max_error_db": "--quality",
}


def job_control(label: str, args):
    """The ``app.Control`` of a command's job: a bar per stage on a terminal,
    the job's notes as lines on standard error in the command's words."""
    from ..app import Control
    from ..errors import in_words
    from ..progress import StageBars
    words = error_words(args)
    return Control(progress=StageBars(label), note=lambda line: say(in_words(line, words)))


def psf_request(args, resp=None):
    """The ``app.PSFRequest`` of --psf-source, --olf, --basis, the sensor
    response and the error budget (--quality; --rays, --wavelengths and
    --field-step, where given, are kept as given)."""
    from ..app import PSFRequest
    given = {"pupil_samples": "rays", "n_wavelengths": "wavelengths", "field_step_px": "field_step"}
    return PSFRequest(source=getattr(args, "psf_source", None), olf_file=getattr(args, "olf", None),
                      basis_file=getattr(args, "basis", None), response=resp,
                      max_error_db=getattr(args, "quality", None),
                      fixed=tuple(k for k, opt in given.items() if getattr(args, opt, None) is not None))


def error_words(args) -> dict:
    """The words a command's errors are shown in: :data:`WORDS`, then the command's own."""
    return {**WORDS, **(getattr(args, "words", None) or {})}


def in_cli_words(args, value):
    """A job's text (a reason, a note; or a dict or list of them) in the
    command's words: the engine's field markers as its options."""
    from ..errors import in_words
    if isinstance(value, str):
        return in_words(value, error_words(args))
    if isinstance(value, dict):
        return {k: in_cli_words(args, v) for k, v in value.items()}
    if isinstance(value, list):
        return [in_cli_words(args, v) for v in value]
    return value


def say(text: str) -> None:
    """A line for the user on standard error."""
    print(f"dcdi: {text}", file=sys.stderr)


def show_warning(message, category, filename, lineno, file=None, line=None):
    """warnings.showwarning for the command: one line each, no source line."""
    print(f"dcdi: warning: {one_line(message)}", file=sys.stderr)


def counter(what: str):
    """progress(done, total) drawing 'dcdi <what> done/total' on a terminal, silent elsewhere."""
    tty = sys.stderr.isatty()

    def progress(done, total):
        if tty:
            print(f"\rdcdi {what} {done}/{total}", end="" if done < total else "\n", file=sys.stderr)
    return progress


# ------------------------------------------------------------------ checks before any work
def check_output(path, option: str, *, image: bool = False, suffix: str | None = None) -> None:
    """Refuse, before any work, an output that cannot be written: an image
    extension that is not supported (or not ``suffix``), a folder that is
    read-only or a file."""
    if not path:
        return
    from pathlib import Path

    from ..errors import InputRangeError, check_writable_folder
    if image:
        from ..io.image_checks import check_image_output
        check_image_output(path)
    if suffix is not None and not str(path).lower().endswith(suffix):
        raise InputRangeError(option, str(path), f"a file name ending in {suffix} (what it writes)")
    check_writable_folder(Path(path).resolve().parent, f"{option} {path}")


def check_cache(args=None) -> None:
    """Refuse, before any work, a PSF cache folder that cannot be written."""
    if args is not None and getattr(args, "no_cache", False):
        return
    from ..errors import check_writable_folder
    from ..outputs import default_cache_dir
    check_writable_folder(default_cache_dir(), "the PSF cache (set DCDI_CACHE_DIR to a writable folder)")


def check_wavelength(lens, args) -> None:
    if getattr(args, "wavelength", None) is not None:
        lens.check_wavelengths(args.wavelength, "--wavelength")


def check_olf_file(args) -> None:
    """An OLF file given with --olf, read and checked before any work: a
    damaged one is an error naming it (the PSF source would else fall back
    to tracing, saying why, as it does for a file that does not cover the
    request)."""
    if getattr(args, "olf", None) and getattr(args, "psf_source", None) != "trace":
        from ..psf.olf import load_olf_file
        load_olf_file(args.olf)
    if getattr(args, "basis", None) and getattr(args, "psf_source", None) != "trace":
        from ..psf.basis import open_store
        open_store(args.basis)


# ------------------------------------------------------------------ shared option sets
def add_subcommands(parser, dest: str, metavar: str = "SUBCOMMAND"):
    """The subcommands of a command group (one of them is required)."""
    return parser.add_subparsers(dest=dest, required=True, metavar=metavar)


def add_aperture_options(q) -> None:
    """The iris: --f-number, --blades, --blade-rotation (``optics.aperture``)."""
    from ..optics.aperture import MAX_BLADES, MAX_F_NUMBER, MIN_BLADES
    q.add_argument("--f-number", type=float, default=None, metavar="N",
                   help=f"the lens stopped down to f/N, from its widest (its prescription's stop) to f/"
                        f"{MAX_F_NUMBER:g}; a wider one is refused (default: wide open)")
    q.add_argument("--blades", type=int, default=0, metavar="N",
                   help=f"the iris's blades: 0 round (default), or {MIN_BLADES}-{MAX_BLADES}: a regular polygon "
                        "(its corners on the f-number's circle)")
    q.add_argument("--blade-rotation", type=float, default=None, metavar="DEG",
                   help="with --blades: a corner's angle from up towards the right, degrees (default 0)")


def load_lens_with_aperture(args, name: str | None = None):
    """The lens ``name`` (default ``args.lens``) stopped down and shaped as
    the aperture options say (checked before any work)."""
    from ..errors import InputRangeError
    from ..optics.aperture import MAX_BLADES, MIN_BLADES, Aperture, stopped_down
    from ..optics.lens import load_lens
    if args.blade_rotation is not None and not args.blades:     # a round iris has no corner to turn
        raise InputRangeError("--blade-rotation", args.blade_rotation,
                              f"only with --blades {MIN_BLADES}-{MAX_BLADES} (a round iris has no corners to turn)")
    rotation = 0.0 if args.blade_rotation is None else args.blade_rotation
    aperture = Aperture(args.f_number, args.blades, rotation)
    return stopped_down(load_lens(args.lens if name is None else name), aperture)


# the pixel pitch's one rule, said alike by every verb that takes it
PIXEL_PITCH_RULE = ("one pixel on the sensor, mm; the PSFs are sampled at it (default: the image file's record "
                    "where it has one (`dcdi info`), else the image, or its --sensor-size frame, spans the lens's "
                    "sensor diagonal; with no image, as `dcdi psf`, the lens's own sensor pixels)")


def add_psf_options(q, *, sensor_focus: bool = True, render: bool = False) -> None:
    """The PSF settings' options. ``sensor_focus``: --focus moves the sensor
    (bokeh and dof give --focus a meaning of their own); ``render``: the
    kernel grows with the depth map unless --kernel is given."""
    from ..psf.compute import PSFSettings
    d = PSFSettings()
    grows = "; without this option it grows to hold the depth map's blur, up to 129" if render else ""
    q.add_argument("--kernel", type=positive_int, default=None, metavar="K",
                   help=f"kernel size K x K px, odd (default {d.kernel_size}{grows})")
    q.add_argument("--deposit-sigma", type=float, default=None, metavar="PX",
                   help=f"Gaussian spread of each ray in pixels on top of the pixel it lands in (default "
                        f"{d.deposit_sigma_px:g}: what a sensor records; the paper's 0.471 blurs)")
    q.add_argument("--rays", type=positive_int, default=None, metavar="N",
                   help=f"pupil grid N x N over the real stop (default {d.pupil_samples})")
    q.add_argument("--wavelengths", type=positive_int, default=None, metavar="W",
                   help=f"wavelength samples over 400-700 nm (default {d.n_wavelengths})")
    q.add_argument("--precision", choices=["float32", "float64"], default=None,
                   help=f"ray tracing precision (default {d.precision})")
    if render:      # the image's pitch: one option, its old name kept as a spelling of it
        q.add_argument("--pixel-pitch", "--image-pixel-pitch", dest="image_pixel_pitch", type=float, default=None,
                       metavar="MM", help=PIXEL_PITCH_RULE)
    else:
        q.add_argument("--pixel-pitch", type=float, default=None, metavar="MM", help=PIXEL_PITCH_RULE)
    if sensor_focus:
        q.add_argument("--focus", type=depth_value, default=None, metavar="D",
                       help="move the sensor to focus depth D metres (default: as prescribed)")
    q.add_argument("--response", default=None, metavar="CSV",
                   help="sensor spectral response CSV (wavelength_nm,r,g,b); default: shipped curves")


def add_quality_option(q) -> None:
    """--quality: the render's error budget (``psf.budget``)."""
    from ..psf.budget import DEFAULT_DB
    q.add_argument("--quality", type=quality_value, default=DEFAULT_DB["render"], metavar="DB",
                   help="the error budget: the result at least DB dB PSNR from the render with converged PSFs "
                        f"(default {DEFAULT_DB['render']:g}; the add-on's preview takes "
                        f"{DEFAULT_DB['preview']:g}); the rays, wavelengths and field step of a ray map or a "
                        "trace, and which depth layers of a bokeh are blurred at a coarser resolution, are "
                        "planned from the lens's measured error table (`dcdi bench quality LENS`), those given "
                        "by --rays, --wavelengths and --field-step kept; 'full': no plan, the full-quality "
                        "defaults")


def add_psf_source_options(q) -> None:
    q.add_argument("--psf-source", choices=["basis", "raymap", "olf", "trace"], default=None,
                   help="where the PSFs come from: the lens's PSF basis (a compressed traced library, "
                        "prescribed focus), its ray map (the catalogue's lenses: any focus, f-number, "
                        "blades and pixel pitch), the Omni-Lens-Field (each an error if it cannot serve the "
                        f"request) or ray tracing; default: {rule_text()}; a line on standard error "
                        "says which and why")
    q.add_argument("--basis", default=None, metavar="FILE.npz",
                   help="the PSF basis file to serve PSFs from (default: the lens's shipped one in "
                        "dcdi_core/psf/data/basis; `dcdi psflib compress` writes one)")
    q.add_argument("--olf", default=None, metavar="FILE.npz",
                   help="the OLF file to serve PSFs from (default: the one shipped in dcdi_core/models/weights)")


def add_device_option(parser, torchrun: bool = True) -> None:
    """--device of a torch command (not a setting: a run resumes on another device)."""
    parser.add_argument("--device", default="auto", metavar="auto|cpu|cuda[:N]",
                        help="where torch computes: auto (CUDA when torch sees a device, else the CPU), cpu, "
                             "cuda or cuda:N" + ("; under torchrun each process takes cuda:LOCAL_RANK"
                                                 if torchrun else ""))


def add_export_options(t) -> None:
    """The options of `dacn export` and `depth export`."""
    t.add_argument("run", help="run folder or checkpoint.pt")
    t.add_argument("-o", "--output", required=True, help="the .npz to write")
    t.add_argument("--dtype", choices=["float16", "float32"], default="float16", help="storage dtype")
    t.add_argument("--weights", choices=["ema", "model"], default="ema", help="which weights")


def psf_settings(args, *, sensor_focus: bool = True):
    """PSF settings from the shared options; ``sensor_focus``: read --focus
    as the sensor's focus (bokeh's and dof's --focus mean more, read there)."""
    from ..psf.compute import PSFSettings
    base = PSFSettings()
    sigma = getattr(args, "deposit_sigma", None)
    return PSFSettings(kernel_size=args.kernel or base.kernel_size,
                       pupil_samples=args.rays or base.pupil_samples,
                       n_wavelengths=args.wavelengths or base.n_wavelengths,
                       precision=args.precision or base.precision,
                       deposit_sigma_px=base.deposit_sigma_px if sigma is None else sigma,
                       pixel_pitch_mm=getattr(args, "pixel_pitch", None),     # an image's is the request's
                       focus_distance_m=getattr(args, "focus", None) if sensor_focus else None)


def response(args):
    """The sensor response of --response, or None (the shipped curves)."""
    if getattr(args, "response", None):
        from ..psf.spectral import load_response
        return load_response(args.response)
    return None


# ------------------------------------------------------------------ training runs
def progress_bar(desc: str, every: int = 0):
    """(progress(step, total, loss), log(text), close()) for a training run:
    a tqdm bar on a terminal, made at the first step so that its rate is the
    training's (a resumed run starts at its step); off a terminal (a
    background run's log) one line every ``every`` steps and at the end, and
    the run's own messages."""
    tty = sys.stderr.isatty()
    bar = None
    t_start = time.perf_counter()

    def progress(step, total, loss):
        nonlocal bar
        if not tty:
            if every and (step % every == 0 or step == total):
                print(f"{desc}: iteration {step}/{total}, loss {loss:.3g}, "
                      f"{time.perf_counter() - t_start:.0f} s since start", file=sys.stderr, flush=True)
            return
        if bar is None:
            try:
                from tqdm import tqdm
            except ImportError:     # no bar without tqdm (requirements.txt has it)
                return
            bar = tqdm(total=total, initial=step - 1, desc=desc, unit="it", file=sys.stderr, dynamic_ncols=True)
        bar.set_postfix(loss=f"{loss:.3g}", refresh=False)
        bar.update(step - bar.n)

    def log(text):
        if bar is not None:
            bar.write(text)
        else:
            print(f"{text} ({time.perf_counter() - t_start:.0f} s since start)", file=sys.stderr, flush=True)

    def close():
        if bar is not None:
            bar.close()
    return progress, log, close


def torchrun_worker() -> bool:
    """A torchrun process other than rank 0 (it trains but writes nothing)."""
    import os
    return os.environ.get("RANK", "0") not in ("", "0")


def ran_on(where: dict) -> str:
    n = where.get("world_size", 1)
    return f"ran on {where.get('device', 'cpu')}" + (f", {n} processes (torchrun)" if n > 1 else "")


def run_training(desc: str, run, train_fn, every: int = 0):
    """train_fn(progress=..., log=...) under a progress bar; None (after
    saying how to resume) when interrupted."""
    progress, log, close = progress_bar(desc, every)
    try:
        result = train_fn(progress=progress, log=log)
    except KeyboardInterrupt:
        close()
        say(f"interrupted; the last checkpoint is in {run}: run the same command to resume")
        return None
    close()
    return result


def exported(args, meta: dict) -> int:
    """The line both export commands print about the file they wrote."""
    from ..outputs import size_of
    print(f"wrote {args.output} ({size_of(args.output) / 1e6:.2f} MB, {args.dtype}, {meta['weights']} "
          f"weights, lens {meta['lens']}, {meta['step']} iterations)")
    return 0
