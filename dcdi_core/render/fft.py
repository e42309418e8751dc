"""Batched real 2-D FFTs for the patch-wise convolution, in float32 where possible.

numpy's FFT (numpy < 2) computes in float64 only; scipy.fft computes float32
natively and is 3-4x faster on the small (48-80 px) transforms the
convolution makes (``dcdi bench render`` prints which backend ran). scipy is
optional: Blender's own Python has numpy but not scipy, so without it the
numpy backend runs, with results equal to float32 rounding (tested).
The backend is a parameter of each call (``backend='numpy'`` forces numpy's;
``patch_convolve``, ``simulate``, ``bokeh`` and ``LensSimulator`` pass their
``fft_backend`` down): no process-wide switch.
"""
from __future__ import annotations

import numpy as np

try:                                    # optional accelerator, absent in Blender's Python
    import scipy.fft as _sfft
except ImportError:                     # pragma: no cover - depends on the environment
    _sfft = None

BACKENDS = ("scipy", "numpy")


def available() -> list[str]:
    """The backends this Python has: 'scipy' (if installed) and 'numpy'."""
    return (["scipy"] if _sfft is not None else []) + ["numpy"]


def backend(name: str | None = None) -> str:
    """The backend a call with ``backend=name`` uses: ``name`` itself ('scipy'
    needs scipy), or by default 'scipy' (float32) when installed, else
    'numpy' (float64)."""
    if name is None:
        return "scipy" if _sfft is not None else "numpy"
    if name not in BACKENDS:
        raise ValueError(f"FFT backend {name!r}: allowed {', '.join(BACKENDS)} (or None: the fastest installed)")
    if name == "scipy" and _sfft is None:
        raise ValueError("FFT backend 'scipy' asked for, but scipy is not installed here")
    return name


def rfft2(x: np.ndarray, s: tuple[int, int], backend_name: str | None = None) -> np.ndarray:
    """Real FFT over the last two axes, zero-padded to ``s``; complex64 with
    scipy, complex128 with numpy. One thread: callers run chunks on the pool."""
    s = None if tuple(np.shape(x)[-2:]) == tuple(s) else s           # no padding copy when it fits
    if backend(backend_name) == "scipy":
        return _sfft.rfft2(np.asarray(x, np.float32), s=s, workers=1)
    return np.fft.rfft2(x, s=s)


def irfft2(spec: np.ndarray, s: tuple[int, int], backend_name: str | None = None) -> np.ndarray:
    """Inverse of ``rfft2`` to a real (..., s[0], s[1]) array."""
    if backend(backend_name) == "scipy":
        return _sfft.irfft2(spec, s=s, workers=1)
    return np.fft.irfft2(spec, s=s)


def rfft2_small(x: np.ndarray, s: tuple[int, int], backend_name: str | None = None) -> np.ndarray:
    """``rfft2(x, s)`` for an x (..., a, b) smaller than ``s``: the transform
    along the rows runs on the a rows that hold data, not on the zero rows
    padding would add (a kernel crop of 25 rows in a 56-px transform)."""
    if backend(backend_name) == "scipy":
        return _sfft.fft(_sfft.rfft(np.asarray(x, np.float32), n=s[1], axis=-1, workers=1), n=s[0], axis=-2,
                         workers=1)
    return np.fft.fft(np.fft.rfft(x, n=s[1], axis=-1), n=s[0], axis=-2)


def irfft2_rows(spec: np.ndarray, s: tuple[int, int], row0: int, n_rows: int,
                backend_name: str | None = None) -> np.ndarray:
    """Rows [row0, row0 + n_rows) of ``irfft2(spec, s)``: the last (real)
    stage runs only on the rows that are kept."""
    if backend(backend_name) == "scipy":
        cols = _sfft.ifft(spec, n=None if spec.shape[-2] == s[0] else s[0], axis=-2,
                          workers=1)[..., row0:row0 + n_rows, :]
        return _sfft.irfft(cols, n=s[1], axis=-1, workers=1)
    cols = np.fft.ifft(spec, n=s[0], axis=-2)[..., row0:row0 + n_rows, :]
    return np.fft.irfft(cols, n=s[1], axis=-1)


def fast_size(n: int) -> int:
    """Smallest 2^a 3^b 5^c 7^d >= n: sizes pocketfft (numpy's and scipy's)
    transforms fastest (measured: 58, 62 or 74 cost twice 56, 60 or 72)."""
    best = 1 << (n - 1).bit_length()
    for b in range(6):
        for c in range(4):
            for d in range(3):
                v = 3 ** b * 5 ** c * 7 ** d
                while v < n:
                    v *= 2
                best = min(best, v)
    return best
