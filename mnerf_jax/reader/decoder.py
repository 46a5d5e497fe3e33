"""The HiDDeN watermark decoder (as stable-signature and WateRF use it) and PCA whitening.

The decoder reads the level-2 LL2 sub-band of an image (``dwt.ll2``, un-normalised, roughly [0, 4]):

    LL2 [B, h, w, 3] ─► 9 × (Conv3×3 pad 1 → BatchNorm(eps 1e-3) → GELU exact), channels 3→64, 7×64→64, 64→L
                    ─► global average pool [B, L] ─► Linear(L, L) ─► whitening Linear(L, L) ─► logits [B, L]

The pool can skip a margin of positions at each side (``with_pool_margin``; the receptive-field radius, 9,
makes the read exactly shift-invariant): with zero padding, a decoder pooled over every position learns to
read patterns tied to the image frame (docs/decoders.md measures this), which a 3D watermark cannot carry
into every view. The margin travels with the variables as ``{"pooling": {"margin": int32}}`` and in the
file's metadata; decoders without it (converted stable-signature / WateRF ones included) pool everywhere.

A bit is 1 where its logit is > 0. The whitening layer is the identity until :func:`fit_whitening` sets it to
``W = diag(e^-1/2)·Vᵀ``, ``b = −W·mean`` from the covariance of the raw outputs over a set of images, which
makes the output covariance the identity over those images.

Variables are a plain pytree ``{"params": ..., "batch_stats": ...}`` (plus ``"pooling"`` when set); the
architecture (bits, channels, depth) is read back from the array shapes, so no module object needs to travel
with them. Weights files, the shipped decoders and fresh decoders are :mod:`mnerf_jax.reader.decoder_io`.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from mnerf_jax.core import xla_cpu
from mnerf_jax.core.errors import MnerfError
from mnerf_jax.reader import dwt

SUPPORTED_BITS = (8, 16, 32, 48)

Variables = dict[str, Any]


BN_MOMENTUM = 0.9  # flax convention (= torch momentum 0.1)


class ConvBNGELU(nn.Module):
    """Conv3×3 (pad 1) → BatchNorm (eps 1e-3, torch momentum 0.1) → exact GELU: ``[B,h,w,C] → [B,h,w,F]``."""

    features: int

    @nn.compact
    def __call__(self, x: jax.Array, train: bool = False) -> jax.Array:
        x = nn.Conv(self.features, (3, 3), padding=1, name="conv")(x)
        # Flax's momentum is the weight of the old running value: torch's 0.1 is flax's 0.9.
        x = nn.BatchNorm(use_running_average=not train, momentum=BN_MOMENTUM, epsilon=1e-3, name="bn")(x)
        return nn.gelu(x, approximate=False)


def _identity_init(key: jax.Array, shape: tuple[int, ...], dtype: Any = jnp.float32) -> jax.Array:
    del key
    return jnp.eye(shape[0], shape[1], dtype=dtype)


class HiddenDecoder(nn.Module):
    """HiDDeN decoder over an LL2 sub-band: ``[B, h, w, 3] → logits [B, bits]``.

    ``depth`` counts the blocks of ``channels`` outputs (8: the first 3→64 plus seven 64→64); one more block
    maps to ``bits`` channels before the pool. ``whiten=False`` returns the output before the whitening layer
    (what :func:`fit_whitening` needs).
    """

    bits: int
    channels: int = 64
    depth: int = 8

    @nn.compact
    def __call__(self, ll2: jax.Array, train: bool = False, whiten: bool = True) -> jax.Array:
        x = ll2
        for i in range(self.depth):
            x = ConvBNGELU(self.channels, name=f"block_{i}")(x, train)
        x = ConvBNGELU(self.bits, name=f"block_{self.depth}")(x, train)
        if self.has_variable("pooling", "margin"):
            x = interior_mean(x, self.get_variable("pooling", "margin"))
        else:
            x = jnp.mean(x, axis=(-3, -2))
        x = nn.Dense(self.bits, name="linear")(x)
        # The whitening layer is created (as the identity) even when skipped so that the variables always
        # have the same structure.
        whitening = nn.Dense(self.bits, kernel_init=_identity_init, name="whiten")
        y = whitening(x)
        return y if whiten else x


def interior_mean(features: jax.Array, margin: jax.Array | int) -> jax.Array:
    """Mean of ``features [..., h, w, C]`` over positions at least ``margin`` from every side → ``[..., C]``.

    ``margin`` may be traced (it travels with the variables). Where ``h`` or ``w`` is not larger than
    ``2·margin`` there is no interior and the mean is over every position.
    """
    h, w = features.shape[-3], features.shape[-2]
    margin = jnp.asarray(margin, jnp.int32)
    rows, cols = jnp.arange(h), jnp.arange(w)
    inside_rows = (rows >= margin) & (rows < h - margin)
    inside = inside_rows[:, None] & ((cols >= margin) & (cols < w - margin))[None]
    weights = jnp.where(jnp.any(inside), inside, True).astype(features.dtype)[:, :, None]
    return jnp.sum(features * weights, axis=(-3, -2)) / jnp.sum(weights)


def receptive_radius(variables: Mapping[str, Any]) -> int:
    """Positions of the last feature map that see zero padding: one per 3×3 convolution (9 for HiDDeN's)."""
    return architecture(variables)[2] + 1


def pool_margin(variables: Mapping[str, Any]) -> int:
    """The pooling margin of ``variables`` (0: the pool covers every position)."""
    pooling = variables.get("pooling")
    return int(np.asarray(pooling["margin"])) if pooling else 0


def with_pool_margin(variables: Mapping[str, Any], margin: int) -> Variables:
    """``variables`` whose pool skips ``margin`` positions at each side (0 removes the setting)."""
    if margin < 0:
        raise MnerfError(f"the pooling margin must be >= 0, got {margin}")
    out = {k: v for k, v in variables.items() if k != "pooling"}
    if margin:
        out["pooling"] = {"margin": jnp.asarray(margin, jnp.int32)}
    return out


def _module_variables(variables: Mapping[str, Any]) -> Variables:
    """The collections the module reads: params, batch_stats and pooling when set (nothing else)."""
    return {k: variables[k] for k in ("params", "batch_stats", "pooling") if k in variables}


def _with_weights(variables: Mapping[str, Any], params: Any, batch_stats: Any) -> Variables:
    """``variables`` with new weights, keeping the pooling setting."""
    return _module_variables({**variables, "params": params, "batch_stats": batch_stats})


def architecture(variables: Mapping[str, Any]) -> tuple[int, int, int]:
    """``(bits, channels, depth)`` read from the variables' shapes."""
    params = variables["params"]
    bits = int(params["linear"]["kernel"].shape[-1])
    channels = int(params["block_0"]["conv"]["kernel"].shape[-1])
    depth = sum(1 for name in params if name.startswith("block_")) - 1
    return bits, channels, depth


def module_for(variables: Mapping[str, Any]) -> HiddenDecoder:
    bits, channels, depth = architecture(variables)
    return HiddenDecoder(bits=bits, channels=channels, depth=depth)


def init_decoder(key: jax.Array, bits: int, channels: int = 64, depth: int = 8) -> Variables:
    """Fresh decoder variables ``{"params", "batch_stats"}`` (whitening = identity)."""
    if bits not in SUPPORTED_BITS:
        raise MnerfError(
            f"unsupported message length {bits} bits (supported: {', '.join(map(str, SUPPORTED_BITS))})"
        )
    return dict(_compiled_init(bits, channels, depth)(key, jnp.zeros((1, 8, 8, 3), jnp.float32)))


DECODER_INITS = ("random", "filterbank")


def filterbank_init(variables: Mapping[str, Any]) -> Variables:
    """``variables`` with the first block set to a fixed local filter bank, the middle ones near identity.

    Block 0 (Conv 3×3, 3 → C): every 3×3 DCT-II basis pattern (the 8 oscillating ones first, then the
    constant one) on each opponent colour channel (luminance R+G+B, red−green, yellow−blue), each with both
    signs (so the GELU after it passes both half-waves), 54 channels; the remaining channels keep their random
    init. Blocks 1 … depth−1 (C → C): the identity plus 0.1 × their random init, so the rectified band
    responses reach the pool from the first step. The last block, the linear layers and BatchNorm are left
    as initialised. A decoder learns against its own gradient watermark markedly faster from this start
    (docs/decoders.md has the A/B); the architecture and the file format do not change.
    """
    params = jax.tree.map(lambda a: np.array(a, np.float32), dict(variables["params"]))
    _, channels, depth = architecture(variables)
    colour = np.array([[1, 1, 1], [1, -1, 0], [1, 1, -2]], np.float64)
    colour /= np.linalg.norm(colour, axis=1, keepdims=True)
    n = np.arange(3)
    dct = np.stack([np.cos(np.pi * (2 * n + 1) * k / 6) for k in range(3)])
    patterns = [np.outer(dct[u], dct[v]) for u in range(3) for v in range(3) if (u, v) != (0, 0)]
    patterns.append(np.outer(dct[0], dct[0]))  # the constant pattern last
    kernel = params["block_0"]["conv"]["kernel"]  # [3, 3, 3, C] (HWIO)
    filled = 0
    for c in range(3):
        for pattern in patterns:
            unit = pattern / np.linalg.norm(pattern)
            for sign in (1.0, -1.0):
                if filled < channels:
                    kernel[:, :, :, filled] = sign * unit[:, :, None] * colour[c][None, None, :]
                    filled += 1
    params["block_0"]["conv"]["bias"][:filled] = 0.0
    for i in range(1, depth):
        k = params[f"block_{i}"]["conv"]["kernel"]
        k *= 0.1
        k[1, 1] += np.eye(k.shape[2], k.shape[3], dtype=np.float32)
    return _with_weights(variables, jax.tree.map(jnp.asarray, params), variables["batch_stats"])


@functools.cache
def _compiled_init(bits: int, channels: int, depth: int) -> Any:
    """One compiled init per architecture (instead of dispatching each initialiser separately), kept: the
    compilation takes seconds and a run's setup or a checkpoint check may init several times."""
    return jax.jit(HiddenDecoder(bits=bits, channels=channels, depth=depth).init)


# Jitted (a whole-network compile instead of op-by-op dispatch), with the XLA:CPU options that keep its
# convolutions out of YNNPACK fusions (xla_cpu); inside other jitted code they simply inline.
@xla_cpu.jit_cpu_tuned(static_argnames=("whiten",))
def apply_ll2(variables: Mapping[str, Any], ll2: jax.Array, whiten: bool = True) -> jax.Array:
    """Eval-mode logits (BatchNorm running statistics) of LL2 sub-bands ``[B, h, w, 3]`` → ``[B, bits]``."""
    variables = _module_variables(variables)
    return module_for(variables).apply(variables, ll2, train=False, whiten=whiten)


@xla_cpu.jit_cpu_tuned
def apply_ll2_train(variables: Mapping[str, Any], ll2: jax.Array) -> tuple[jax.Array, Any]:
    """Train-mode logits ``[B, bits]`` (batch statistics) and the updated ``batch_stats``."""
    variables = _module_variables(variables)
    logits, updates = module_for(variables).apply(variables, ll2, train=True, mutable=["batch_stats"])
    return logits, updates["batch_stats"]


@xla_cpu.jit_cpu_tuned(static_argnames=("wavelet",))
def decode_logits(variables: Mapping[str, Any], images: jax.Array, wavelet: str = "bior4.4") -> jax.Array:
    """Eval-mode logits of rendered images ``[B, H, W, 3]`` in [0, 1] → ``[B, bits]`` (LL2 taken here)."""
    return apply_ll2(variables, dwt.ll2(images, wavelet))


# ------------------------------------------------------------------------------------------------------------
# Whitening


def whitening_from_outputs(raw: np.ndarray, eps: float = 1e-9) -> tuple[np.ndarray, np.ndarray]:
    """PCA whitening of raw decoder outputs ``[N, L]``: ``(W [L, L], b [L])`` with ``W·x + b`` white.

    ``W = diag(e^-1/2)·Vᵀ`` and ``b = −W·mean`` where ``(e, V)`` eigendecompose the output covariance
    (in float64).
    ``eps`` (relative to the largest eigenvalue) keeps a degenerate direction from blowing up.
    """
    raw = np.asarray(raw, np.float64)
    if raw.ndim != 2 or raw.shape[0] <= raw.shape[1]:
        raise MnerfError(f"whitening needs more images than bits, got outputs of shape {raw.shape}")
    mean = raw.mean(axis=0)
    centred = raw - mean
    cov = centred.T @ centred / raw.shape[0]
    e, v = np.linalg.eigh(cov)
    e = np.maximum(e, eps * max(float(e.max()), 1e-30))
    w = np.diag(e**-0.5) @ v.T
    b = -w @ mean
    return w, b


def set_whitening(variables: Mapping[str, Any], w: np.ndarray, b: np.ndarray) -> Variables:
    """Variables with the whitening layer set to ``y = W·x + b`` (Flax's Dense computes ``x @ kernel``)."""
    params = dict(variables["params"])
    dtype = params["whiten"]["kernel"].dtype
    params["whiten"] = {"kernel": jnp.asarray(np.asarray(w).T, dtype), "bias": jnp.asarray(b, dtype)}
    return _with_weights(variables, params, variables["batch_stats"])


def calibrate_batch_norm(variables: Mapping[str, Any], ll2: jax.Array) -> Variables:
    """Set every BatchNorm's running mean and variance to the batch statistics of ``ll2 [B, h, w, 3]``.

    A random-init decoder keeps BatchNorm's initial statistics (mean 0, variance 1), so in eval mode its
    activations are not normalised and its outputs barely vary between images: whitening then scales them
    up by orders of magnitude, and every optimizer step on the decoder moves the logits by ~1. Calibrated
    statistics make eval mode behave like the network as initialised.
    """
    old = variables["batch_stats"]
    _, new = apply_ll2_train(variables, ll2)
    # flax: running = momentum · running + (1 − momentum) · batch; solved for batch.
    batch = jax.tree.map(lambda n, o: (n - BN_MOMENTUM * o) / (1.0 - BN_MOMENTUM), new, old)
    return {**variables, "batch_stats": jax.tree.map(lambda x: np.asarray(x, np.float32), batch)}


def fit_whitening(variables: Mapping[str, Any], ll2_batches: list[jax.Array]) -> Variables:
    """Fit the whitening layer to the raw outputs over the given LL2 batches (each ``[b, h, w, 3]``)."""
    apply = jax.jit(lambda v, x: apply_ll2(v, x, whiten=False))
    raw = np.concatenate([np.asarray(apply(variables, x)) for x in ll2_batches])
    w, b = whitening_from_outputs(raw)
    return set_whitening(variables, w, b)


def recentre_whitening(
    variables: Mapping[str, Any], ll2_batches: list[jax.Array]
) -> tuple[Variables, dict[str, float]]:
    """Re-centre and re-scale the whitening so the logits over the given LL2 batches have zero mean and unit
    variance; the rotation is kept (each logit is only shifted and scaled by a positive factor).

    For a decoder trained further after its whitening was fitted: an encoder learned against that rotation,
    so refitting it would scramble the encoder's bits, while a per-logit offset (the drift on clean images)
    and positive scale leave them readable. Returns the variables and the drift found: ``max_abs_mean``
    (the largest logit mean removed), ``max_std_ratio`` (the largest logit standard deviation divided out)
    and ``max_abs_corr`` (the largest correlation between two logits, which neither step can change).
    """
    logits = np.concatenate([np.asarray(apply_ll2(variables, x)) for x in ll2_batches]).astype(np.float64)
    mean, std = logits.mean(axis=0), np.maximum(logits.std(axis=0), 1e-12)
    corr = np.corrcoef(logits, rowvar=False)
    params = dict(variables["params"])
    whiten = params["whiten"]
    kernel = np.asarray(whiten["kernel"], np.float64) / std  # Dense: y = x @ kernel + bias, output on axis 1
    bias = (np.asarray(whiten["bias"], np.float64) - mean) / std
    dtype = whiten["bias"].dtype
    params["whiten"] = {"kernel": jnp.asarray(kernel, dtype), "bias": jnp.asarray(bias, dtype)}
    report = {
        "max_abs_mean": float(np.abs(mean).max()),
        "max_std_ratio": float(std.max()),
        "max_abs_corr": float(np.abs(corr - np.eye(corr.shape[0])).max()),
    }
    return _with_weights(variables, params, variables["batch_stats"]), report
