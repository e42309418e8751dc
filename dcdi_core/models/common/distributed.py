"""Where a training or inference run computes: the device (``--device``) and,
under ``torchrun``, the process group.

``resolve_device("auto" | "cpu" | "cuda" | "cuda:N")``: auto is CUDA when
torch sees a device, else the CPU; an explicit CUDA device that torch does
not see is refused (``InputRangeError`` naming ``--device``) before any work.

``Context.from_environment(device)``: one process (rank 0 of 1) unless
``torchrun`` set ``WORLD_SIZE`` > 1, ``RANK`` and ``LOCAL_RANK``; then the
process group is joined (gloo on the CPU, nccl on CUDA; each process takes
``cuda:LOCAL_RANK``). Every rank draws the same global batch from the same
seeded generator and keeps its slice (``Context.part``: rows
``rank * B / W`` to ``(rank + 1) * B / W``, no overlap); DistributedDataParallel
averages the gradients, so with a mean loss an update equals the one process
update with the same global batch (to floating-point rounding). Rank 0 alone
writes checkpoints and logs; the state it writes does not depend on the
world size, so a run may resume under another one. The others wait for it
(the PSFs it traces, its checkpoints) up to DCDI_DIST_TIMEOUT_S seconds
(default 6 hours).
"""
from __future__ import annotations

import os
from contextlib import contextmanager
from dataclasses import dataclass

from ...errors import InputRangeError
from .. import require_torch

torch = require_torch()

DEVICES = "auto, cpu, cuda or cuda:N"
# how long a process waits for the others at a barrier, s: rank 0 may trace
# an OLF's PSF libraries (hours at the paper's settings) while they wait
DEFAULT_TIMEOUT_S = 6 * 3600


def resolve_device(name: str = "auto", *, option: str = "--device"):
    """The ``torch.device`` that ``name`` means here (see the module)."""
    text = str(name).strip().lower()
    if text == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if text == "cpu":
        return torch.device("cpu")
    index = _cuda_index(text, name, option)
    if not torch.cuda.is_available():
        raise InputRangeError(option, name, "auto or cpu: torch sees no CUDA device here (a CPU-only torch, no "
                                            "GPU or no driver); auto falls back to the CPU")
    count = torch.cuda.device_count()
    if index is not None and index >= count:
        raise InputRangeError(option, name, f"cuda:0 to cuda:{count - 1} ({count} CUDA device(s) seen), "
                                            "cuda, cpu or auto")
    return torch.device("cuda" if index is None else f"cuda:{index}")


def _cuda_index(text: str, name, option: str):
    """None for 'cuda', N for 'cuda:N'; anything else refused."""
    if text == "cuda":
        return None
    head, _, tail = text.partition(":")
    if head == "cuda" and tail.isdigit():
        return int(tail)
    raise InputRangeError(option, name, DEVICES)


def describe(device) -> str:
    """'cpu', or 'cuda:0 (NVIDIA ...)': what a run records as its device."""
    device = torch.device(device)
    if device.type != "cuda":
        return str(device)
    index = device.index if device.index is not None else torch.cuda.current_device()
    return f"cuda:{index} ({torch.cuda.get_device_name(index)})"


def _env_int(name: str, default: int) -> int:
    value = os.environ.get(name)
    if value is None or value == "":
        return default
    try:
        return int(value)
    except ValueError:
        raise InputRangeError(f"environment variable {name}", value, "an integer (set by torchrun)") from None


@dataclass
class Context:
    """This process's place in a run: rank of world, its device, and whether
    it joined (and so must leave) a process group."""

    rank: int = 0
    world: int = 1
    local_rank: int = 0
    device: object = None
    owns_group: bool = False

    @property
    def main(self) -> bool:
        """Rank 0: the one writer of checkpoints, logs and exports."""
        return self.rank == 0

    @property
    def distributed(self) -> bool:
        return self.world > 1

    @classmethod
    def from_environment(cls, device: str = "auto") -> "Context":
        """The context of this process (joins torchrun's group when WORLD_SIZE > 1)."""
        world = _env_int("WORLD_SIZE", 1)
        rank, local = _env_int("RANK", 0), _env_int("LOCAL_RANK", 0)
        if world < 1 or not 0 <= rank < world:
            raise InputRangeError("RANK, WORLD_SIZE", (rank, world), "0 <= RANK < WORLD_SIZE (set by torchrun)")
        dev = resolve_device(device)
        if world == 1:
            return cls(device=dev)
        if dev.type == "cuda":
            if device.strip().lower() not in ("auto", "cuda"):
                raise InputRangeError("--device", device, "auto or cuda under torchrun (each process takes "
                                                          "cuda:LOCAL_RANK), or cpu")
            dev = torch.device(f"cuda:{local}")
            torch.cuda.set_device(dev)
        import torch.distributed as dist
        owns = not dist.is_initialized()
        if owns:
            from datetime import timedelta
            wait = _env_int("DCDI_DIST_TIMEOUT_S", DEFAULT_TIMEOUT_S)
            dist.init_process_group("nccl" if dev.type == "cuda" else "gloo", rank=rank, world_size=world,
                                    timeout=timedelta(seconds=wait))
        return cls(rank, world, local, dev, owns)

    def part(self, batch: int, name: str = "batch") -> slice:
        """This rank's rows of a global batch of ``batch`` (refused unless the
        world size divides it: every rank must hold as many)."""
        if batch % self.world:
            raise InputRangeError(name, batch, f"a multiple of the number of processes ({self.world})")
        n = batch // self.world
        return slice(self.rank * n, (self.rank + 1) * n)

    def barrier(self) -> None:
        if self.distributed:
            import torch.distributed as dist
            dist.barrier()

    def wrap(self, module, *, find_unused_parameters: bool = False):
        """``module`` itself alone, in DistributedDataParallel across processes."""
        if not self.distributed:
            return module
        from torch.nn.parallel import DistributedDataParallel
        ids = [self.device.index] if self.device.type == "cuda" else None
        return DistributedDataParallel(module, device_ids=ids, find_unused_parameters=find_unused_parameters)

    @contextmanager
    def main_first(self):
        """Rank 0 runs the block first (it may write shared files: a split, a
        points file, a PSF cache), the others after it, reading them."""
        if not self.main:
            self.barrier()
        yield
        if self.main:
            self.barrier()

    def mean(self, value) -> float:
        """A scalar tensor's mean over the processes (the global batch's loss
        from each rank's mean over its equal share)."""
        if not self.distributed:
            return float(value)
        import torch.distributed as dist
        t = value.detach().reshape(1).to(self.device, torch.float64)
        dist.all_reduce(t)
        return float(t) / self.world

    def close(self, clean: bool = True) -> None:
        """Leave the process group this context joined (after waiting for the
        others, unless the run failed: a failed rank does not wait)."""
        if self.owns_group:
            import torch.distributed as dist
            if clean:
                dist.barrier()
            dist.destroy_process_group()
            self.owns_group = False

    def record(self) -> dict:
        """What a run's log records of where it ran (operational: not a setting)."""
        return {"device": describe(self.device), "world_size": self.world}


class LossModule(torch.nn.Module):
    """``loss_fn(model, *batch)`` as one module's forward, so that
    DistributedDataParallel sees a whole step in one forward call."""

    def __init__(self, model, loss_fn):
        super().__init__()
        self.model = model
        self.loss_fn = loss_fn

    def forward(self, *batch):
        return self.loss_fn(self.model, *batch)


def to_cpu(obj):
    """Tensors in a (nested) state dict moved to the CPU, so a checkpoint
    written on a GPU loads anywhere."""
    if isinstance(obj, torch.Tensor):
        return obj.detach().cpu()
    if isinstance(obj, dict):
        return {k: to_cpu(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return type(obj)(to_cpu(v) for v in obj)
    return obj
