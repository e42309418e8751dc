"""This process's CPU seconds and resident memory, for the factory's
timings (the manifest's ``cpu_seconds`` and ``stage_seconds``) and its
progress lines."""
from __future__ import annotations

import math


def cpu_seconds() -> float:
    """CPU seconds (user + system) of this process, all threads."""
    try:
        import resource
    except ImportError:           # not on Windows
        return math.nan
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def rss_mib() -> float:
    """Current resident memory (Linux /proc), else the peak (resource), MiB."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    try:
        import resource
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    except ImportError:
        return math.nan
