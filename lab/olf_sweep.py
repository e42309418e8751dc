"""The sweep that chose the shipped Omni-Lens-Field: size x learning rate on
one lens (radial variant, MOS-S1), 1 thread, about the same wall time per
size (iterations from each size's measured speed: tiny 20, small 9.8,
medium 5.1 it/s), held-out figures of the EMA weights, each run exported in
float32 and float16 (the figures of the stored files, by the numpy runtime,
and their largest difference from torch's PSFs).

    python -m lab olf-sweep OUT_DIR [--variant paper]

``--variant paper``: the paper's variant on the same lens at about the same
wall time per size (its on-the-fly rotated targets add ~50 ms a step: tiny
9.9 it/s, small and medium estimated from radial's step plus that), at the
rate that won the radial sweep (1e-3); its figures are on its own targets
(2-D kernels in image orientation, the paper's peak scale).

writes OUT_DIR/results.jsonl (one JSON record per run, appended as each
ends; `python -m lab report olf --sweep OUT_DIR/results.jsonl` tabulates and plots
them) and each run's folder and files. A killed sweep run again resumes.
"""
from __future__ import annotations

import json
import os
import shutil
import time

import numpy as np

from dcdi_core.models import require_torch

torch = require_torch()

from dcdi_core.models.olf.spec import OLFSpec  # noqa: E402
from dcdi_core.models.olf.data import PSFDataConfig, build_data  # noqa: E402
from dcdi_core.models.olf.export import export_olf  # noqa: E402
from dcdi_core.psf.olf import OmniLensField  # noqa: E402
from dcdi_core.models.olf.config import OLFTrainConfig  # noqa: E402
from dcdi_core.models.olf.train import train  # noqa: E402

ITERS = {"tiny": 2400, "small": 1200, "medium": 600}        # ~2 minutes each on one core
RATES = (1e-3, 3e-4)
PAPER_ITERS = {"tiny": 1200, "small": 800, "medium": 480}   # the same ~2 minutes (paper variant)
PAPER_RATES = (1e-3,)
PAPER_LENSES = (("mos-s1", 41), ("mos-s2", 47), ("double-gauss", 129), ("6p", 65))


def run_sweep(out: str, lens: str = "mos-s1", seed: int = 0, variant: str = "radial") -> list[dict]:
    torch.set_num_threads(1)
    os.makedirs(out, exist_ok=True)
    data_cfg = PSFDataConfig(lenses=(lens,), variant=variant, seed=seed)
    iters_of, rates = (ITERS, RATES) if variant == "radial" else (PAPER_ITERS, PAPER_RATES)
    points = os.path.join(out, "points.npz")
    t = time.perf_counter()
    build_data(data_cfg, points_file=points, log=print)
    print(f"data {time.perf_counter() - t:.1f} s", flush=True)
    done = set()
    results = os.path.join(out, "results.jsonl")
    if os.path.exists(results):
        with open(results, encoding="utf-8") as f:
            done = {json.loads(line)["name"] for line in f if line.strip()}
    records = []
    for lr in rates:
        for size, iters in iters_of.items():
            name = f"{size}-lr{lr:g}" + ("" if variant == "radial" else f"-{variant}")
            if name in done:
                continue
            run = os.path.join(out, name + ".run")
            os.makedirs(run, exist_ok=True)
            shutil.copy(points, os.path.join(run, "points.npz"))     # the same traced points for every run
            cfg = OLFTrainConfig(data=data_cfg, size=size, iters=iters, lr=lr, seed=seed, threads=1,
                                 checkpoint_every=10_000)
            r = train(cfg, run)
            rec = {"name": name, "variant": variant, "size": size, "lr": lr, "iters": r.step, "seconds": r.seconds,
                   "params": r.spec.param_count(), "torch": r.held_out["ema"]["mean"]}
            ls = r.data.lenses[0]
            with torch.no_grad():
                x = torch.from_numpy(ls.val_x)
                ref = (r.ema(x) if variant == "paper" else r.ema(x, 0)).double().numpy()
            for dt in ("float32", "float16"):
                p = os.path.join(out, f"{name}-{dt}.npz")
                meta = export_olf(r, p, dtype=dt)
                got = OmniLensField.load(p).forward(ls.val_x, None if variant == "paper" else 0, np.float64)
                diff = np.abs(got - ref)
                rec[dt] = {"bytes": os.path.getsize(p), "held_out": meta["held_out"]["mean"],
                           "max_abs_vs_torch": float(diff.max()),
                           "max_rel_vs_torch": float((diff.max(axis=(-1, -2)) / ref.max(axis=(-1, -2))).max())}
            ids, ks = zip(*PAPER_LENSES)
            if variant == "paper":       # one network for any number of lenses (41 px heads)
                rec["four_lens_params"] = rec["three_lens_params"] = OLFSpec.sized(
                    "paper", ids, [41] * len(ids), size).param_count()
            else:
                rec["four_lens_params"] = OLFSpec.sized("radial", ids, ks, size).param_count()
                rec["three_lens_params"] = OLFSpec.sized("radial", [i for i in ids if i != "double-gauss"],
                                                         [k for i, k in PAPER_LENSES if i != "double-gauss"],
                                                         size).param_count()
            print(json.dumps(rec), flush=True)
            with open(results, "a", encoding="utf-8") as f:
                f.write(json.dumps(rec) + "\n")
            records.append(rec)
    return records


def main(argv=None) -> int:
    import argparse
    ap = argparse.ArgumentParser(prog="python -m lab olf-sweep", description="the OLF sweep (module docstring)")
    ap.add_argument("out", nargs="?", default="out/sweep")
    ap.add_argument("--variant", choices=["radial", "paper"], default="radial")
    ap.add_argument("--lens", default="mos-s1")
    a = ap.parse_args(argv)
    run_sweep(a.out, lens=a.lens, variant=a.variant)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
