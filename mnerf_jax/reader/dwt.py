"""Level-2 discrete wavelet transform: the LL2 (approximation) sub-band that the watermark decoder reads.

Two wavelet/extension pairs are supported, each matching PyWavelets'
``wavedec2(x, wavelet, mode, level=2)[0]``:

- ``"bior4.4"`` with ``periodization`` (the default; WateRF's and MultiNeRF's choice). An odd-length axis is
  first extended by repeating its last sample, then ``y[k] = Σ_j h[j]·x[(2k + L/2 − j) mod N]`` with ``h`` the
  decomposition low-pass filter (``L = 10`` taps) and ``N`` the (even) extended length; the output has
  ``ceil(N/2)`` samples. LL2 of an image in [0, 1] lies roughly in [0, 4] (≈ 4× the local mean: each level
  multiplies a constant signal by ``Σh = √2`` per axis).
- ``"haar"`` with ``symmetric`` extension (PyWavelets' default mode): half-sample symmetric extension
  (``x[-1] = x[0]``, ``x[N] = x[N-1]``), ``y[k] = Σ_j h[j]·x_ext[2k + 1 − j]``, giving
  ``floor((N + L − 1)/2)`` samples.

Either mode can be combined with either wavelet through the ``mode`` argument.

The transform is linear and separable, so each axis is one matrix: the level-1 analysis matrix ``A1 [n1, N]``
followed by the level-2 one ``A2 [n2, n1]`` composes into a single ``A2·A1 [n2, N]``, built once per static
shape in NumPy (float64, then cast). LL2 is then ``A_h · X · A_wᵀ`` per channel: two dense matrix products.
XLA:CPU handles these dense products far better than the same transform written as strided slices per level
of an extended signal (and their transposes).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

# Decomposition low-pass filters (PyWavelets ``Wavelet(name).dec_lo``), hard-coded so that PyWavelets is only
# a test oracle. ``bior4.4`` is the CDF 9/7 analysis filter zero-padded to 10 taps, as PyWavelets stores it.
DEC_LO: dict[str, tuple[float, ...]] = {
    "haar": (0.7071067811865476, 0.7071067811865476),
    "bior4.4": (
        0.0,
        0.03782845550726404,
        -0.023849465019556843,
        -0.11062440441843718,
        0.37740285561283066,
        0.8526986790088938,
        0.37740285561283066,
        -0.11062440441843718,
        -0.023849465019556843,
        0.03782845550726404,
    ),
}

# The extension mode each wavelet uses unless told otherwise.
DEFAULT_MODE: dict[str, str] = {"haar": "symmetric", "bior4.4": "periodization"}
MODES = ("symmetric", "periodization")


def _check(wavelet: str, mode: str | None) -> str:
    if wavelet not in DEC_LO:
        raise ValueError(f"unknown wavelet {wavelet!r} (known: {', '.join(DEC_LO)})")
    mode = DEFAULT_MODE[wavelet] if mode is None else mode
    if mode not in MODES:
        raise ValueError(f"unknown DWT mode {mode!r} (known: {', '.join(MODES)})")
    return mode


def _dwt_len(n: int, taps: int, mode: str) -> int:
    """Number of approximation coefficients of one DWT level on ``n`` samples (PyWavelets' rule)."""
    if mode == "periodization":
        return -(-n // 2)
    return (n + taps - 1) // 2


def ll2_shape(h: int, w: int, wavelet: str = "bior4.4", mode: str | None = None) -> tuple[int, int]:
    """Spatial size ``(h2, w2)`` of the LL2 sub-band of an ``h × w`` image."""
    mode = _check(wavelet, mode)
    taps = len(DEC_LO[wavelet])
    return tuple(_dwt_len(_dwt_len(n, taps, mode), taps, mode) for n in (h, w))  # type: ignore[return-value]


def _symmetric_index(i: np.ndarray, n: int) -> np.ndarray:
    """Half-sample symmetric extension: index into ``[0, n)`` for any integer position (period ``2n``)."""
    i = np.mod(i, 2 * n)
    return np.where(i < n, i, 2 * n - 1 - i)


def _taps_and_indices(n: int, wavelet: str, mode: str) -> tuple[np.ndarray, np.ndarray]:
    """Filter ``h [L]`` and source indices ``idx [n_out, L]`` into the length-``n`` signal for one level.

    ``y[k] = Σ_j h[j]·x[idx[k, j]]``; extension and odd-length padding are folded into ``idx``.
    """
    h = np.asarray(DEC_LO[wavelet], np.float64)
    taps = h.size
    n_out = _dwt_len(n, taps, mode)
    k = np.arange(n_out)[:, None]
    j = np.arange(taps)[None, :]
    if mode == "periodization":
        n_even = n + (n % 2)
        idx = np.mod(2 * k + taps // 2 - j, n_even)
        idx = np.minimum(idx, n - 1)  # the padded sample repeats the last one
    else:
        idx = _symmetric_index(2 * k + 1 - j, n)
    return h, idx


def _analysis_matrix(n: int, wavelet: str, mode: str) -> np.ndarray:
    """One DWT level as a dense matrix ``[n_out, n]`` (float64)."""
    h, idx = _taps_and_indices(n, wavelet, mode)
    mat = np.zeros((idx.shape[0], n), np.float64)
    rows = np.broadcast_to(np.arange(idx.shape[0])[:, None], idx.shape)
    np.add.at(mat, (rows, idx), np.broadcast_to(h, idx.shape))
    return mat


@functools.lru_cache(maxsize=64)
def ll2_matrix(n: int, wavelet: str = "bior4.4", mode: str | None = None) -> np.ndarray:
    """Two DWT levels along one axis as one matrix ``[n2, n]`` (float32): ``A2 · A1``."""
    mode = _check(wavelet, mode)
    a1 = _analysis_matrix(n, wavelet, mode)
    a2 = _analysis_matrix(a1.shape[0], wavelet, mode)
    out = (a2 @ a1).astype(np.float32)
    out.setflags(write=False)
    return out


def _ll2_matrix(images: jax.Array, wavelet: str, mode: str) -> jax.Array:
    h, w = images.shape[-3], images.shape[-2]
    a_h = jnp.asarray(ll2_matrix(h, wavelet, mode), images.dtype)
    a_w = jnp.asarray(ll2_matrix(w, wavelet, mode), images.dtype)
    # Highest precision: on accelerators the default may round the operands to bfloat16.
    out = jnp.einsum("ph,...hwc->...pwc", a_h, images, precision=jax.lax.Precision.HIGHEST)
    return jnp.einsum("qw,...pwc->...pqc", a_w, out, precision=jax.lax.Precision.HIGHEST)


def ll2(images: jax.Array, wavelet: str = "bior4.4", mode: str | None = None) -> jax.Array:
    """Level-2 LL2 sub-band of ``images [..., H, W, C]`` → ``[..., H2, W2, C]`` (see :func:`ll2_shape`).

    ``mode=None`` picks the wavelet's default extension (bior4.4: periodization; haar: symmetric). Linear in
    the images, so it jits, vmaps and differentiates like any matrix product. Values are not normalised: each
    level multiplies a constant by ``Σh = √2`` per axis, so LL2 is about 4× the local mean.
    """
    mode = _check(wavelet, mode)
    images = jnp.asarray(images)
    if images.ndim < 3:
        raise ValueError(f"ll2 expects images [..., H, W, C], got shape {images.shape}")
    if not jnp.issubdtype(images.dtype, jnp.floating):
        images = images.astype(jnp.float32)
    return _ll2_matrix(images, wavelet, mode)
