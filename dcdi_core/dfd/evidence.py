"""The evidence a capture's blur gives for each depth: per window, the
negative log-likelihood of its spectrum under each depth hypothesis.

Model (a Gaussian marginal likelihood, as in depth from coded apertures and
chromatic aberration: Levin et al. 2007, Trouvé et al. 2013): a window's
sharp content is ``x_c = a_c u + r_c`` for the three colour channels c,
``u`` a shared texture of power spectrum ``A / (|f|^2 + f0^2)`` (natural
images' 1/f^2), ``a_c`` the window's mean colour (blur keeps each
channel's mean: every PSF sums to its channel's transmission) and ``r_c``
a colour residual of ``rho`` times u's power. The capture is
``y_c = k_c * x_c + n_c`` with ``k_c`` the PSF of the hypothesised depth
at the window's field and azimuth and ``n_c`` the sensor noise. Each
frequency's three channels are then Gaussian with covariance
``C = D + P v v^H`` (``v_c = a_c K_c``, ``D`` diagonal), whose inverse and
determinant are closed-form (Sherman-Morrison). The log-determinant is what
a plain deconvolution residual lacks: without it the smallest blur always
explains the data best, and the far depths win.

The window's spectrum is that of its periodic component (Moisan 2011): no
taper, whose leakage makes every window look sharper than it is (measured:
a taper read depths 1.3-1.9 times too far), and no cross of border jumps.

Units: frequencies in cycles per pixel, depths in metres, diopters in 1/m.
"""
from __future__ import annotations

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view


def periodic_spectrum(u: np.ndarray) -> np.ndarray:
    """rfft2 over the last two axes of the periodic component of ``u``
    (Moisan's periodic plus smooth decomposition): ``u``'s spectrum less
    that of the smooth image whose Laplacian is the jumps across its
    borders. One thread (``render.fft``: float32 where scipy is here)."""
    from ..render import fft
    n, m = u.shape[-2:]
    v = np.zeros_like(u)
    v[..., 0, :] += u[..., -1, :] - u[..., 0, :]
    v[..., -1, :] += u[..., 0, :] - u[..., -1, :]
    v[..., :, 0] += u[..., :, -1] - u[..., :, 0]
    v[..., :, -1] += u[..., :, 0] - u[..., :, -1]
    den = (2 * np.cos(2 * np.pi * np.arange(n) / n)[:, None]
           + 2 * np.cos(2 * np.pi * np.arange(m // 2 + 1) / m)[None, :] - 4)
    den[0, 0] = 1.0
    smooth = fft.rfft2(v, (n, m)) / den.astype(np.float32)
    smooth[..., 0, 0] = 0.0
    return fft.rfft2(u, (n, m)) - smooth


def bins(size: int, max_frequency: float):
    """The 2 x 2 blocks of a size x size window's rfft2 bins the likelihood
    sums over (a transfer function of a PSF a third of the window wide
    barely changes across a block): (members (B, 4) flat indices into the
    rfft2 grid, -1 where a block has fewer; count (B,); f2 (B, 4) the
    members' |f|^2, cycles^2/px^2, NaN where none) of the blocks whose first
    frequency lies within ``max_frequency``; the DC bin is in no block.
    Block (i, j) is sampled at frequency (2i, 2j) / size: the transfer
    function of a kernel folded onto size / 2 (:func:`otfs`)."""
    half = size // 2
    cols = size // 2 + 1
    fy, fx = np.fft.fftfreq(size), np.fft.rfftfreq(size)
    members, count, f2 = [], [], []
    for i in range(half):
        for j in range(half // 2 + 1):
            if fy[2 * i] ** 2 + fx[2 * j] ** 2 > max_frequency ** 2:
                continue
            m = [r * cols + c for r in (2 * i, 2 * i + 1) for c in (2 * j, 2 * j + 1)
                 if c < cols and (r, c) != (0, 0)]
            members.append(m + [-1] * (4 - len(m)))
            count.append(len(m))
            f2.append([fy[k // cols] ** 2 + fx[k % cols] ** 2 for k in m] + [np.nan] * (4 - len(m)))
    return np.array(members), np.array(count, np.float32), np.array(f2)


def prior_shape(f2: np.ndarray, size: int, sharpness_px: float, slope: float = 2.0) -> np.ndarray:
    """The sharp texture's power spectrum's shape summed over each block
    (B,): 1 / (|f|^2 + f0^2) ** (slope / 2), f0 = 1 / size, times a
    Gaussian blur of ``sharpness_px`` (the sharp image's own softness: a
    render's pixel filter, a sensor's pixel), averaged over the block's
    members."""
    g = np.exp(-(2 * np.pi * sharpness_px) ** 2 * f2) / (f2 + size ** -2.0) ** (slope / 2.0)
    return np.nanmean(g, axis=1).astype(np.float32)


def block_index(size: int, members: np.ndarray) -> np.ndarray:
    """Flat indices into the folded (size / 2) rfft2 grid of each block."""
    cols, half_cols = size // 2 + 1, size // 4 + 1
    first = members[:, 0]
    first = np.where(first < 0, 0, first)
    # a block's first member is (2i, 2j), or (0, 1) for the DC block (then i = j = 0)
    r, c = first // cols, first % cols
    return (r // 2) * half_cols + c // 2


def otfs(kernels: np.ndarray, size: int, index: np.ndarray) -> np.ndarray:
    """Transfer functions (..., 3, B) complex64 of kernels (..., 3, k, k)
    (centred in their square) at the blocks' frequencies (2i, 2j) / size:
    the rfft2 of each kernel folded onto a (size / 2)^2 grid about its
    centre, which samples its transfer function there exactly (a kernel
    wider than the window is folded, not cropped)."""
    k = kernels.shape[-1]
    half = size // 2
    n = -(-k // half) * half
    buf = np.zeros(kernels.shape[:-2] + (n, n), np.float32)
    buf[..., :k, :k] = kernels
    buf = np.roll(buf, (-(k // 2), -(k // 2)), axis=(-2, -1))
    fold = buf.reshape(kernels.shape[:-2] + (n // half, half, n // half, half)).sum(axis=(-4, -2))
    from ..render import fft
    return fft.rfft2(fold, (half, half)).reshape(kernels.shape[:-2] + (-1,))[..., index].astype(np.complex64)


class WindowSpectra:
    """What the likelihood needs of a capture's windows (n = tiles, row by
    row), computed once: whether each was clipped (``clipped``), per
    frequency block, the channels' summed cross powers ``S`` (the diagonal
    ``power`` (n, 3, B) and ``cross`` (n, 3, B) complex: 01, 02, 12), the
    windows' mean colours ``a`` (n, 3, normalised to mean 1), the noise
    variance of each bin ``noise`` (n, 3), the texture amplitude's starting
    value ``a0`` (n,), the blocks' ``count`` and prior ``shape`` (B,)."""

    def __init__(self, capture: np.ndarray, stride: int, size: int, blocks, noise_model,
                 sharpness_px=(0.0,), colour_floor: float = 0.05, slopes=(2.0,)):
        """Of the windows of ``capture`` (H, W, 3) centred on its stride x
        stride tiles (:func:`windows`), a band of tile rows at a time on the
        pool."""
        from ..parallel import thread_pool
        members, self.count, f2 = blocks
        shapes = [prior_shape(f2, size, sp, a) for a in slopes for sp in sharpness_px]
        low = shapes[0] >= np.sort(shapes[0])[-min(8, len(shapes[0]))]  # the lowest frequencies: K ~ 1
        # every shape scaled to the first's power at the lowest frequencies: one amplitude estimate serves all
        self.shapes = [g * (shapes[0][low].mean() / g[low].mean()) for g in shapes]
        self.shape = self.shapes[0]
        h, w = capture.shape[:2]
        nph = -(-h // stride)
        pad = (size - stride) // 2
        y = np.pad(np.asarray(capture, np.float32), ((pad, nph * stride - h + size - stride - pad),
                                                     (pad, -(-w // stride) * stride - w + size - stride - pad),
                                                     (0, 0)), mode="symmetric")
        view = sliding_window_view(y, (size, size), axis=(0, 1))[::stride, ::stride]
        npw = -(-w // stride)

        def band_of(rows):
            wins = np.ascontiguousarray(view[rows, :npw]).reshape((-1, 3, size, size))
            mean = wins.mean(axis=(-1, -2), dtype=np.float64)
            Y = periodic_spectrum(wins - mean[..., None, None].astype(np.float32)).reshape(len(wins), 3, -1)
            Y = np.concatenate([Y, np.zeros(Y.shape[:2] + (1,), Y.dtype)], -1)[..., members]  # (n, 3, B, 4)
            power = (Y.real ** 2 + Y.imag ** 2).sum(-1).astype(np.float32)
            cross = np.stack([(Y[:, a] * np.conj(Y[:, b])).sum(-1) for a, b in ((0, 1), (0, 2), (1, 2))], 1)
            clipped = (wins >= 0.98).mean(axis=(-3, -2, -1)) > 0.02
            return mean, power, cross.astype(np.complex64), clipped

        step = max(1, nph // 16)
        parts = list(thread_pool().map(band_of, [slice(r, r + step) for r in range(0, nph, step)]))
        mean, self.power, self.cross, self.clipped = (np.concatenate(x) for x in zip(*parts))
        self.tiles = (nph, npw)
        self.noise = np.maximum(noise_model.variance(mean) * size * size, 1e-12).astype(np.float32)
        a = np.maximum(mean, colour_floor * mean.max(-1, keepdims=True))
        self.a = (a / np.maximum(a.mean(-1, keepdims=True), 1e-12)).astype(np.float32)
        excess = (self.power[:, :, low].mean(1) / self.count[low] - self.noise.mean(1)[:, None]) / self.shape[low]
        self.a0 = np.maximum(excess.mean(-1), 1e-12).astype(np.float32)       # (n,)
        self.mean = mean

    def rows(self, sel) -> "WindowSpectra":
        """The same for the windows ``sel`` only."""
        part = object.__new__(WindowSpectra)
        part.count, part.shape, part.shapes = self.count, self.shape, self.shapes
        for name in ("power", "cross", "noise", "a", "a0", "mean", "clipped"):
            setattr(part, name, getattr(self, name)[sel])
        return part

    def terms(self, K: np.ndarray, rho: float, eta: float) -> tuple:
        """What the likelihood needs of transfer functions ``K`` (n, 3, B)
        whatever the texture's amplitude and spectrum, all real: ``v2`` =
        |a_c K_c|^2, ``weight`` = rho v2 + eta a_c^2 (the share of the
        texture's power each channel's variance gains), ``signal`` = v2 x
        the channel's power, and ``pairs`` = Re(conj(v_a) v_b S_ab) for
        the pairs 01, 02, 12 (n, 3, B)."""
        v = self.a[..., None] * K                                            # (n, 3, B)
        v2 = v.real ** 2 + v.imag ** 2
        weight = rho * v2 + eta * (self.a ** 2)[..., None]
        pairs = np.stack([(np.conj(v[:, a]) * v[:, b] * self.cross[:, i]).real
                          for i, (a, b) in enumerate(((0, 1), (0, 2), (1, 2)))], 1)
        return v2, weight, v2 * self.power, pairs

    def nll_of_terms(self, terms: tuple, amplitude: np.ndarray, shape) -> np.ndarray:
        """The NLL (n,) from :meth:`terms` and the texture's amplitudes (n,)
        and prior shape (B,). The covariance C = D + P v v^H, D = noise + P
        weight (diagonal): by Sherman-Morrison, y^H C^-1 y = sum |y_c|^2 / D_c
        - P |sum conj(v_c) y_c / D_c|^2 / (1 + P q), q = sum |v_c|^2 / D_c,
        and log det C = sum log D_c + log(1 + P q)."""
        v2, weight, signal, pairs = terms
        P = amplitude[:, None] * shape                                       # (n, B)
        D = self.noise[..., None] + P[:, None, :] * weight
        inv = 1.0 / D
        q = (v2 * inv).sum(1)
        form = (signal * inv * inv).sum(1) + 2.0 * (pairs[:, 0] * inv[:, 0] * inv[:, 1]
                                                    + pairs[:, 1] * inv[:, 0] * inv[:, 2]
                                                    + pairs[:, 2] * inv[:, 1] * inv[:, 2])
        quad = (self.power * inv).sum(1) - P * form / (1.0 + P * q)
        logdet = np.log(D).sum(1) + np.log1p(P * q)
        return (quad + self.count * logdet).sum(-1, dtype=np.float64)

    def nll(self, K: np.ndarray, amplitude: np.ndarray, rho: float, eta: float, shape=None) -> np.ndarray:
        """Negative log-likelihood (n,) of each window under transfer
        functions ``K`` (n, 3, B) and texture amplitudes ``amplitude`` (n,);
        ``rho``: the colour residual's share, ``eta``: the PSF model's error,
        a share of the sharp texture's power that no hypothesis explains
        (without it a hypothesis whose transfer function has a zero where the
        true one has not is refused outright, and the evidence jumps from one
        depth bin to the next). ``shape``: the prior's (B,), default the
        first of ``shapes``."""
        return self.nll_of_terms(self.terms(K, rho, eta), amplitude, self.shape if shape is None else shape)

    def profile_nll(self, K: np.ndarray, rho: float, eta: float, steps: np.ndarray) -> np.ndarray:
        """The NLL (n,) minimised over the texture amplitude ``a0 * steps``
        and the prior's shapes (the sharp image's softness); the terms that
        depend on neither are made once."""
        terms = self.terms(K, rho, eta)
        return np.min([self.nll_of_terms(terms, self.a0 * s, shape) for s in steps for shape in self.shapes], axis=0)
