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
        try:
            found = os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
        except (ValueError, OSError, AttributeError):
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
