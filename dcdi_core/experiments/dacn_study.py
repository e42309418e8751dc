"""The paper's DACN tables at this machine's scale, at equal budget.

    python -m dcdi_core.experiments.dacn_study OUT --pairs mos-s1=DIR1 --pairs mos-s2=DIR2 \\
        --iters 2000 --config tiny-rb --jobs 2

For each lens, the runs of ``RUNS`` (same configuration, iterations, data,
split and seed; only what the row names differs) are trained as separate
``dcdi train dacn`` processes (``jobs`` at a time, one thread each; each is
resumable, so the same command again finishes a cut study), then scored
together by ``dcdi eval`` on the held-out pairs of that lens's data, every
model on the depth-aware captures. ``OUT/<lens>/<run>/`` are the runs,
``OUT/<lens>/eval.json`` the scores, ``OUT/<lens>/pictures/`` capture |
corrections | target, ``OUT/<lens>/table.md`` its table (a later call with
more rows adds them: finished runs are not trained again).

The rows (the paper's Tables on NYUv2 with the RB module):
- ``baseline``: depth-unaware: trained on the one-depth baseline, neither
  depth mechanism (depth is not an input);
- ``da2t``: the same network trained on the depth-aware captures;
- ``dacn``: DA2T with RDICAB and D2CB;
- ``dacn-diopter``: ``dacn`` with metric inverse depth at the input instead
  of the per-crop min-max;
- ``dacn-rstb``: ``dacn`` with Swin blocks (RSTB) in place of the
  configuration's; ``dacn-c24`` / ``dacn-c72``: 24 or 72 channels (size
  against error);
- ``scenes=N``: ``dacn`` on N of the training scenes (the data-size curve).
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

from ..atomic import write_text

NO_DEPTH = ["--no-rdicab", "--no-d2cb"]
RUNS = {
    "baseline": ["--input", "baseline", *NO_DEPTH],
    "da2t": ["--input", "capture", *NO_DEPTH],
    "dacn": ["--input", "capture"],
    "dacn-diopter": ["--input", "capture", "--depth-encoding", "diopter"],
    "dacn-rstb": ["--input", "capture", "--racm", "rstb"],
    "dacn-c24": ["--input", "capture", "--channels", "24"],
    "dacn-c72": ["--input", "capture", "--channels", "72"],
}
DEFAULT_RUNS = ("baseline", "da2t", "dacn")


def run_flags(name: str) -> list:
    """The ``dcdi train dacn`` options that make row ``name``."""
    if name in RUNS:
        return list(RUNS[name])
    if name.startswith("scenes="):
        n = name.split("=", 1)[1]
        if n.isdigit() and int(n) > 0:
            return ["--input", "capture", "--train-scenes", n]
    raise SystemExit(f"dacn_study: unknown run {name!r}: one of {', '.join(RUNS)} or scenes=N (N >= 1)")


def label(name: str) -> str:
    """A row's name in folders and score tables ('scenes=34' -> 'scenes-34')."""
    return name.replace("=", "-")


def run_folder(out: Path, lens: str, name: str) -> Path:
    return out / lens / label(name)


def train_command(data: str, folder: Path, name: str, args) -> list:
    return [sys.executable, "-m", "dcdi_core", "train", "dacn", "--data", data, "--config", args.config,
            "--iters", str(args.iters), "-o", str(folder), "--seed", str(args.seed), "--threads", "1",
            "--batch", str(args.batch), "--crop", str(args.crop), "--lr", str(args.lr), *run_flags(name)]


def finished(folder: Path) -> bool:
    log = folder / "log.jsonl"
    return log.exists() and any(json.loads(s).get("final") for s in log.read_text().splitlines() if s.strip())


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


def training_seconds(folder: Path) -> float:
    recs = [json.loads(s) for s in (folder / "log.jsonl").read_text().splitlines() if s.strip()]
    return float(sum(r["seconds"] for r in recs if r.get("final")))


def evaluate_lens(out: Path, lens: str, data: str, names: list, weights: str = "model") -> dict:
    first, rest = names[0], names[1:]
    cmd = [sys.executable, "-m", "dcdi_core", "eval", str(run_folder(out, lens, first)), "--data", data,
           "--name", label(first), "--json", str(out / lens / "eval.json"), "--pictures", str(out / lens / "pictures"),
           "--weights", weights]
    for n in rest:
        cmd += ["--compare", f"{label(n)}={run_folder(out, lens, n)}"]
    subprocess.run(cmd, check=True)
    return json.loads((out / lens / "eval.json").read_text())


def table(lens: str, ev: dict, secs: dict, names: list, args) -> str:
    """One lens's rows as Markdown."""
    lines = [f"{lens}: DACN `{args.config}`, {args.iters} iterations, batch {args.batch} of {args.crop}^2, lr "
             f"{args.lr:g}, seed {args.seed}; {args.weights} weights; {len(ev['pairs'])} held-out pairs; PSNR dB / SSIM "
             "over the imaged pixels.\n",
             "| row | PSNR | SSIM | vs capture | training wall min |", "|---|---|---|---|---|"]
    cap = ev["mean"]["capture"]
    lines.append(f"| capture (uncorrected) | {cap['psnr']:.2f} | {cap['ssim']:.4f} | | |")
    for n in names:
        m = ev["mean"][label(n)]
        lines.append(f"| {n} | {m['psnr']:.2f} | {m['ssim']:.4f} | {m['psnr'] - cap['psnr']:+.2f} dB "
                     f"| {secs[n] / 60:.1f} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m dcdi_core.experiments.dacn_study", description=__doc__.split("\n\n")[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--pairs", action="append", required=True, metavar="LENS=DIR", help="a lens's pairs folder")
    ap.add_argument("--runs", default=",".join(DEFAULT_RUNS), help=f"rows (default {','.join(DEFAULT_RUNS)})")
    ap.add_argument("--config", default="tiny-rb")
    ap.add_argument("--iters", type=int, default=2000)
    ap.add_argument("--batch", type=int, default=4)
    ap.add_argument("--crop", type=int, default=128)
    ap.add_argument("--lr", type=float, default=2e-4, help="initial learning rate (the paper's 2e-4)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--jobs", type=int, default=2, help="trainings at a time (one core each)")
    ap.add_argument("--weights", choices=["ema", "model"], default="model",
                    help="weights scored (default model: at a few thousand iterations the EMA's 0.999 still "
                         "holds a share of the initial network)")
    args = ap.parse_args(argv)
    lenses = {}
    for item in args.pairs:
        lens, sep, d = item.partition("=")
        if not sep or not Path(d, "pairs.jsonl").exists():
            raise SystemExit(f"dacn_study: --pairs {item!r}: expected LENS=DIR with DIR/pairs.jsonl")
        lenses[lens] = d
    names = [n.strip() for n in args.runs.split(",") if n.strip()]
    for n in names:
        run_flags(n)
    jobs = [(train_command(d, run_folder(args.out, lens, n), n, args), run_folder(args.out, lens, n))
            for n in names for lens, d in lenses.items()]
    train_all(jobs, args.jobs)
    for lens, d in lenses.items():
        ev = evaluate_lens(args.out, lens, d, names, args.weights)
        text = table(lens, ev, {n: training_seconds(run_folder(args.out, lens, n)) for n in names}, names, args)
        write_text(args.out / lens / "table.md", text)
        print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
