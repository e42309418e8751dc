"""Beyond one process: --device (auto falls back to the CPU, cuda without a
GPU is refused by name) and torchrun training (2 CPU processes, gloo) that
equals one process with the same global batch, resumes across a changed
world size and leaves one writer's files."""
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from dcdi_core.errors import InputRangeError  # noqa: E402
from dcdi_core.models.common import distributed  # noqa: E402
from dcdi_core.models.common.distributed import Context, resolve_device  # noqa: E402
from conftest import Killed, kill_at  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
# 2 processes against 1: the gradients differ by float rounding (sums in
# another order); Adam divides each by its own RMS, so where a gradient is
# near zero (tiny, cancelling sums) rounding moves that element's update by a
# fraction of the learning rate. Allowed: nearly every weight within 1e-6,
# none further than 5 % of one step (lr); a wrong share (overlapping,
# missing or other samples) moves most weights by about lr.
CLOSE, SHARE_CLOSE, STEP_FRACTION = 1e-6, 0.999, 0.05


@pytest.fixture
def no_cuda(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 0)


# ------------------------------------------------------------------ devices
def test_auto_falls_back_to_the_cpu_and_cuda_without_a_gpu_is_refused(no_cuda):
    assert resolve_device("auto") == torch.device("cpu")
    assert resolve_device("cpu") == torch.device("cpu")
    for name in ("cuda", "cuda:0", "CUDA:1"):
        with pytest.raises(InputRangeError, match=r"--device = .* out of range; allowed: auto or cpu: torch sees "
                                                  r"no CUDA device"):
            resolve_device(name)
    for name in ("gpu", "cuda:x", "cuda:-1", ""):
        with pytest.raises(InputRangeError, match="allowed: auto, cpu, cuda or cuda:N"):
            resolve_device(name)


def test_auto_takes_cuda_when_torch_sees_it_and_a_missing_index_is_refused(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    assert resolve_device("auto") == torch.device("cuda")
    assert resolve_device("cuda:1") == torch.device("cuda:1")
    with pytest.raises(InputRangeError, match=r"cuda:0 to cuda:1 \(2 CUDA device\(s\) seen\)"):
        resolve_device("cuda:2")


def test_commands_refuse_cuda_without_a_gpu_before_any_work(no_cuda, tmp_path, capsys):
    from dcdi_core.cli import main
    run = tmp_path / "run"
    assert main(["dacn", "train", "--data", str(tmp_path / "nothing"), "--iters", "1", "-o", str(run),
                 "--device", "cuda"]) == 2
    err = capsys.readouterr().err
    assert "--device = 'cuda' is out of range" in err and "auto falls back to the CPU" in err
    assert not run.exists()
    assert main(["olf", "train", "--lens", "mos-s1", "--iters", "1", "-o", str(tmp_path / "o.npz"),
                 "--device", "cuda:0"]) == 2
    assert "--device = 'cuda:0'" in capsys.readouterr().err and not (tmp_path / "o.npz.run").exists()
    assert main(["correct", "--image", str(tmp_path / "none.exr"), "--depth", str(tmp_path / "none.exr"),
                 "--model", str(run), "-o", str(tmp_path / "out.exr"), "--device", "cuda"]) == 2
    assert "--device = 'cuda'" in capsys.readouterr().err
    from dcdi_core.models.dacn.correct import load_dacn
    with pytest.raises(InputRangeError, match="--device"):
        load_dacn(tmp_path / "no-such-run", device="cuda")


def test_a_batch_the_processes_cannot_share_equally_is_refused():
    ctx = Context(rank=1, world=2, device=torch.device("cpu"))
    assert ctx.part(8) == slice(4, 8)
    with pytest.raises(InputRangeError, match=r"batch = 5 is out of range; allowed: a multiple of the number of "
                                              r"processes \(2\)"):
        ctx.part(5)


def test_the_ranks_shares_of_a_batch_partition_it():
    from dcdi_core.models.olf.train import local_groups
    rng = np.random.default_rng(0)
    groups = [(li, rng.normal(size=(n, 2)), rng.normal(size=(n, 3)), rng.normal(size=(n, 1)))
              for li, n in ((0, 5), (1, 0), (2, 3))]
    groups = [g for g in groups if len(g[2])]
    whole = np.concatenate([g[2] for g in groups])
    parts = [local_groups(groups, Context(rank=r, world=4).part(8)) for r in range(4)]
    assert [[li for li, *_ in p] for p in parts] == [[0], [0], [0, 2], [2]]
    np.testing.assert_array_equal(np.concatenate([y for p in parts for _, _, y, _ in p]), whole)


# ------------------------------------------------------------------ torchrun, 2 CPU processes
def _torchrun(args, env_extra=None, n=2, timeout=240):
    """`torchrun --standalone --nproc-per-node n -m dcdi_core ARGS`; (seconds, output)."""
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get(
        "PYTHONPATH", ""), **(env_extra or {})}
    for k in ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT"):
        env.pop(k, None)
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc-per-node={n}",
           "-m", "dcdi_core", *args]
    t0 = time.perf_counter()
    p = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=timeout)
    assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-3000:]
    return time.perf_counter() - t0, p.stdout + p.stderr


def _weights(run: Path) -> dict:
    ck = torch.load(run / "checkpoint.pt", weights_only=True)
    return {**{f"model.{k}": v for k, v in ck["model"].items()}, **{f"ema.{k}": v for k, v in ck["ema"].items()},
            "step": ck["step"]}


def _compare(a: dict, b: dict, lr: float) -> tuple[float, float]:
    """(max abs weight difference, share of weights within CLOSE), both
    checked against the allowance above."""
    assert a.keys() == b.keys() and a["step"] == b["step"]
    d = torch.cat([(a[k].double() - b[k].double()).abs().reshape(-1) for k in a if k != "step"])
    worst, share = float(d.max()), float((d <= CLOSE).double().mean())
    assert share >= SHARE_CLOSE and worst <= STEP_FRACTION * lr, (worst, share)
    return worst, share


def _final_records(run: Path) -> list:
    return [r for r in map(json.loads, (run / "log.jsonl").read_text().splitlines()) if r.get("final")]


def test_two_gloo_processes_train_dacn_as_one_process_with_the_same_global_batch(pairs, tmp_path):
    from dcdi_core.models.dacn.config import DACNTrainConfig
    from dcdi_core.models.dacn.train import train_dacn
    ddp = tmp_path / "ddp"
    seconds, out = _torchrun(["dacn", "train", "--data", str(pairs), "--config", "tiny", "--iters", "4",
                              "--batch", "4", "--crop", "16", "--lr", "1e-3", "--channels", "8", "--groups", "1",
                              "--blocks", "2", "--threads", "1", "--checkpoint-every", "2", "--device", "cpu",
                              "-o", str(ddp)])
    assert out.count("trained ") == 1 and "ran on cpu, 2 processes (torchrun)" in out      # rank 0 reports
    config = DACNTrainConfig.from_json((ddp / "config.json").read_text())
    torch.set_num_threads(1)
    one = train_dacn(config, tmp_path / "one")
    assert one.where == {"device": "cpu", "world_size": 1}
    worst, share = _compare(_weights(ddp), _weights(tmp_path / "one"), config.lr)
    print(f"\n2-process DACN: {seconds:.1f} s, max |w_ddp - w_one| = {worst:.3g}, {share:.2%} within {CLOSE}")
    assert [r["world_size"] for r in _final_records(ddp)] == [2]        # one writer of the log
    assert not list(ddp.glob(".*"))                                     # no stray temporaries


@pytest.mark.slow          # about 20 s here (PSFs traced, one process run, then torchrun)
def test_a_run_resumes_across_a_changed_world_size(tmp_path):
    """One process killed after step 4 (checkpoint at 3), resumed by 2
    torchrun processes: it ends where one uninterrupted process does. Two
    lenses: a rank's share of a batch may lack one (its head unused there)."""
    from dcdi_core.models.olf.data import PSFDataConfig
    from dcdi_core.models.olf.config import OLFTrainConfig
    from dcdi_core.models.olf.train import train
    torch.set_num_threads(1)
    cache = tmp_path / "cache"
    data = PSFDataConfig(lenses=("mos-s1", "mos-s2"), pupil_samples=16, n_wavelengths=3, n_fields=3, n_depths=2,
                         offgrid=6, held_out=4)
    config = OLFTrainConfig(data=data, iters=6, batch=16, lr=3e-3, threads=1, checkpoint_every=3)
    straight = train(config, tmp_path / "straight", cache_dir=cache)
    with pytest.raises(Killed):
        train(config, tmp_path / "olf.npz.run", cache_dir=cache, on_step=kill_at(4))
    argv = ("olf train --lens mos-s1 --lens mos-s2 --iters 6 --batch 16 --lr 3e-3 --threads 1 --checkpoint-every 3 "
            "--rays 16 --wavelengths 3 --fields 3 --depths 2 --offgrid 6 --held-out 4 --device auto").split()
    seconds, out = _torchrun([*argv, "-o", str(tmp_path / "olf.npz")], {"DCDI_CACHE_DIR": str(cache)})
    assert "resumed" in out and "at iteration 3 of 6" in out
    worst, share = _compare(_weights(tmp_path / "olf.npz.run"), _weights(tmp_path / "straight"), config.lr)
    print(f"\n2-process OLF resume: {seconds:.1f} s, max |w_ddp - w_one| = {worst:.3g}, {share:.2%} within {CLOSE}")
    assert straight.step == 6 and (tmp_path / "olf.npz").exists()
    assert [r["world_size"] for r in _final_records(tmp_path / "olf.npz.run")] == [2]


def test_distributed_helpers_are_idle_in_one_process():
    ctx = Context.from_environment("cpu")
    assert (ctx.rank, ctx.world, ctx.main, ctx.distributed) == (0, 1, True, False)
    m = torch.nn.Linear(2, 2)
    assert ctx.wrap(m) is m and ctx.mean(torch.tensor(2.5)) == 2.5
    ctx.barrier()
    ctx.close()
    assert distributed.to_cpu({"a": [torch.ones(1)]})["a"][0].device.type == "cpu"
