"""How much memory this machine can give, and refusing work that would not fit.

An estimate is checked before the work starts, so that a run too large for
the machine is refused with a message naming the options to lower, instead
of a MemoryError deep inside numpy or the kernel's OOM killer ending the
process without a word.
"""
from __future__ import annotations

import os

from .errors import MemoryLimitError

# refuse when the estimate exceeds this share of the available memory
SAFETY = 0.9


def _cgroup_room() -> int | None:
    """Bytes left under this process's cgroup (v2) memory limit, if it has one."""
    try:
        with open("/proc/self/cgroup") as f:
            rel = next((line.split("::", 1)[1].strip() for line in f if line.startswith("0::")), None)
        if rel is None:
            return None
        base = os.path.join("/sys/fs/cgroup", rel.lstrip("/"))
        with open(os.path.join(base, "memory.max")) as f:
            limit = f.read().strip()
        if limit == "max":
            return None
        with open(os.path.join(base, "memory.current")) as f:
            used = int(f.read().strip())
        return max(0, int(limit) - used)
    except (OSError, ValueError, StopIteration):
        return None


def available_bytes() -> int | None:
    """Memory a new allocation can use now: Linux's MemAvailable (and the
    cgroup's room, if smaller), else the physical memory; None if unknown."""
    found = None
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    found = int(line.split()[1]) * 1024
                    break
    except (OSError, ValueError):
        pass
    if found is None:
        found = _physical_bytes()
        if found is None:
            return None
    room = _cgroup_room()
    return found if room is None else min(found, room)


def gib(n: float) -> str:
    return f"{n / 2 ** 30:.1f} GiB" if n >= 2 ** 30 else f"{n / 2 ** 20:.0f} MiB"


def check_fits(estimate_bytes: float, what: str, advice: str, *, available: int | None = None) -> None:
    """Raise :class:`MemoryLimitError` when ``estimate_bytes`` would not fit.

    ``what`` names the work and the options that size it ("--rays 4096 x
    --wavelengths 31 x --kernel 41"); ``advice`` says what to lower."""
    have = available_bytes() if available is None else available
    if have is None or estimate_bytes <= SAFETY * have:
        return
    raise MemoryLimitError(f"{what} needs about {gib(estimate_bytes)} of memory, but {gib(have)} are available; "
                           f"{advice}")


# Peak bytes a job holds per image pixel, beyond the interpreter's ~0.25 GiB:
# the growth of the peak RSS from 320 x 480 to 1280 x 1920 (the synthetic
# scene, MOS-S1, its PSF basis; `dcdi bench memory`, docs/performance.md):
# simulate 259, bokeh 298-336, correct (deconvolution) 327-331; with a
# margin, and dof running both stages.
JOB_BYTES_PER_PIXEL = {"simulate": 320, "bokeh": 420, "correct": 420, "dof": 520}


def image_job_bytes(height: int, width: int, job: str) -> float:
    """About how much memory ``job`` needs on a ``height`` x ``width`` image."""
    return float(height) * float(width) * JOB_BYTES_PER_PIXEL[job]


def check_image_job(height: int, width: int, job: str, image: str, *, available: int | None = None) -> None:
    """Refuse, before any pixel is read, an image too large for this
    machine's memory for ``job`` (:data:`JOB_BYTES_PER_PIXEL`); the refusal
    names the image, the figure needed and what is free."""
    need = image_job_bytes(height, width, job)
    have = available_bytes() if available is None else available
    if have is None or need <= SAFETY * have:
        return
    total = _physical_bytes()
    of = f" of this machine's {gib(total)}" if total else ""
    raise MemoryLimitError(f"{image}: {width} x {height} px; {job} needs about {gib(need)} of memory for it, but "
                           f"{gib(have)}{of} are free; use a smaller image (or crop it into parts)")


def _physical_bytes() -> int | None:
    try:
        return os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None
