"""`dcdi dacn pairs|train|export|eval|correct`: the depth-aware correction
network, from its training pairs to a shipped file and its scores.

Engine imports are inside the handlers: torch is loaded only once a command
needs it.
"""
from __future__ import annotations

import argparse
import sys
import time

from .common import (UNITS, add_device_option, add_export_options, add_subcommands, counter, exported,
                     positive_int, ran_on, run_training, shard, torchrun_worker)


def cmd_dacn_pairs(args) -> int:
    from ..dataset.rgbd import open_source
    from ..models.dacn.data import DA2TConfig, build_pairs
    source = open_source(args.source, args.kind)
    noise = None if args.no_noise else {"full_well_electrons": args.full_well, "read_noise_electrons": args.read_noise}
    config = DA2TConfig(lens=args.lens, perturb_fraction=args.perturb, noise=noise,
                        baseline_depth_m=args.baseline_depth, sensor_px=args.sensor_px, pupil_samples=args.rays,
                        n_wavelengths=args.wavelengths, n_fields=args.fields, n_depths=args.depths,
                        lens_pool=args.lens_pool, saturate=not args.no_saturate, seed=args.seed,
                        refocus=not args.no_refocus, placement=args.placement,
                        deconvolved=not args.no_deconvolved)
    t0 = time.perf_counter()
    done = build_pairs(source, args.output, config, variants=args.variants, shard=args.shard,
                       log=lambda t: print(t, file=sys.stderr))
    print(f"{len(done)} DA2T pairs of {source.name} ({len(source)} frames) for {args.lens} in {args.output} "
          f"({time.perf_counter() - t0:.1f} s this run)")
    return 0


def cmd_dacn_train(args) -> int:
    from pathlib import Path

    from ..models.dacn.config import DACNTrainConfig
    arch = {}
    for k in ("rdicab", "d2cb", "racm", "depth_encoding", "channels", "groups", "blocks", "condition", "refine"):
        if getattr(args, k) is not None:
            arch[k] = getattr(args, k)
    config = DACNTrainConfig(data=args.data, config=args.config, arch=arch, input=args.input, iters=args.iters,
                             batch=args.batch, crop=args.crop, lr=args.lr, seed=args.seed, threads=args.threads,
                             checkpoint_every=args.checkpoint_every, validate_every=args.validate_every,
                             train_scenes=args.train_scenes, schedule=args.schedule, warmup=args.warmup,
                             loss=args.loss, crop_choice=args.crop_choice, ema_decay=args.ema_decay)
    from ..models.dacn.train import train_dacn       # torch from here on
    run = Path(args.output)
    result = run_training("dacn train", run, lambda **kw: train_dacn(config, run, device=args.device, **kw),
                          config.checkpoint_every)
    if result is None:
        return 130
    if torchrun_worker():
        return 0                                        # rank 0 reports
    v = result.validation["ema"].get("mean")
    rate = result.step / result.seconds if result.seconds > 0 else float("nan")
    print(f"trained {run} ({args.config}, {result.step} iterations, {result.seconds:.1f} s here, {rate:.2f} it/s)")
    if v:
        print(f"validation ({len(result.data.val)} pairs, EMA): PSNR {v['psnr']:.2f} dB (input {v['psnr_input']:.2f})"
              + (f", SSIM {v['ssim']:.4f} (input {v['ssim_input']:.4f})" if "ssim" in v else ""))
    else:
        print("no validation pairs (the split gave no 'val' scene)")
    print(ran_on(result.where))
    return 0


def cmd_dacn_export(args) -> int:
    from ..models.dacn.export import export_dacn
    return exported(args, export_dacn(args.run, args.output, weights=args.weights, dtype=args.dtype))


def _model_splits(runs: dict) -> list:
    """The recorded splits of the runs among ``runs`` {name: path} (run
    folders and checkpoints beside one; an exported file names its run's)."""
    from pathlib import Path

    from ..models.common.split import Split
    out = []
    for path in runs.values():
        p = Path(path)
        folder = p if p.is_dir() else p.parent
        if (folder / "split.json").exists():
            out.append(Split.load(folder / "split.json"))
    return out


def _eval_runs(args) -> dict:
    """{name: run} of the model and --compare, refused before any work."""
    from pathlib import Path

    from ..errors import InputRangeError
    runs = {args.name: args.run}
    for item in args.compare:
        name, sep, path = item.partition("=")
        if not sep or not name or not path:
            raise InputRangeError("--compare", item, "NAME=RUN")
        if name in runs or name == "capture":
            raise InputRangeError("--compare", item, f"a name other than {', '.join(list(runs) + ['capture'])} "
                                  "(taken)")
        runs[name] = path
    for name, path in runs.items():
        if not Path(path).exists():
            from ..errors import ModelFileError
            raise ModelFileError(path, f"model {name}: does not exist")
    return runs


def _told_depth_correction(loaded: dict, data):
    """The inference of runs trained told one depth (models.dacn.unaware):
    told it again, refining the one-depth deconvolution; None when no run
    was (every run then gets the pairs' depth and deconvolution)."""
    from ..models.dacn.unaware import Correction, told_depth
    told = {m: told_depth(info) for m, info in loaded.values()}
    if all(t is None for t in told.values()):
        return None
    from pathlib import Path

    from ..io.jsontext import loads
    lens = loads(Path(data, "da2t.json").read_text(encoding="utf-8"), Path(data, "da2t.json"))["lens"]
    for name, (m, info) in loaded.items():
        if told[m] is not None:
            print(f"eval: {name} was trained told {told[m]:g} m everywhere: told it here too, refining the "
                  "one-depth deconvolution")
    return Correction(told, lens, data)


def cmd_dacn_eval(args) -> int:
    import json
    runs = _eval_runs(args)
    import torch
    torch.set_num_threads(args.threads)
    from ..models.dacn.correct import load_dacn
    from ..models.dacn.evaluate import evaluate_models, held_out_pairs, markdown_tables, write_pictures
    ids, _ = held_out_pairs(args.data, _model_splits(runs))
    loaded = {name: load_dacn(path, weights=args.weights) for name, path in runs.items()}
    models = {name: m for name, (m, _) in loaded.items()}
    correct_fn = _told_depth_correction(loaded, args.data)
    lp = None
    if args.lpips:
        from ..models.common.lpips import load_lpips
        lp = load_lpips(*args.lpips)
    ev, kept = evaluate_models(models, args.data, ids=ids, tile=args.tile, overlap=args.overlap,
                               correct_fn=correct_fn, progress=counter("eval: pair"),
                               keep_outputs=args.pictures_count if args.pictures else 0, lpips=lp)
    print(f"{len(ids)} held-out pairs of {args.data}; PSNR dB / SSIM over the imaged pixels")
    print(markdown_tables(ev), end="")
    for name, sec in ev.seconds.items():
        print(f"{name}: {sec / len(ids):.2f} s per pair")
    if args.json:
        from ..atomic import write_text
        write_text(args.json, json.dumps(dict(ev.as_dict(), runs=runs), indent=1) + "\n")
    if args.pictures:
        paths = write_pictures(kept, args.pictures, list(models))
        print(f"wrote {len(paths)} pictures to {args.pictures} (capture | {' | '.join(models)} | target)")
    return 0


# ------------------------------------------------------------------ parsers
def train_parser(subparsers, name: str, **kw):
    """The parser of `dacn train`."""
    t = subparsers.add_parser(name, **kw,
                              description="Train DACN (CPU, seeded, Adam, L1, EMA). Checkpoints go to the run folder; "
                                          "the same command again resumes a killed run and ends where an "
                                          "uninterrupted one would.")
    t.add_argument("--data", required=True, help="pairs folder (dcdi dacn pairs)")
    t.add_argument("--config", default="refine",
                   help="named configuration: refine (default), tiny, tiny-rb, demo, paper (docs/dacn.md)")
    t.add_argument("--iters", type=positive_int, default=1000, help="iterations (the paper: 200000)")
    t.add_argument("-o", "--output", required=True, help="run folder")
    t.add_argument("--batch", type=positive_int, default=4, help="batch (default 4; the paper 8)")
    t.add_argument("--crop", type=positive_int, default=128, help="crop size (default 128; the paper 256)")
    t.add_argument("--lr", type=float, default=2e-4, help="peak learning rate")
    t.add_argument("--schedule", choices=["cosine", "steps"], default="cosine",
                   help="cosine (default: warm-up, then down to lr / 100) or steps (halved at 50/80/90/95 %%, the "
                        "paper's release)")
    t.add_argument("--warmup", type=float, default=0.03, help="warm-up, a fraction of the iterations (cosine)")
    t.add_argument("--loss", choices=["srgb_l1", "l1"], default="srgb_l1",
                   help="L1 of the sRGB-encoded images (default) or of the linear ones")
    t.add_argument("--ema-decay", type=float, default=0.999,
                   help="EMA of the weights per iteration (default 0.999, the paper's for 200k iterations; a few "
                        "thousand want less, e.g. 0.995: 0.999^2000 still holds 13.5 %% of the initial weights)")
    t.add_argument("--crop-choice", type=positive_int, default=2,
                   help="each crop is the worst-captured of this many imaged places (1: uniform)")
    t.add_argument("--seed", type=int, default=0, help="seed of weights and crops")
    t.add_argument("--threads", type=positive_int, default=1, help="torch threads (default 1)")
    add_device_option(t, torchrun=True)
    t.add_argument("--checkpoint-every", type=positive_int, default=500, help="iterations between checkpoints")
    t.add_argument("--validate-every", type=int, default=0, help="iterations between validations (0: at the end)")
    t.add_argument("--input", choices=["capture", "baseline"], default="capture",
                   help="train on the depth-aware capture (DA2T) or the depth-unaware baseline")
    t.add_argument("--rdicab", action=argparse.BooleanOptionalAction, default=None,
                   help="the paper's image x depth cross-attention (default: the config's)")
    t.add_argument("--d2cb", action=argparse.BooleanOptionalAction, default=None,
                   help="the paper's depth-steered deformable conv (default: the config's)")
    t.add_argument("--racm", choices=["rb", "rstb"], default=None, help="replace the blocks (EDSR or Swin)")
    t.add_argument("--depth-encoding", choices=["minmax", "diopter"], default=None, help="depth at the input")
    t.add_argument("--condition", action=argparse.BooleanOptionalAction, default=None,
                   help="depth and field maps as input channels (default: the config's)")
    t.add_argument("--refine", action=argparse.BooleanOptionalAction, default=None,
                   help="refine the deconvolved capture (an input, and the base of the output) (default: the "
                        "config's)")
    t.add_argument("--channels", type=positive_int, default=None, help="override C")
    t.add_argument("--groups", type=positive_int, default=None, help="override G")
    t.add_argument("--blocks", type=positive_int, default=None, help="override B")
    t.add_argument("--train-scenes", type=int, default=0,
                   help="train on this many of the training scenes (0: all; for a data-size curve)")
    t.set_defaults(func=cmd_dacn_train)
    return t


def eval_parser(subparsers, name: str, **kw):
    """The parser of `dacn eval`."""
    t = subparsers.add_parser(name, **kw,
                              description="PSNR / SSIM (over the imaged pixels) of each model's correction of the "
                                          "depth-aware captures, beside the uncorrected capture: mean, per depth "
                                          "band and per scene. Pairs of scenes a model trained or validated on are "
                                          "skipped.")
    t.add_argument("run", help="a DACN run folder, checkpoint.pt or exported .npz")
    t.add_argument("--data", required=True, help="pairs folder with the test pairs (dcdi dacn pairs)")
    t.add_argument("--compare", action="append", default=[], metavar="NAME=RUN",
                   help="another model to score beside it, e.g. depth-unaware=out/baseline (repeatable)")
    t.add_argument("--name", default="dacn", help="the first model's name in the tables (default dacn)")
    t.add_argument("--pictures", default=None, metavar="DIR",
                   help="write capture | corrections | target PNGs of the first pairs here")
    t.add_argument("--pictures-count", type=positive_int, default=3, help="pairs to picture (default 3)")
    t.add_argument("--json", default=None, metavar="FILE", help="write all scores as JSON")
    t.add_argument("--weights", choices=["ema", "model"], default="ema",
                   help="the runs' EMA or raw weights (an exported file has one kind)")
    t.add_argument("--lpips", nargs=2, default=None, metavar=("ALEXNET.pth", "LIN.pth"),
                   help="also LPIPS (AlexNet, v0.1) from weights on this disk: torchvision's alexnet-owt-*.pth and "
                        "the lpips package's weights/v0.1/alex.pth (never downloaded)")
    t.add_argument("--threads", type=positive_int, default=1, help="torch threads (default 1)")
    t.add_argument("--tile", type=positive_int, default=256, help="tile size, px (default 256)")
    t.add_argument("--overlap", type=int, default=32, help="tile overlap, px (default 32)")
    t.set_defaults(func=cmd_dacn_eval)
    return t


def add_commands(sub) -> None:
    from .correct import correct_parser
    q = sub.add_parser("dacn", help="depth-aware correction network: pairs, train, export, eval, correct",
                       description="The depth-aware correction network (DACN): its DA2T training pairs, training, "
                                   "export, scores and use. " + UNITS)
    dsub = add_subcommands(q, "dacn_command")
    t = dsub.add_parser("pairs", help="pre-build DA2T pairs from an RGB-D source (resumable, sharded)",
                        description="Simulate every frame of an RGB-D source through a (perturbed) lens: "
                                    "capture, aligned target, depth on the sensor, depth-unaware baseline.")
    t.add_argument("source", help="factory folder, images/+depth/ folder, NYUv2 labeled .mat or Middlebury 2014")
    t.add_argument("--kind", choices=["factory", "folder", "nyuv2", "middlebury2014"], default=None,
                   help="the source's kind (default: found from what is there)")
    t.add_argument("--lens", required=True, help="lens id")
    t.add_argument("-o", "--output", required=True, help="pairs folder")
    t.add_argument("--variants", type=positive_int, default=1, help="perturbed lenses per frame (default 1)")
    t.add_argument("--perturb", type=float, default=0.05,
                   help="perturbation fraction (default 0.05 = +-5 %%, refocused; the paper: within 10 %%)")
    t.add_argument("--no-refocus", action="store_true",
                   help="keep each perturbed lens's sensor where its perturbed thickness puts it (default: moved "
                        "back to the nominal focus, as a focus compensator does)")
    t.add_argument("--lens-pool", type=int, default=0,
                   help="K perturbed lenses shared by all frames (0: a new one per frame; each costs a PSF library)")
    t.add_argument("--baseline-depth", type=float, default=2.0, help="the depth-unaware baseline's depth, m")
    t.add_argument("--no-noise", action="store_true", help="no sensor noise")
    t.add_argument("--no-saturate", action="store_true",
                   help="keep values above 1 (default: capture, baseline and target clipped to [0, 1] as a sensor "
                        "records them)")
    t.add_argument("--full-well", type=float, default=10000.0, help="full well, electrons")
    t.add_argument("--read-noise", type=float, default=3.0, help="read noise, electrons RMS")
    t.add_argument("--sensor-px", type=int, nargs=2, default=(1280, 1920), metavar=("ROWS", "COLS"),
                   help="frames are crops of a sensor of this many pixels, at its pitch (default: the paper's "
                        "1280 1920, 12.2 um for the MOS lenses)")
    t.add_argument("--full-sensor", dest="sensor_px", action="store_const", const=None,
                   help="frames span the whole sensor instead (480 x 640: 35.2 um)")
    t.add_argument("--placement", choices=["random", "centre"], default="random",
                   help="where a frame lies on the sensor: a seeded place per frame and variant (default; every "
                        "field is reached) or the centre")
    t.add_argument("--no-deconvolved", action="store_true",
                   help="skip the capture's deconvolution with the nominal lens (what a refining network reads)")
    t.add_argument("--rays", type=positive_int, default=64, help="pupil samples per side (PSF settings)")
    t.add_argument("--wavelengths", type=positive_int, default=31, help="wavelengths per PSF")
    t.add_argument("--fields", type=positive_int, default=64, help="library fields")
    t.add_argument("--depths", type=positive_int, default=20, help="library depth bins (plus infinity)")
    t.add_argument("--seed", type=int, default=0, help="seed of perturbations and noise")
    t.add_argument("--shard", type=shard, default=(0, 1), help="I/N: the frames at positions i %% N == I")
    t.set_defaults(func=cmd_dacn_pairs)

    train_parser(dsub, "train", help="train (or resume) DACN on pre-built DA2T pairs")
    t = dsub.add_parser("export", help="write a trained run's DACN as a shipped .npz (no pickle)",
                        description="Export the EMA weights of a DACN run to .npz (float16 by default) with "
                                    "its spec, training config and DA2T settings; `dcdi correct --model` reads it.")
    add_export_options(t)
    t.set_defaults(func=cmd_dacn_export)
    eval_parser(dsub, "eval", help="score trained DACNs on held-out pairs, per scene and depth band")
    correct_parser(dsub, "correct", network_only=True,
                   help="undo a lens's blur with a trained DACN (`dcdi correct --method dacn`)")
