"""The TensoRF VM field: density, appearance features and the MLP_Fea colour decoder.

Params pytree::

    {"density": VMGrid, "appearance": VMGrid,
     "basis": [C0 + C1 + C2 (appearance), app_features],        # Linear without bias
     "mlp": {"w0": [in, W], "b0": [W], "w1": [W, W], "b1": [W], "w2": [W, 3], "b2": [3]}}

The MLP may also hold ``"out_extra" [E, 3]`` (rows of the last layer met by ``extra_last``) and
``"in_extra" [E, W]`` (rows of the first layer met by ``extra_first``); the watermark module adds them.
Points given to the field are normalised to [-1, 1] over the scene aabb (see ``grids``).
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp

from mnerf_jax.core.config import ModelConfig
from mnerf_jax.tensorf import grid_volume, grids

Array = jax.Array
Params = dict


def _torch_linear(key: Array, fan_in: int, fan_out: int, bias: bool = True) -> tuple[Array, Array | None]:
    """torch.nn.Linear's default init: weight and bias ~ U(-1/sqrt(fan_in), 1/sqrt(fan_in))."""
    bound = 1.0 / math.sqrt(fan_in)
    kw, kb = jax.random.split(key)
    w = jax.random.uniform(kw, (fan_in, fan_out), jnp.float32, -bound, bound)
    b = jax.random.uniform(kb, (fan_out,), jnp.float32, -bound, bound) if bias else None
    return w, b


def mlp_in_features(cfg: ModelConfig) -> int:
    """Input width of MLP_Fea: ``F + 3 + 2 F pe_features + 2 * 3 pe_view`` (150 for Blender)."""
    f = cfg.app_features
    return f + 3 + 2 * f * cfg.pe_features + 2 * 3 * cfg.pe_view


def init_mlp(key: Array, cfg: ModelConfig) -> dict[str, Array]:
    """MLP_Fea weights: Linear(in, W) -> ReLU -> Linear(W, W) -> ReLU -> Linear(W, 3), last bias 0."""
    k0, k1, k2 = jax.random.split(key, 3)
    width = cfg.mlp_width
    w0, b0 = _torch_linear(k0, mlp_in_features(cfg), width)
    w1, b1 = _torch_linear(k1, width, width)
    w2, _ = _torch_linear(k2, width, 3)
    return {"w0": w0, "b0": b0, "w1": w1, "b1": b1, "w2": w2, "b2": jnp.zeros((3,), jnp.float32)}


def init_field(key: Array, model_cfg: ModelConfig, resolution: tuple[int, int, int]) -> Params:
    """Fresh TensoRF VM field at ``resolution (X, Y, Z)`` grid nodes.

    Returns ``{"density", "appearance", "basis" [sum(appearance_ranks), app_features], "mlp"}``.
    """
    return _init_field(key, model_cfg, tuple(int(r) for r in resolution))


@functools.partial(jax.jit, static_argnums=(1, 2))
def _init_field(key: Array, model_cfg: ModelConfig, resolution: tuple[int, ...]) -> Params:
    kd, ka, kb, km = jax.random.split(key, 4)
    n_app = sum(model_cfg.appearance_ranks)
    basis, _ = _torch_linear(kb, n_app, model_cfg.app_features, bias=False)
    return {
        "density": grids.init_vm(kd, resolution, model_cfg.density_ranks, model_cfg.init_scale),
        "appearance": grids.init_vm(ka, resolution, model_cfg.appearance_ranks, model_cfg.init_scale),
        "basis": basis,
        "mlp": init_mlp(km, model_cfg),
    }


def density_activation(feature: Array, cfg: ModelConfig) -> Array:
    """Feature to density: ``softplus(feature + density_shift)`` or ``relu(feature)``."""
    if cfg.density_activation == "softplus":
        return jax.nn.softplus(feature + cfg.density_shift)
    if cfg.density_activation == "relu":
        return jax.nn.relu(feature)
    raise ValueError(f"unknown density_activation {cfg.density_activation!r} (softplus | relu)")


def density(params: Params, xyz: Array, cfg: ModelConfig) -> Array:
    """Volume density σ ``[P]`` (per unit length before the distance scale) at normalised ``xyz [P, 3]``."""
    return density_activation(grid_volume.sample_vm_sum(params["density"], xyz), cfg)


def appearance_features(params: Params, xyz: Array) -> Array:
    """Appearance features ``[P, app_features]``: VM component products through the basis matrix."""
    return grid_volume.sample_vm_projected(params["appearance"], params["basis"], xyz)


# pi/2 split into three float32 parts (Cody-Waite): q * _PIO2[0] is exact for |q| < 2^15.
_PIO2 = (1.5703125, 4.837512969970703125e-4, 7.54978995489188216e-8)
# Minimax polynomials of sin and cos on [-pi/4, pi/4] (Cephes sinf / cosf).
_SIN_COEFFS = (-1.6666654611e-1, 8.3321608736e-3, -1.9515295891e-4)
_COS_COEFFS = (4.166664568298827e-2, -1.388731625493765e-3, 2.443315711809948e-5)


@jax.custom_jvp
def sincos(x: Array) -> tuple[Array, Array]:
    """``(sin x, cos x)`` elementwise in float32, absolute error <= 1e-7 for ``|x| <= 1e4``.

    XLA:CPU's ``sin`` is not vectorised, which made the positional encoding most of the colour MLP's
    forward pass. This shares one range reduction between sin and cos and vectorises (the derivative
    reuses the values). Beyond ``|x| ~ 5e4`` the reduction loses accuracy; features never get there.
    """
    q = jnp.round(x * (2.0 / math.pi))
    r = ((x - q * _PIO2[0]) - q * _PIO2[1]) - q * _PIO2[2]
    z = r * r
    a, b, c = _SIN_COEFFS
    s = r + r * z * (a + z * (b + z * c))
    a, b, c = _COS_COEFFS
    co = 1.0 - 0.5 * z + z * z * (a + z * (b + z * c))
    quadrant = q.astype(jnp.int32) & 3
    sin = jnp.where(quadrant == 0, s, jnp.where(quadrant == 1, co, jnp.where(quadrant == 2, -s, -co)))
    cos = jnp.where(quadrant == 0, co, jnp.where(quadrant == 1, -s, jnp.where(quadrant == 2, -co, s)))
    return sin, cos


@sincos.defjvp
def _sincos_jvp(
    primals: tuple[Array], tangents: tuple[Array]
) -> tuple[tuple[Array, Array], tuple[Array, Array]]:
    (x,), (dx,) = primals, tangents
    sin, cos = sincos(x)
    return (sin, cos), (cos * dx, -sin * dx)


def positional_encoding(x: Array, n_freqs: int) -> Array:
    """TensoRF's encoding ``[sin(x_d 2^k)] ++ [cos(x_d 2^k)]`` (no π), index ``d * n_freqs + k``.

    ``x [P, D]`` -> ``[P, 2 D n_freqs]``.
    """
    # One sin and one cos per input (`sincos`), the higher octaves by the double-angle formulas.
    # The error grows about 2x per octave (~1e-6 at k = 4 against sin(x 2^k) directly), far below
    # what the MLP can tell apart.
    s, c = sincos(x)
    sines, cosines = [s], [c]
    for _ in range(n_freqs - 1):
        s, c = sines[-1], cosines[-1]
        sines.append(2.0 * s * c)
        cosines.append((c - s) * (c + s))
    shape = (*x.shape[:-1], x.shape[-1] * n_freqs)
    return jnp.concatenate(
        [jnp.stack(sines, -1).reshape(shape), jnp.stack(cosines, -1).reshape(shape)], axis=-1
    )


def mlp_inputs(features: Array, viewdirs: Array, cfg: ModelConfig) -> Array:
    """MLP_Fea input ``[features, viewdirs, PE(features), PE(viewdirs)]`` (PE parts omitted at 0)."""
    parts = [features, viewdirs]
    if cfg.pe_features > 0:
        parts.append(positional_encoding(features, cfg.pe_features))
    if cfg.pe_view > 0:
        parts.append(positional_encoding(viewdirs, cfg.pe_view))
    return jnp.concatenate(parts, axis=-1)


def narrow_matmul(x: Array, w: Array) -> Array:
    """``x [P, K] @ w [K, N]`` for a few output columns (N <= 4), one matrix-vector product each.

    XLA:CPU's matrix product is slow with 3 output columns (the colour MLP's last layer); matrix-vector
    products are not.
    """
    if w.shape[-1] > 4:
        return x @ w
    return jnp.stack([x @ w[:, j] for j in range(w.shape[-1])], axis=-1)


def mlp_hidden(
    mlp: dict[str, Array],
    features: Array,
    viewdirs: Array,
    cfg: ModelConfig,
    extra_first: Array | None = None,
) -> Array:
    """MLP_Fea's last hidden activation ``[P, W]`` (``extra_first`` as :func:`colour_mlp`)."""
    h = mlp_inputs(features, viewdirs, cfg) @ mlp["w0"] + mlp["b0"]
    if extra_first is not None:
        h = h + extra_first @ mlp["in_extra"]
    h = jax.nn.relu(h)
    return jax.nn.relu(h @ mlp["w1"] + mlp["b1"])


def colour_logits(params: Params, xyz: Array, viewdirs: Array, cfg: ModelConfig) -> Array:
    """TensoRF's colour before its sigmoid, ``[P, 3]``: what a watermark's last-layer rows add to
    (``sample_cache``)."""
    h = mlp_hidden(params["mlp"], appearance_features(params, xyz), viewdirs, cfg)
    return narrow_matmul(h, params["mlp"]["w2"]) + params["mlp"]["b2"]


def colour_mlp(
    mlp: dict[str, Array],
    features: Array,
    viewdirs: Array,
    cfg: ModelConfig,
    extra_last: Array | None = None,
    extra_first: Array | None = None,
    extra_logits: Array | None = None,
) -> Array:
    """MLP_Fea colour ``[P, 3]`` in (0, 1).

    Args:
      mlp: MLP weights (see the module docstring).
      features: ``[P, app_features]`` appearance features.
      viewdirs: ``[P, 3]`` unit view directions.
      cfg: model config (PE frequencies).
      extra_last: optional ``[P, E]``, concatenated to the last hidden activation and met by the rows
        ``mlp["out_extra"] [E, 3]`` of the last layer; or ``[P, K, E]``, K sets of extra features that share
        everything before the last layer: the output is then ``[P, 3K]`` (set ``k`` in columns ``3k:3k+3``).
      extra_first: optional ``[P, E]``, concatenated to the input and met by ``mlp["in_extra"] [E, W]``.
      extra_logits: optional ``[P, K, 3]``, added to the last layer's output (before the sigmoid) K times:
        what ``extra_last [P, K, E]`` contributes, for a caller that can form it without that tensor.
        The output is then ``[P, 3K]``, as for ``extra_last [P, K, E]``.

    With both extras None this is exactly TensoRF's MLPRender_Fea.
    """
    h = mlp_hidden(mlp, features, viewdirs, cfg, extra_first)
    out = narrow_matmul(h, mlp["w2"]) + mlp["b2"]
    if extra_last is not None and extra_last.ndim == 3:
        # K renders of one sample set: the hidden layers once, the last layer's extra rows per set.
        extra_logits = narrow_matmul(extra_last, mlp["out_extra"])
    elif extra_last is not None:
        out = out + narrow_matmul(extra_last, mlp["out_extra"])
    if extra_logits is not None:
        out = out[:, None, :] + extra_logits
        return jax.nn.sigmoid(out).reshape(out.shape[0], -1)
    return jax.nn.sigmoid(out)


def colour(params: Params, xyz: Array, viewdirs: Array, cfg: ModelConfig) -> Array:
    """TensoRF colour ``[P, 3]`` at normalised ``xyz [P, 3]`` seen along unit ``viewdirs [P, 3]``."""
    return colour_mlp(params["mlp"], appearance_features(params, xyz), viewdirs, cfg)


def param_count(params: Params) -> int:
    """Total number of scalars in a params pytree."""
    return int(sum(math.prod(x.shape) for x in jax.tree_util.tree_leaves(params)))
