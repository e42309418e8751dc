"""The engine's process-wide caches, in one object.

Files read once and kept (ray maps, PSF bases, the Omni-Lens-Field, the
error tables, depth refinements), derived tables (a ray map's monomials,
the deposit's phase taps), user photographs made into textures, the
shipped spectral response and the worker pool: each registers here where
it is made, with how to clear it and how many entries it holds. A host
that outlives its jobs (the Blender add-on's session) clears them all with
one call, :func:`clear`; :func:`sizes` says what each holds.

Standard library only: every module may register without importing more.
"""
from __future__ import annotations

import threading
from typing import Callable


class EngineCaches:
    """The registry: name -> (clear(), size() -> int)."""

    def __init__(self):
        self._kept: dict[str, tuple[Callable[[], None], Callable[[], int]]] = {}
        self._lock = threading.Lock()

    def register(self, name: str, clear: Callable[[], None], size: Callable[[], int]) -> None:
        """Add the cache ``name`` (a second registration of a name replaces the first: a reloaded module)."""
        with self._lock:
            self._kept[name] = (clear, size)

    def clear(self) -> None:
        """Empty every cache (each is filled again on its next use)."""
        with self._lock:
            kept = list(self._kept.values())
        for clear, _ in kept:
            clear()

    def sizes(self) -> dict[str, int]:
        """{name: entries held now}."""
        with self._lock:
            kept = dict(self._kept)
        return {name: int(size()) for name, (_, size) in sorted(kept.items())}


ENGINE = EngineCaches()
register, clear, sizes = ENGINE.register, ENGINE.clear, ENGINE.sizes


def lru(name: str, maxsize: int):
    """``functools.lru_cache(maxsize)``, registered as ``name``."""
    import functools

    def wrap(fn):
        cached = functools.lru_cache(maxsize=maxsize)(fn)
        register(name, cached.cache_clear, lambda: cached.cache_info().currsize)
        return cached
    return wrap
