"""The DACN study: what each ingredient of the correction earns, at equal
budget, with two seeds, on held-out scenes at the paper's pitch with noise.

    python -m lab dacn-study OUT --lens mos-s2 \\
        --train PAIRS_TRAIN --test PAIRS_TEST --iters 2000 --seeds 0,1 --jobs 2

Each row and seed is a ``dcdi dacn train`` process (``jobs`` at a time, one
thread each; resumable, so the same command again finishes a cut study;
finished runs are not trained again), all with the same configuration
(``--config``), iterations, batch, crop, learning rate and training pairs;
only what the row names differs. Then ``dcdi dacn eval`` scores every run
on the test pairs (other scenes than the training pairs', built with the
nominal lens) beside the capture and the deconvolution alone.

Rows (``RUNS``):
- ``baseline``: the paper's depth-unaware training: the one-depth baseline
  captures, no depth, no field, no deconvolution;
- ``da2t``: the same network trained on the depth-aware captures (DA2T);
- ``da2t+cond``: DA2T with the depth and field maps as input channels (the
  network on the capture alone);
- ``refine``: ``da2t+cond`` refining the deconvolution (its input, and the
  base of its output): the shipped design;
- ``refine+mech``: ``refine`` with the paper's RDICAB and D2CB;
- ``refine@2m``: ``refine`` trained the depth-unaware way (the one-depth
  captures, told that depth everywhere, refining the one-depth
  deconvolution; ``models.dacn.unaware``) and tested told it too: only
  depth differs from ``refine``. Its pairs are derived from the training
  pairs into ``OUT/<lens>/pairs-told-<depth>m``.

Writes ``OUT/<lens>/<row>-s<seed>/`` (runs), ``OUT/<lens>/eval.json``,
``OUT/<lens>/table.md`` (mean of the seeds and each seed; per depth and field
band; linear and sRGB; imaged pixels and every pixel) and
``OUT/<lens>/curves.png`` (validation PSNR against iterations).
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

from dcdi_core.atomic import write_text

PLAIN = ["--no-condition", "--no-refine", "--no-rdicab", "--no-d2cb"]
RUNS = {
    "baseline": ["--input", "baseline", *PLAIN],
    "da2t": ["--input", "capture", *PLAIN],
    "da2t+cond": ["--input", "capture", "--condition", "--no-refine", "--no-rdicab", "--no-d2cb"],
    "refine": ["--input", "capture", "--condition", "--refine", "--no-rdicab", "--no-d2cb"],
    "refine+mech": ["--input", "capture", "--condition", "--refine", "--rdicab", "--d2cb"],
    "refine@2m": ["--input", "capture", "--condition", "--refine", "--no-rdicab", "--no-d2cb"],
}
TOLD_DEPTH_M = {"refine@2m": 2.0}     # rows trained on derived one-depth pairs (models.dacn.unaware)
DEFAULT_RUNS = ("baseline", "da2t", "da2t+cond", "refine")


def run_flags(name: str) -> list:
    """The ``dcdi dacn train`` options that make row ``name``."""
    if name not in RUNS:
        raise SystemExit(f"dacn_study: unknown row {name!r}: one of {', '.join(RUNS)}")
    return list(RUNS[name])


def run_name(name: str, seed: int) -> str:
    return f"{name}-s{seed}"


def train_command(data: str, folder: Path, name: str, seed: int, args) -> list:
    return [sys.executable, "-m", "dcdi_core", "dacn", "train", "--data", data, "--config", args.config,
            "--iters", str(args.iters), "-o", str(folder), "--seed", str(seed), "--threads", "1",
            "--batch", str(args.batch), "--crop", str(args.crop), "--lr", str(args.lr),
            "--validate-every", str(args.validate_every), "--checkpoint-every", str(args.validate_every),
            "--ema-decay", str(args.ema_decay),
            *run_flags(name)]


def finished(folder: Path) -> bool:
    return bool(final_record(folder))


def log_records(folder: Path) -> list:
    log = folder / "log.jsonl"
    if not log.exists():
        return []
    return [json.loads(s) for s in log.read_text().splitlines() if s.strip()]


def final_record(folder: Path) -> dict:
    return next((r for r in log_records(folder) if r.get("final")), {})


def train_all(jobs: list, n_parallel: int) -> None:
    """Run (command, folder) jobs, ``n_parallel`` at a time; a failure stops the study."""
    todo = [j for j in jobs if not finished(j[1])]
    running = []
    while todo or running:
        while todo and len(running) < n_parallel:
            cmd, folder = todo.pop(0)
            folder.mkdir(parents=True, exist_ok=True)
            log = open(folder.parent / f"{folder.name}.log", "a")
            print(f"dacn_study: training {folder}", file=sys.stderr)
            running.append((subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT), folder, log))
        time.sleep(2)
        for item in list(running):
            proc, folder, log = item
            if proc.poll() is not None:
                log.close()
                running.remove(item)
                if proc.returncode != 0:
                    for p, _, lg in running:
                        p.terminate()
                        lg.close()
                    raise SystemExit(f"dacn_study: {folder} failed (exit {proc.returncode}); see {folder}.log")
                print(f"dacn_study: finished {folder}", file=sys.stderr)


def evaluate(out: Path, lens: str, test: str, runs: list, weights: str) -> dict:
    first, rest = runs[0], runs[1:]
    cmd = [sys.executable, "-m", "dcdi_core", "dacn", "eval", str(out / lens / first), "--data", test,
           "--name", first, "--json", str(out / lens / "eval.json"), "--pictures", str(out / lens / "pictures"),
           "--weights", weights]
    for n in rest:
        cmd += ["--compare", f"{n}={out / lens / n}"]
    subprocess.run(cmd, check=True)
    return json.loads((out / lens / "eval.json").read_text())


def _mean(xs):
    return sum(xs) / len(xs)


def table(lens: str, ev: dict, out: Path, names: list, seeds: list, args) -> str:
    """One lens's study as Markdown: the rows (mean of the seeds, then each
    seed), then the depth and field bands of each row's mean."""
    mean = ev["mean"]
    n_pairs = len(ev["pairs"])
    lines = [f"{lens}: `{args.config}` design, {args.iters} iterations of batch {args.batch} x {args.crop}^2, lr "
             f"{args.lr:g} (cosine), {args.weights} weights (EMA {args.ema_decay:g}); seeds {', '.join(map(str, seeds))}; {n_pairs} held-out "
             "pairs; PSNR dB.\n",
             "| row | PSNR imaged | each seed | SSIM | PSNR sRGB | PSNR every pixel | vs capture | vs deconvolution "
             "| training min (1 core) |",
             "|---|---|---|---|---|---|---|---|---|"]
    cap = mean["capture"]["psnr"]
    dec = mean.get("deconvolution", {}).get("psnr")
    fixed = ["capture"] + (["deconvolution"] if "deconvolution" in mean else [])
    def vs_dec(v):
        return "" if dec is None else f"{v - dec:+.2f}"

    for n in fixed:
        m = mean[n]
        lines.append(f"| {n} | {m['psnr']:.2f} | | {m['ssim']:.4f} | {m['psnr_srgb']:.2f} | {m['psnr_unmasked']:.2f} "
                     f"| {m['psnr'] - cap:+.2f} | {vs_dec(m['psnr'])} | |")
    for n in names:
        runs = [run_name(n, s) for s in seeds]
        ms = [mean[r] for r in runs]
        avg = {k: _mean([m[k] for m in ms]) for k in ("psnr", "ssim", "psnr_srgb", "psnr_unmasked")}
        minutes = _mean([final_record(out / lens / r).get("seconds", 0.0) for r in runs]) / 60
        each = " / ".join(f"{m['psnr']:.2f}" for m in ms)
        lines.append(f"| {n} | {avg['psnr']:.2f} | {each} | {avg['ssim']:.4f} "
                     f"| {avg['psnr_srgb']:.2f} | {avg['psnr_unmasked']:.2f} | {avg['psnr'] - cap:+.2f} "
                     f"| {vs_dec(avg['psnr'])} | {minutes:.0f} |")
    text = "\n".join(lines) + "\n"
    for kind in ("bands", "fields"):
        scores = ev.get(kind) or {}
        cols = list(scores.get("capture", {}))
        if not cols:
            continue
        rows = [f"| {'depth' if kind == 'bands' else 'field'} band (PSNR, mean of seeds) | " + " | ".join(cols) + " |",
                "|" + "---|" * (len(cols) + 1)]
        for n in fixed + names:
            keys = [n] if n in fixed else [run_name(n, s) for s in seeds]
            cells = []
            for c in cols:
                vals = [scores[k][c]["psnr"] for k in keys if "psnr" in scores[k].get(c, {})]
                cells.append(f"{_mean(vals):.2f}" if vals else "-")
            rows.append(f"| {n} | " + " | ".join(cells) + " |")
        px = [scores["capture"][c]["pixels"] for c in cols]
        rows.append("| share of pixels | " + " | ".join(f"{100 * p / max(sum(px), 1):.1f} %" for p in px) + " |")
        text += "\n" + "\n".join(rows) + "\n"
    return text


def plot_curves(path: Path, out: Path, lens: str, names: list, seeds: list) -> None:
    """Validation PSNR (EMA weights, the validation scenes' centre crops)
    against iterations, a line per run, and the input's PSNR dashed."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(7, 4.2), dpi=110)
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for i, n in enumerate(names):
        for j, s in enumerate(seeds):
            recs = [r for r in log_records(out / lens / run_name(n, s)) if (r.get("val_ema") or {}).get("psnr")]
            if not recs:
                continue
            ax.plot([r["step"] for r in recs], [r["val_ema"]["psnr"] for r in recs], color=colours[i % len(colours)],
                    ls="-" if j == 0 else ":", label=f"{n} (seed {s})")
            if i == 0 and j == 0:
                ax.axhline(recs[-1]["val_ema"]["psnr_input"], color="grey", ls="--", lw=0.8, label="its input")
    ax.set_xlabel("iteration")
    ax.set_ylabel("validation PSNR, dB")
    ax.set_title(f"{lens}: learning curves (validation scenes)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)


DEPTHS_M = (0.7, 1.0, 2.0, 5.0, 10.0, float("inf"))
FIELDS = (0.0, 0.5, 0.9)


def blur_table(pairs_dir: str, pitch_um: float = 12.2) -> str:
    """RMS spot radius (px at ``pitch_um``, green) of the pairs' nominal lens
    and of each perturbed lens of their pool, per depth (rows) and field."""
    from dcdi_core.models.dacn.data import DA2TConfig, finished_pairs, perturbed
    from dcdi_core.optics.analysis import spot_diagram
    from dcdi_core.optics.lens import load_lens
    cfg = DA2TConfig.from_dict(json.loads(Path(pairs_dir, "da2t.json").read_text()))
    base = load_lens(cfg.lens)
    seeds = sorted({r["perturbation"]["seed"] for r in finished_pairs(pairs_dir).values()} - {None})
    lenses = [("nominal", base)] + [(f"pool {s}", perturbed(base, cfg.perturb_fraction, s, cfg.refocus)[0])
                                    for s in seeds]
    head = "| lens | field | " + " | ".join(f"{d:g} m" for d in DEPTHS_M) + " |"
    lines = [f"RMS blur radius, px at {pitch_um:g} um (550 nm), {cfg.lens}, perturbation +-{cfg.perturb_fraction:.0%}"
             f"{' refocused' if cfg.refocus else ''}:\n", head, "|---|---|" + "---|" * len(DEPTHS_M)]
    for name, lens in lenses:
        sp = spot_diagram(lens, list(DEPTHS_M), [550.0], field=list(FIELDS), rays=64)
        px = sp.rms_radius_mm[:, :, 0] * 1000.0 / pitch_um
        for i, f in enumerate(FIELDS):
            lines.append(f"| {name} | {f:g} | " + " | ".join(f"{v:.1f}" for v in px[i]) + " |")
    return "\n".join(lines) + "\n"


def data_table(pairs_dir: str, n: int = 40) -> str:
    """PSNR of the capture and of the deconvolution (imaged pixels), the
    target's clipped share and its high-frequency texture energy, over the
    first ``n`` pairs (by id) of a folder."""
    import numpy as np

    from dcdi_core.dataset.statistics import high_frequency_share
    from dcdi_core.models.common.metrics import psnr
    from dcdi_core.models.dacn.data import finished_pairs, load_pair, pair_path
    recs = finished_pairs(pairs_dir)
    ids = sorted(recs)[:: max(1, len(recs) // n)][:n]
    cap, dec, clip, hf = [], [], [], []
    for pid in ids:
        p = load_pair(pair_path(pairs_dir, pid), recs[pid])
        v = ~np.isnan(p.depth)
        t = np.asarray(p.target)
        cap.append(psnr(np.asarray(p.capture)[v], t[v], 1.0))
        if p.deconvolved is not None:
            dec.append(psnr(np.asarray(p.deconvolved)[v], t[v], 1.0))
        clip.append(float((t[v] >= 1.0).any(axis=-1).mean()))
        hf.append(high_frequency_share(t))
    q = lambda xs: f"{np.median(xs):.2f} ({np.min(xs):.2f}-{np.max(xs):.2f})" if xs else "-"  # noqa: E731
    return (f"{len(ids)} of {len(recs)} pairs of {pairs_dir}: capture PSNR {q(cap)} dB, deconvolution {q(dec)} dB, "
            f"clipped target pixels {q([100 * c for c in clip])} %, high-frequency share {q([100 * h for h in hf])} %"
            " (median, min-max)\n")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m lab dacn-study",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--lens", required=True, help="the lens id (a folder name under OUT)")
    ap.add_argument("--train", required=True, help="training pairs folder (dcdi dacn pairs)")
    ap.add_argument("--test", required=True, help="test pairs folder: other scenes, the nominal lens")
    ap.add_argument("--runs", default=",".join(DEFAULT_RUNS), help=f"rows (default {','.join(DEFAULT_RUNS)})")
    ap.add_argument("--seeds", default="0,1", help="seeds of each row (default 0,1)")
    ap.add_argument("--config", default="refine")
    ap.add_argument("--iters", type=int, default=2000)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--crop", type=int, default=128)
    ap.add_argument("--lr", type=float, default=1e-3)
    ap.add_argument("--validate-every", type=int, default=250)
    ap.add_argument("--ema-decay", type=float, default=0.995,
                    help="weights' EMA (default 0.995: a time constant of 200 iterations)")
    ap.add_argument("--jobs", type=int, default=2, help="trainings at a time (one core each)")
    ap.add_argument("--weights", choices=["ema", "model"], default="ema")
    args = ap.parse_args(argv)
    for d, what in ((args.train, "--train"), (args.test, "--test")):
        if not Path(d, "pairs.jsonl").exists():
            raise SystemExit(f"dacn_study: {what} {d}: no pairs.jsonl there (dcdi dacn pairs)")
    names = [n.strip() for n in args.runs.split(",") if n.strip()]
    seeds = [int(s) for s in args.seeds.split(",") if s.strip()]
    for n in names:
        run_flags(n)
    look = blur_table(args.train) + "\n" + data_table(args.train) + data_table(args.test)
    write_text(args.out / args.lens / "data.md", look)
    print(look)
    data = {n: args.train for n in names}
    for n in names:
        if n in TOLD_DEPTH_M:
            from dcdi_core.models.dacn.unaware import derive_pairs
            data[n] = str(args.out / args.lens / f"pairs-told-{TOLD_DEPTH_M[n]:g}m")
            print(f"dacn_study: {n}: deriving its one-depth pairs into {data[n]}", file=sys.stderr)
            derive_pairs(args.train, data[n], TOLD_DEPTH_M[n])
    jobs = [(train_command(data[n], args.out / args.lens / run_name(n, s), n, s, args),
             args.out / args.lens / run_name(n, s)) for s in seeds for n in names]
    train_all(jobs, args.jobs)
    ev = evaluate(args.out, args.lens, args.test, [run_name(n, s) for n in names for s in seeds], args.weights)
    text = table(args.lens, ev, args.out, names, seeds, args)
    write_text(args.out / args.lens / "table.md", text)
    plot_curves(args.out / args.lens / "curves.png", args.out, args.lens, names, seeds)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
