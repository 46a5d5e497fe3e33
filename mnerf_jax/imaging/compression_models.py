"""CompressAI's learned image codecs as regeneration attacks, in JAX, from the weights the user supplies.

The peers (WAVES, MultiNeRF's supplement) regenerate images with CompressAI's pretrained
``bmshj2018_factorized`` and ``cheng2020_anchor`` in eval mode: ``x_hat = model.forward(x)["x_hat"]``.
Hand-written here because no JAX port of CompressAI exists among the project's libraries; the layers follow
CompressAI's definitions (``compressai/layers``, ``compressai/models/google.py`` and ``waseda.py``):

- ``bmshj2018-factorized`` (FactorizedPrior): ``g_a`` = 4 × conv 5×5 stride 2 with GDN between them (3 → N →
  N → N → M), ``g_s`` = 4 × transposed conv 5×5 stride 2 (padding 2, output padding 1) with inverse GDN; the
  entropy bottleneck's eval forward quantises ``y_hat = round(y − median) + median``, the medians being
  ``entropy_bottleneck.quantiles[:, 0, 1]``.
- ``cheng2020-anchor`` / ``cheng2020-attn``: residual blocks (LeakyReLU, slope 0.01), strided residual
  blocks with GDN, sub-pixel upsampling blocks with inverse GDN, 3×3 convs, and (attn) attention blocks. The
  Gaussian conditional's eval forward quantises ``y_hat = round(y)`` (no means), so
  ``x_hat = g_s(round(y))``: the hyperprior and the context model do not change ``x_hat`` and are neither
  needed nor run (their weights in the file are ignored).

GDN (CompressAI's ``GDN``): ``beta`` and ``gamma`` are stored reparametrised (``NonNegativeParametrizer``):
value ``v`` → ``max(v, bound)² − pedestal`` with ``pedestal = (2⁻¹⁸)²`` and ``bound = (minimum +
pedestal)^½`` (minimum 1e-6 for beta, 0 for gamma); ``norm[i] = beta[i] + Σ_j gamma[i, j]·x[j]²``;
GDN ``x / √norm``, inverse GDN ``x · √norm``.

Weights are a flat ``{state-dict name: array}`` in PyTorch layouts (Conv2d ``[out, in, kH, kW]``,
ConvTranspose2d ``[in, out, kH, kW]``), read by :func:`mnerf_jax.core.torch_state.read_state_dict` without
running the file's pickle; N and M follow from the shapes, so any quality level loads. Tensors run NCHW as
in PyTorch. Images: uint8 ``[B, H, W, 3]`` → [0, 1], zero-padded (centred) to a multiple of 64 as
CompressAI's evaluation pads, coded, cropped back, clipped to [0, 1] and rounded to uint8.
"""

from __future__ import annotations

import dataclasses
import functools
import re
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from mnerf_jax.core.errors import MnerfError
from mnerf_jax.core.torch_state import read_state_dict
from mnerf_jax.imaging.attacks import AttackError

Params = Mapping[str, jax.Array]

PAD_MULTIPLE = 64  # 2⁶: the deepest models' total stride (CompressAI's evaluation pads to it)
REPARAM_OFFSET = 2.0**-18
PEDESTAL = REPARAM_OFFSET**2
BETA_MIN = 1e-6
LEAKY_SLOPE = 0.01  # torch.nn.LeakyReLU's default


class CompressionModelError(AttackError):
    """A weights file that does not hold the named compression model, or an unknown architecture."""


class _Weights:
    """The state dict as the forward reads it; a missing name raises one line naming it and the model."""

    def __init__(self, arrays: Mapping[str, Any], architecture: str):
        self.arrays = arrays
        self.architecture = architecture

    def __getitem__(self, name: str) -> Any:
        if name not in self.arrays:
            raise CompressionModelError(
                f"the weights lack {name}, which {self.architecture} needs (wrong architecture or file?)"
            )
        return self.arrays[name]


# ------------------------------------------------------------------------------------------------ layers


def conv2d(x: jax.Array, weight: jax.Array, bias: jax.Array | None, stride: int = 1) -> jax.Array:
    """PyTorch's ``Conv2d`` with padding ``k // 2``: ``x [B, Cin, H, W]``, ``weight [Cout, Cin, k, k]`` →
    ``[B, Cout, ⌈H/stride⌉, ⌈W/stride⌉]`` (odd ``k``)."""
    pad = weight.shape[-1] // 2
    out = jax.lax.conv_general_dilated(
        x, weight, (stride, stride), ((pad, pad), (pad, pad)), dimension_numbers=("NCHW", "OIHW", "NCHW")
    )
    return out if bias is None else out + bias[None, :, None, None]


def conv_transpose2d(
    x: jax.Array, weight: jax.Array, bias: jax.Array | None, stride: int = 2, output_padding: int = 1
) -> jax.Array:
    """PyTorch's ``ConvTranspose2d`` with padding ``k // 2``: ``x [B, Cin, H, W]``, ``weight [Cin, Cout, k,
    k]`` → ``[B, Cout, (H−1)·s − 2p + k + op, …]`` (``2H`` for CompressAI's k 5, s 2, p 2, op 1). As a
    convolution of the input dilated by the stride with the kernel flipped and its channels swapped,
    padded ``k − 1 − p`` before and ``k − 1 − p + op`` after."""
    k = weight.shape[-1]
    p = k // 2
    kernel = jnp.flip(jnp.swapaxes(weight, 0, 1), axis=(2, 3))
    lo, hi = k - 1 - p, k - 1 - p + output_padding
    out = jax.lax.conv_general_dilated(
        x,
        kernel,
        (1, 1),
        ((lo, hi), (lo, hi)),
        lhs_dilation=(stride, stride),
        dimension_numbers=("NCHW", "OIHW", "NCHW"),
    )
    return out if bias is None else out + bias[None, :, None, None]


def pixel_shuffle(x: jax.Array, r: int) -> jax.Array:
    """PyTorch's ``PixelShuffle(r)``: ``[B, C·r², H, W]`` → ``[B, C, H·r, W·r]``, output ``[c, h·r + i,
    w·r + j]`` = input ``[c·r² + i·r + j, h, w]``."""
    b, c, h, w = x.shape
    x = x.reshape(b, c // (r * r), r, r, h, w)
    return x.transpose(0, 1, 4, 2, 5, 3).reshape(b, c // (r * r), h * r, w * r)


def non_negative(value: jax.Array, minimum: float) -> jax.Array:
    """CompressAI's ``NonNegativeParametrizer`` forward: ``max(v, (minimum + pedestal)^½)² − pedestal``."""
    bound = (minimum + PEDESTAL) ** 0.5
    return jnp.maximum(value, bound) ** 2 - PEDESTAL


def gdn(x: jax.Array, beta: jax.Array, gamma: jax.Array, inverse: bool = False) -> jax.Array:
    """GDN (``x / √norm``) or inverse GDN (``x · √norm``) of ``x [B, C, H, W]`` with the stored ``beta [C]``
    and ``gamma [C, C]``; ``norm[i] = beta[i] + Σ_j gamma[i, j]·x[j]²`` (a 1×1 conv of ``x²``)."""
    beta = non_negative(beta, BETA_MIN)
    gamma = non_negative(gamma, 0.0)
    norm = jnp.einsum("ij,bjhw->bihw", gamma, x * x) + beta[None, :, None, None]
    return x * jnp.sqrt(norm) if inverse else x * jax.lax.rsqrt(norm)


def _leaky(x: jax.Array) -> jax.Array:
    return jnp.where(x >= 0, x, LEAKY_SLOPE * x)


# ------------------------------------------------------------------------------ CompressAI's blocks


def _conv(w: _Weights, name: str, x: jax.Array, stride: int = 1) -> jax.Array:
    return conv2d(x, w[f"{name}.weight"], w[f"{name}.bias"], stride)


def _subpel(w: _Weights, name: str, x: jax.Array) -> jax.Array:
    """``subpel_conv3x3(in, out, 2)``: ``Sequential(Conv2d(in, out·4, 3), PixelShuffle(2))``."""
    return pixel_shuffle(_conv(w, f"{name}.0", x), 2)


def _residual_with_stride(w: _Weights, name: str, x: jax.Array) -> jax.Array:
    """``ResidualBlockWithStride(in, out, 2)``: conv1 (3×3 /2) → LeakyReLU → conv2 → GDN, + skip (1×1 /2)."""
    out = _leaky(_conv(w, f"{name}.conv1", x, 2))
    out = gdn(_conv(w, f"{name}.conv2", out), w[f"{name}.gdn.beta"], w[f"{name}.gdn.gamma"])
    return out + _conv(w, f"{name}.skip", x, 2)


def _residual(w: _Weights, name: str, x: jax.Array) -> jax.Array:
    """``ResidualBlock(N, N)``: conv1 → LeakyReLU → conv2 → LeakyReLU, + x (or a 1×1 skip where the file
    has one)."""
    out = _leaky(_conv(w, f"{name}.conv2", _leaky(_conv(w, f"{name}.conv1", x))))
    return out + (_conv(w, f"{name}.skip", x) if f"{name}.skip.weight" in w.arrays else x)


def _residual_upsample(w: _Weights, name: str, x: jax.Array) -> jax.Array:
    """``ResidualBlockUpsample(N, N, 2)``: subpel → LeakyReLU → conv → inverse GDN, + subpel upsample(x)."""
    out = _conv(w, f"{name}.conv", _leaky(_subpel(w, f"{name}.subpel_conv", x)))
    out = gdn(out, w[f"{name}.igdn.beta"], w[f"{name}.igdn.gamma"], inverse=True)
    return out + _subpel(w, f"{name}.upsample", x)


def _attention(w: _Weights, name: str, x: jax.Array) -> jax.Array:
    """``AttentionBlock(N)``: ``a · sigmoid(b) + x``, ``a`` = 3 residual units, ``b`` = 3 units and a 1×1
    conv; a unit is ``relu(x + conv1x1(relu(conv3x3(relu(conv1x1(x))))))`` (N → N/2 → N/2 → N)."""

    def unit(prefix: str, y: jax.Array) -> jax.Array:
        out = jax.nn.relu(_conv(w, f"{prefix}.conv.0", y))
        out = jax.nn.relu(_conv(w, f"{prefix}.conv.2", out))
        return jax.nn.relu(_conv(w, f"{prefix}.conv.4", out) + y)

    a = b = x
    for i in range(3):
        a = unit(f"{name}.conv_a.{i}", a)
        b = unit(f"{name}.conv_b.{i}", b)
    b = _conv(w, f"{name}.conv_b.3", b)
    return a * jax.nn.sigmoid(b) + x


# ------------------------------------------------------------------------------------------- models


def _factorized_analysis(w: _Weights, x: jax.Array) -> jax.Array:
    """FactorizedPrior's ``g_a``: ``x [B, 3, H, W]`` → ``y [B, M, H/16, W/16]``."""
    for i in (0, 2, 4, 6):
        x = _conv(w, f"g_a.{i}", x, 2)
        if i < 6:
            x = gdn(x, w[f"g_a.{i + 1}.beta"], w[f"g_a.{i + 1}.gamma"])
    return x


def _factorized_synthesis(w: _Weights, y: jax.Array) -> jax.Array:
    """FactorizedPrior's ``g_s``: ``y [B, M, h, w]`` → ``[B, 3, 16h, 16w]``."""
    for i in (0, 2, 4, 6):
        y = conv_transpose2d(y, w[f"g_s.{i}.weight"], w[f"g_s.{i}.bias"])
        if i < 6:
            y = gdn(y, w[f"g_s.{i + 1}.beta"], w[f"g_s.{i + 1}.gamma"], inverse=True)
    return y


def median_quantise(y: jax.Array, quantiles: jax.Array) -> jax.Array:
    """The entropy bottleneck's eval quantisation of ``y [B, C, h, w]``: ``round(y − m) + m`` with the
    medians ``m = quantiles[:, 0, 1]`` (``quantiles [C, 1, 3]``); half to even (``torch.round``)."""
    medians = quantiles[:, 0, 1][None, :, None, None]
    return jnp.round(y - medians) + medians


# The blocks of g_a and g_s in order (their index in the nn.Sequential is their place in the list).
_CHENG_ANCHOR = (
    ("stride", "res", "stride", "res", "stride", "res", "conv_s2"),
    ("res", "up", "res", "up", "res", "up", "res", "subpel"),
)
_CHENG_ATTN = (
    ("stride", "res", "stride", "attn", "res", "stride", "res", "conv_s2", "attn"),
    ("attn", "res", "up", "res", "up", "attn", "res", "up", "res", "subpel"),
)
_BLOCKS: dict[str, Callable[[_Weights, str, jax.Array], jax.Array]] = {
    "stride": _residual_with_stride,
    "res": _residual,
    "up": _residual_upsample,
    "attn": _attention,
    "subpel": _subpel,
    "conv_s2": lambda w, name, x: _conv(w, name, x, 2),
}


def _sequential(kinds: tuple[str, ...], prefix: str, w: _Weights, x: jax.Array) -> jax.Array:
    """The blocks ``kinds`` of the ``nn.Sequential`` named ``prefix``, in order."""
    for i, kind in enumerate(kinds):
        x = _BLOCKS[kind](w, f"{prefix}.{i}", x)
    return x


@dataclasses.dataclass(frozen=True)
class _Architecture:
    analysis: Callable[[_Weights, jax.Array], jax.Array]
    quantise: Callable[[_Weights, jax.Array], jax.Array]
    synthesis: Callable[[_Weights, jax.Array], jax.Array]
    first_weight: str  # the state dict's first name: where a nested file's prefix ends, and N
    latent_weight: str  # the weight whose output count is the latent's M


def _round(w: _Weights, y: jax.Array) -> jax.Array:
    """The Gaussian conditional's eval quantisation (``"dequantize"`` without means): ``round(y)``."""
    del w
    return jnp.round(y)


def _cheng(layout: tuple[tuple[str, ...], tuple[str, ...]]) -> _Architecture:
    return _Architecture(
        functools.partial(_sequential, layout[0], "g_a"),
        _round,
        functools.partial(_sequential, layout[1], "g_s"),
        "g_a.0.conv1.weight",
        "g_a.0.conv1.weight",
    )


ARCHITECTURES: dict[str, _Architecture] = {
    "bmshj2018-factorized": _Architecture(
        _factorized_analysis,
        lambda w, y: median_quantise(y, w["entropy_bottleneck.quantiles"]),
        _factorized_synthesis,
        "g_a.0.weight",
        "g_a.6.weight",
    ),
    "cheng2020-anchor": _cheng(_CHENG_ANCHOR),
    "cheng2020-attn": _cheng(_CHENG_ATTN),
}


def analysis(architecture: str, params: Params, x: jax.Array) -> jax.Array:
    """The latent ``y = g_a(x)`` of ``x [B, 3, H, W]`` (H, W multiples of 64): ``[B, M, H/16, W/16]``."""
    return ARCHITECTURES[architecture].analysis(_Weights(params, architecture), x)


def quantise(architecture: str, params: Params, y: jax.Array) -> jax.Array:
    """``y_hat`` as the model's eval forward quantises the latent ``y``."""
    return ARCHITECTURES[architecture].quantise(_Weights(params, architecture), y)


def synthesis(architecture: str, params: Params, y_hat: jax.Array) -> jax.Array:
    """``g_s(y_hat)``: ``[B, M, h, w]`` → ``[B, 3, 16h, 16w]``, unclipped."""
    return ARCHITECTURES[architecture].synthesis(_Weights(params, architecture), y_hat)


def forward(architecture: str, params: Params, x: jax.Array) -> jax.Array:
    """``x_hat = g_s(quantise(g_a(x)))`` of ``x [B, 3, H, W]`` in [0, 1] (H, W multiples of 64), unclipped,
    as CompressAI's eval ``forward(x)["x_hat"]`` returns it."""
    return synthesis(architecture, params, quantise(architecture, params, analysis(architecture, params, x)))


# -------------------------------------------------------------------------------------- loading


def _check_architecture(architecture: str) -> None:
    if architecture not in ARCHITECTURES:
        raise CompressionModelError(
            f"unknown compression model {architecture!r} (known: {', '.join(ARCHITECTURES)})"
        )


def rename_keys(state: Mapping[str, np.ndarray], architecture: str) -> dict[str, np.ndarray]:
    """The model's own names: a checkpoint's nesting (``state_dict.``, ``model.``) and DataParallel's
    ``module.`` dropped (whatever precedes the first weight's name), and older files' ``.downsample.``
    renamed ``.skip.`` as CompressAI's ``load_pretrained`` does. CompressionModelError if that weight is
    absent."""
    first = ARCHITECTURES[architecture].first_weight
    anchors = [k for k in state if k == first or k.endswith(f".{first}")]
    if not anchors:
        raise CompressionModelError(
            f"the weights lack {first}, which {architecture} needs (wrong architecture or file?)"
        )
    prefix = min(anchors, key=len)[: -len(first)]
    out = {}
    for key, value in state.items():
        if key.startswith(prefix):
            out[key[len(prefix) :].replace(".downsample.", ".skip.")] = value
    return out


@dataclasses.dataclass(frozen=True)
class CompressionModel:
    """A loaded model: ``architecture``, ``params`` (float32 JAX arrays by state-dict name), channel counts
    ``n`` and ``m`` (``m`` = the latent's), ``source`` (the weights file)."""

    architecture: str
    params: dict[str, jax.Array]
    n: int
    m: int
    source: str

    def __call__(self, images: np.ndarray) -> np.ndarray:
        """uint8 ``[B, H, W, 3]`` → the model's reconstruction, uint8 ``[B, H, W, 3]`` (one image at a
        time, to bound memory)."""
        return np.concatenate([regenerate(self.architecture, self.params, image[None]) for image in images])


def load(architecture: str, path: str | Path) -> CompressionModel:
    """The CompressAI model ``architecture`` with the weights at ``path`` (what ``torch.save`` writes of its
    state dict, or ``.npz``), checked by tracing the forward on a 64×64 input: CompressionModelError, in one
    line naming the file, for a missing weight (the first the forward reads) or weights of wrong shapes."""
    _check_architecture(architecture)
    arch = ARCHITECTURES[architecture]
    try:
        state = rename_keys(read_state_dict(path), architecture)
        params = {
            k: jnp.asarray(v, jnp.float32)
            for k, v in state.items()
            if k.startswith(("g_a.", "g_s.", "entropy_bottleneck.quantiles"))
            and np.issubdtype(v.dtype, np.floating)
        }
        probe = jax.ShapeDtypeStruct((1, 3, PAD_MULTIPLE, PAD_MULTIPLE), jnp.float32)
        out = jax.eval_shape(functools.partial(forward, architecture), params, probe)
    except CompressionModelError as err:
        raise CompressionModelError(f"{path}: {err}") from None
    except MnerfError as err:  # the file itself (missing, foreign, hostile): its message names it
        raise CompressionModelError(str(err)) from None
    except (TypeError, ValueError) as err:  # lax's shape checks
        first_line = (str(err).strip().splitlines() or [type(err).__name__])[0]
        raise CompressionModelError(
            f"{path}: weights of the wrong shapes for {architecture} ({first_line})"
        ) from None
    if out.shape != probe.shape:
        raise CompressionModelError(
            f"{path}: {architecture} with these weights maps {probe.shape} to {out.shape}"
        )
    n, m = (int(params[name].shape[0]) for name in (arch.first_weight, arch.latent_weight))
    return CompressionModel(architecture, params, n, m, str(path))


def quality_label(path: str | Path) -> str:
    """A short label of a weights file: ``qN`` for CompressAI's published names (``…-N-<8 hex>.pth.tar``)
    or names ending ``-N`` / ``-qN`` / ``_qualityN``, else the file name without its suffixes."""
    stem = Path(path).name
    for suffix in (".tar", ".pth", ".pt", ".npz", ".ckpt", ".bin"):
        stem = stem.removesuffix(suffix)
    match = re.search(r"(?:^|[-_])(?:q|quality)?(\d{1,2})(?:-[0-9a-f]{8})?$", stem)
    return f"q{int(match.group(1))}" if match else stem


# ------------------------------------------------------------------------------------- running


@functools.partial(jax.jit, static_argnums=0)
def _run(architecture: str, params: Params, x: jax.Array) -> jax.Array:
    return jnp.clip(forward(architecture, params, x), 0.0, 1.0)


def regenerate(architecture: str, params: Params, images: np.ndarray) -> np.ndarray:
    """uint8 ``[B, H, W, 3]`` through the model: [0, 1], zero-padded (centred) to multiples of 64, coded,
    cropped back, clipped, rounded to uint8 ``[B, H, W, 3]``."""
    _, h, w, _ = images.shape
    new_h, new_w = -(-h // PAD_MULTIPLE) * PAD_MULTIPLE, -(-w // PAD_MULTIPLE) * PAD_MULTIPLE
    top, left = (new_h - h) // 2, (new_w - w) // 2
    x = images.astype(np.float32).transpose(0, 3, 1, 2) / np.float32(255.0)
    x = np.pad(x, ((0, 0), (0, 0), (top, new_h - h - top), (left, new_w - w - left)))
    out = np.asarray(_run(architecture, params, jnp.asarray(x)))[:, :, top : top + h, left : left + w]
    return (out.transpose(0, 2, 3, 1) * 255.0 + 0.5).astype(np.uint8)
