"""The process-wide worker pool shared by the ray tracer, the PSF map and the
convolution.

numpy releases the GIL inside its element-wise loops and FFTs, so threads
run chunks of one array operation in parallel. One pool serves every caller:
nested pools would oversubscribe the cores. It is made on first use.
"""
from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager

from . import caches

_POOL: ThreadPoolExecutor | None = None
_LOCK = threading.Lock()


def workers() -> int:
    """Threads of the pool: one per CPU."""
    return max(1, os.cpu_count() or 1)


def _end_pool() -> None:
    """The pool's threads end once their work is done; the next use makes a new pool."""
    global _POOL
    with _LOCK:
        pool, _POOL = _POOL, None
    if pool is not None:
        pool.shutdown(wait=False)


caches.register("worker pool", _end_pool, lambda: int(_POOL is not None))


def thread_pool() -> ThreadPoolExecutor:
    """The shared worker pool (created on first use)."""
    global _POOL
    if _POOL is None:
        with _LOCK:
            if _POOL is None:
                _POOL = ThreadPoolExecutor(max_workers=workers(), thread_name_prefix="dcdi")
    return _POOL


@contextmanager
def one_blas_thread():
    """BLAS (numpy's matmul) on one thread inside the block: the pool's
    threads are the parallelism there, and BLAS's own threads, started by a
    matmul between two pool phases, keep spinning while the pool works
    (measured: the 1280 x 1920 bokeh 6.2 s with them, 5.6 s without). Uses
    threadpoolctl where it is installed (not in Blender's Python: there the
    block runs as it is)."""
    controller = _blas_controller()
    if controller is None:
        yield
        return
    with controller.limit(limits=1, user_api="blas"):
        yield


_CONTROLLER: list = []


def _blas_controller():
    """threadpoolctl's view of the loaded BLAS, found once (finding it scans
    every loaded library: 5 ms a call inside Blender); None without
    threadpoolctl."""
    if not _CONTROLLER:
        try:
            import numpy  # noqa: F401  (BLAS is loaded with numpy: it must be there to be found)
            from threadpoolctl import ThreadpoolController
            _CONTROLLER.append(ThreadpoolController())
        except ImportError:
            _CONTROLLER.append(None)
    return _CONTROLLER[0]
