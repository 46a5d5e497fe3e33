"""The MultiNeRF watermark module: a watermark VM grid, the ID embedding ``Emb``, the FiLM modulator ``Mod``.

For watermark ID ``n`` (an integer in ``[0, N)``)::

    e_n = Emb(onehot(n))                        Linear(N, H) → ReLU → Linear(H, 16)
    [γ_n, β_n] = Mod(e_n)                       one Linear(16, 2C)
    w(x)  = ⊕_m [plane_m · line_m](x)           the watermark VM grid, C = ΣWMCom channels (24 by default)
    w'(x) = γ_n ⊙ w(x) + β_n
    c̃(x)  = MLP_Fea(G_c(x), d; last layer += w'(x) · out_extra)

``Emb`` and ``Mod`` start at torch's default init, so every ID starts with its own, unrelated ``(γ_n, β_n)``
(magnitudes ~0.3). A FiLM around the identity (``γ = 1 + Δγ``, ``Δγ`` small) leaves the IDs nearly alike
for the whole of a short embedding: the shared part of ``w'`` then learns one message for all IDs.
``out_extra`` starts at small noise (1e-3), so the untrained watermarked model renders what the TensoRF it
came from renders (to within one 8-bit level).

``(γ_n, β_n)`` depend on the ID only, so they are computed once per image (:func:`condition`) and passed to
the renderer as ``cond``; the colour function reads them per sample.

Params pytree (a fitted TensoRF's params plus)::

    params["wm"] = {"grid": VMGrid,                            # grid variants
                    "pos_mlp": {"w0", "b0", "w1", "b1"},        # no_grid: position MLP instead of the grid
                    "emb": {"w0": [N, H], "b0", "w1": [H, E], "b1"},
                    "mod": {"w": [E, 2C], "b": [2C]}}           # FiLM variants
    params["mlp"]["out_extra"]: [X, 3]  or  params["mlp"]["in_extra"]: [X, W]

Variants (``WatermarkConfig.variant``), the configurations the paper compares:

============== =========================================================================================
multinerf      grid + Emb + FiLM into the last MLP layer (the method)
no_grid        -GRID(+MLP): a small MLP on the encoded position replaces the grid; FiLM, last layer
no_film        -FiLM: ``[w(x), e_n]`` concatenated (no modulation) into the last layer
frozen_geometry as multinerf, but the fitted field (geometry and appearance) is not trained: the paper's
               G_σ frozen, where only the watermark module learns
early          +EARLY: ``w'(x)`` enters the first MLP layer (``in_extra``)
appearance_film -GRID: no watermark grid nor position MLP; FiLM modulates the appearance features
               ``G_c(x)`` (the field's own, ``app_features`` channels), last layer
appearance_concat -FiLM(-GRID): ``[G_c(x), e_n]`` concatenated (no modulation) into the last layer
waterf         WateRF: one message, no ID, no watermark module; the TensoRF itself is fine-tuned
waterf_mod     WateRF-modified: WateRF plus ``e_n`` fed to the first MLP layer
============== =========================================================================================
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, get_args

import jax
import jax.numpy as jnp

from mnerf_jax.core.config import ModelConfig
from mnerf_jax.core.errors import MnerfError
from mnerf_jax.core.watermark_config import MAX_AUTO_IDS_PER_STEP, Variant, WatermarkConfig
from mnerf_jax.tensorf import field, grids
from mnerf_jax.tensorf.render import FieldFns, TensorfDensity

Array = jax.Array
Params = dict

VARIANTS = get_args(Variant)
_GRID_VARIANTS = ("multinerf", "no_film", "frozen_geometry", "early")
_FILM_VARIANTS = ("multinerf", "no_grid", "frozen_geometry", "early", "appearance_film")
# The paper's -GRID ablations without a replacement MLP: the ID acts on the field's appearance features.
_APPEARANCE_VARIANTS = ("appearance_film", "appearance_concat")
_CONCAT_VARIANTS = ("no_film", "appearance_concat")
# Frequencies of the position encoding that feeds the no_grid variant's MLP.
POS_FREQS = 6
POS_HIDDEN = 64


class WatermarkError(MnerfError):
    """A watermark configuration that cannot be built."""


# --------------------------------------------------------------------------------------------- variants


def uses_ids(cfg: WatermarkConfig) -> bool:
    """True when renders depend on the chosen ID (every variant but waterf)."""
    return cfg.variant != "waterf"


def uses_grid(cfg: WatermarkConfig) -> bool:
    return cfg.variant in _GRID_VARIANTS


def uses_film(cfg: WatermarkConfig) -> bool:
    return cfg.variant in _FILM_VARIANTS


def injection(cfg: WatermarkConfig) -> str | None:
    """Which MLP layer receives the extra features: ``"last"``, ``"first"`` or None (waterf)."""
    if cfg.variant == "waterf":
        return None
    if cfg.variant in ("early", "waterf_mod"):
        return "first"
    return "last"


def ids_per_step_of(cfg: WatermarkConfig, num_ids: int | None = None) -> int:
    """``K``, the IDs an embedding step renders: ``cfg.schedule.ids_per_step`` (every ID when there are
    fewer), or for 0 every ID up to :data:`MAX_AUTO_IDS_PER_STEP`."""
    n = cfg.num_ids if num_ids is None else int(num_ids)
    return min(n, int(cfg.schedule.ids_per_step) if cfg.schedule.ids_per_step > 0 else MAX_AUTO_IDS_PER_STEP)


# Steps per ID of the automatic schedule (watermark.schedule.phase1_steps / phase2_steps = -1), for at least
# AUTO_SCHEDULE_MIN_IDS IDs: 4 IDs get 200 + 800 steps (the paper's ~1,000), 16 IDs 800 + 3,200. More IDs
# need more steps even when every ID renders on every step. A short budget is better spent cutting phase 1
# (configs/embed_cpu.toml) than shrinking this schedule (docs/experiments/).
AUTO_PHASE1_STEPS_PER_ID = 50
AUTO_PHASE2_STEPS_PER_ID = 200
AUTO_SCHEDULE_MIN_IDS = 4


def phase_steps(cfg: WatermarkConfig, num_ids: int | None = None) -> tuple[int, int]:
    """``(phase-1 steps, phase-2 steps)``: the config's, or for -1 the automatic schedule for the IDs."""
    n = max(cfg.num_ids if num_ids is None else int(num_ids), AUTO_SCHEDULE_MIN_IDS)
    p1 = n * AUTO_PHASE1_STEPS_PER_ID if cfg.schedule.phase1_steps < 0 else int(cfg.schedule.phase1_steps)
    p2 = n * AUTO_PHASE2_STEPS_PER_ID if cfg.schedule.phase2_steps < 0 else int(cfg.schedule.phase2_steps)
    return p1, p2


def wm_channels(cfg: WatermarkConfig, app_features: int) -> int:
    """``C``: watermark feature channels: ``Σ wm_ranks`` (24 by default), or for the appearance variants
    the field's ``app_features``."""
    return int(app_features) if cfg.variant in _APPEARANCE_VARIANTS else int(sum(cfg.module.wm_ranks))


def extra_width(cfg: WatermarkConfig, app_features: int) -> int:
    """Width ``X`` of the features the colour MLP receives (rows of ``out_extra`` / ``in_extra``)."""
    if cfg.variant == "waterf":
        return 0
    if cfg.variant == "waterf_mod":
        return cfg.module.emb_dim
    if cfg.variant in _CONCAT_VARIANTS:
        return wm_channels(cfg, app_features) + cfg.module.emb_dim
    return wm_channels(cfg, app_features)


def trains_source(cfg: WatermarkConfig) -> bool:
    """False for frozen_geometry and a cached source: the fitted field (density and appearance grids, basis,
    MLP) keeps its values and only the watermark module learns."""
    return cfg.variant != "frozen_geometry" and not cfg.schedule.cache_source


# ------------------------------------------------------------------------------------------------- init


def _linear(key: Array, fan_in: int, fan_out: int, scale: float = 1.0) -> tuple[Array, Array]:
    """torch.nn.Linear's default init ``U(±1/√fan_in)`` times ``scale``: ``(w [in, out], b [out])``."""
    bound = scale / math.sqrt(fan_in)
    kw, kb = jax.random.split(key)
    w = jax.random.uniform(kw, (fan_in, fan_out), jnp.float32, -bound, bound)
    b = jax.random.uniform(kb, (fan_out,), jnp.float32, -bound, bound)
    return w, b


def init_watermark(
    key: Array,
    cfg: WatermarkConfig,
    num_ids: int,
    resolution: tuple[int, int, int],
    app_features: int,
    grid_scale: float = 0.1,
    mod_scale: float = 1.0,
) -> Params:
    """Fresh watermark params ``params["wm"]`` (see the module docstring; ``{}`` for waterf).

    Args:
      key: PRNG key.
      cfg: watermark config (variant, ranks, embedding sizes).
      num_ids: ``N``, the one-hot width of ``Emb``.
      resolution: grid nodes ``(X, Y, Z)``, the same as the field's density and appearance grids.
      app_features: the field's appearance feature channels (what the appearance variants modulate).
      grid_scale: std of the watermark grid factors (TensoRF's 0.1).
      mod_scale: ``Mod`` starts at this times torch's default init ``U(±1/√emb_dim)``.
    """
    cfg.check_ids(num_ids)
    k_grid, k_pos0, k_pos1, k_emb0, k_emb1, k_mod = jax.random.split(key, 6)
    wm: Params = {}
    c = wm_channels(cfg, app_features)
    if uses_grid(cfg):
        wm["grid"] = grids.init_vm(k_grid, resolution, cfg.module.wm_ranks, grid_scale)
    if cfg.variant == "no_grid":
        w0, b0 = _linear(k_pos0, 3 + 6 * POS_FREQS, POS_HIDDEN)
        w1, b1 = _linear(k_pos1, POS_HIDDEN, c)
        wm["pos_mlp"] = {"w0": w0, "b0": b0, "w1": w1, "b1": b1}
    if uses_ids(cfg):
        w0, b0 = _linear(k_emb0, num_ids, cfg.module.emb_hidden)
        w1, b1 = _linear(k_emb1, cfg.module.emb_hidden, cfg.module.emb_dim)
        wm["emb"] = {"w0": w0, "b0": b0, "w1": w1, "b1": b1}
    if uses_film(cfg):
        w, b = _linear(k_mod, cfg.module.emb_dim, 2 * c, mod_scale)
        wm["mod"] = {"w": w, "b": b}
    return wm


def add_watermark(
    key: Array,
    field_params: Params,
    cfg: WatermarkConfig,
    num_ids: int,
    extra_scale: float = 1e-3,
) -> Params:
    """A fitted TensoRF's params with the watermark module added (new dicts; the input is not changed).

    The watermark grid takes the density grid's resolution; ``out_extra`` / ``in_extra`` start at
    ``extra_scale · N(0, 1)``.
    """
    k_wm, k_extra = jax.random.split(key)
    resolution = grids.vm_resolution(field_params["density"])
    params = dict(field_params)
    mlp = {k: v for k, v in field_params["mlp"].items() if k not in ("out_extra", "in_extra")}
    app_features = int(field_params["basis"].shape[-1])
    width = extra_width(cfg, app_features)
    where = injection(cfg)
    if where == "last":
        mlp["out_extra"] = extra_scale * jax.random.normal(k_extra, (width, 3), jnp.float32)
    elif where == "first":
        hidden = int(field_params["mlp"]["w0"].shape[1])
        mlp["in_extra"] = extra_scale * jax.random.normal(k_extra, (width, hidden), jnp.float32)
    params["mlp"] = mlp
    params["wm"] = init_watermark(k_wm, cfg, num_ids, resolution, app_features)
    return params


def resample_watermark(params: Params, resolution: tuple[int, int, int]) -> Params:
    """Resize the watermark grid to ``resolution`` (with the field's upsampling; no-op without a grid)."""
    if "grid" not in params.get("wm", {}):
        return params
    wm = dict(params["wm"], grid=grids.upsample_vm(params["wm"]["grid"], resolution))
    return dict(params, wm=wm)


def shrink_watermark(params: Params, lo: tuple[int, ...], hi: tuple[int, ...]) -> Params:
    """Crop the watermark grid to nodes ``lo ≤ i < hi`` (with the field's aabb shrink)."""
    if "grid" not in params.get("wm", {}):
        return params
    wm = dict(params["wm"], grid=grids.shrink_vm(params["wm"]["grid"], lo, hi))
    return dict(params, wm=wm)


# ---------------------------------------------------------------------------------------------- forward


def embed_id(wm: Params, index: Array | int, num_ids: int) -> Array:
    """``e_n = Emb(onehot(n))``: ``[emb_dim]``. ``index`` may be traced (one compilation for all IDs)."""
    onehot = jax.nn.one_hot(jnp.asarray(index, jnp.int32), num_ids, dtype=jnp.float32)
    h = jax.nn.relu(onehot @ wm["emb"]["w0"] + wm["emb"]["b0"])
    return h @ wm["emb"]["w1"] + wm["emb"]["b1"]


def film(wm: Params, e: Array) -> tuple[Array, Array]:
    """``(γ [C], β [C]) = Mod(e)``."""
    out = e @ wm["mod"]["w"] + wm["mod"]["b"]
    gamma, beta = jnp.split(out, 2, axis=-1)
    return gamma, beta


def condition(params: Params, index: Array | int, cfg: WatermarkConfig) -> Any:
    """The renderer's ``cond`` for ID ``index``, computed once per image.

    FiLM variants: ``{"gamma": [C], "beta": [C]}``; the concatenating variants and waterf_mod:
    ``{"emb": [E]}``; waterf: None.
    """
    if not uses_ids(cfg):
        return None
    wm = params["wm"]
    num_ids = int(wm["emb"]["w0"].shape[0])
    e = embed_id(wm, index, num_ids)
    if uses_film(cfg):
        gamma, beta = film(wm, e)
        return {"gamma": gamma, "beta": beta}
    return {"emb": e}


def condition_many(params: Params, indices: Array, cfg: WatermarkConfig) -> Any:
    """The renderer's ``cond`` for ``K`` IDs at once (``indices [K]``): :func:`condition`'s leaves with a
    leading ``[K]`` axis. The colour function then returns ``[P, 3K]``: ID ``indices[k]``'s colour in columns
    ``3k:3k+3``, with everything before the last MLP layer computed once (FiLM enters there)."""
    if not uses_ids(cfg):
        raise WatermarkError("variant waterf has no IDs to render several of at once")
    return jax.vmap(lambda i: condition(params, i, cfg))(jnp.asarray(indices, jnp.int32))


def null_renders_source(cfg: WatermarkConfig) -> bool:
    """True when a null FiLM conditioning (``γ = β = 0``, :func:`with_null_condition`) renders exactly the
    fitted field the watermark was embedded into: FiLM enters the last layer additively and the fitted field
    did not train."""
    return uses_film(cfg) and injection(cfg) == "last" and not trains_source(cfg)


def with_null_condition(cond: Any) -> Any:
    """A :func:`condition_many` cond of K IDs with a (K+1)-th whose ``γ`` and ``β`` are zero: its colour is
    the fitted field's own where :func:`null_renders_source`."""
    return jax.tree.map(lambda x: jnp.concatenate([x, jnp.zeros_like(x[:1])]), cond)


def is_multi(cond: Any) -> bool:
    """True for a :func:`condition_many` cond (a leading ``[K]`` axis on every leaf)."""
    if cond is None:
        return False
    leaf = cond["gamma"] if "gamma" in cond else cond["emb"]
    return leaf.ndim == 2


def position_features(pos_mlp: Params, xyz: Array) -> Array:
    """no_grid's ``w(x)``: ``[P, C]`` from an MLP on ``[x, PE(x, 6)]`` (``x`` normalised, π-scaled PE)."""
    enc = jnp.concatenate([xyz, field.positional_encoding(xyz * jnp.pi, POS_FREQS)], axis=-1)
    h = jax.nn.relu(enc @ pos_mlp["w0"] + pos_mlp["b0"])
    return h @ pos_mlp["w1"] + pos_mlp["b1"]


def raw_features(params: Params, xyz: Array, cfg: WatermarkConfig, appearance: Array | None = None) -> Array:
    """``w(x) [P, C]`` at normalised points ``xyz [P, 3]`` (grid, position MLP or appearance features;
    ``appearance``: the field's appearance features at ``xyz`` where the caller has them already)."""
    if cfg.variant in _APPEARANCE_VARIANTS:
        return field.appearance_features(params, xyz) if appearance is None else appearance
    if uses_grid(cfg):
        return grids.sample_vm(params["wm"]["grid"], xyz)
    return position_features(params["wm"]["pos_mlp"], xyz)


def extra_features(
    params: Params, cond: Any, xyz: Array, cfg: WatermarkConfig, appearance: Array | None = None
) -> Array | None:
    """The features ``[P, X]`` the colour MLP receives for ``cond`` at ``xyz [P, 3]`` (None for waterf);
    ``[P, K, X]`` for a :func:`condition_many` cond (``w(x)`` sampled once for the K IDs)."""
    if cfg.variant == "waterf":
        return None
    multi = is_multi(cond)
    lead: tuple[int, ...] = (xyz.shape[0],)
    if multi:
        # cond leaves [K, X] against points [P, 1, C]: features [P, K, X].
        lead = (xyz.shape[0], int(jax.tree.leaves(cond)[0].shape[0]))
        cond = jax.tree.map(lambda a: a[None], cond)
    if cfg.variant == "waterf_mod":
        return jnp.broadcast_to(cond["emb"], (*lead, cond["emb"].shape[-1]))
    w = raw_features(params, xyz, cfg, appearance)
    if multi:
        w = w[:, None]
    if cfg.variant in _CONCAT_VARIANTS:
        emb = jnp.broadcast_to(cond["emb"], (*lead, cond["emb"].shape[-1]))
        return jnp.concatenate([jnp.broadcast_to(w, (*lead, w.shape[-1])), emb], -1)
    return cond["gamma"] * w + cond["beta"]


def film_logits(
    params: Params, cond: Any, xyz: Array, cfg: WatermarkConfig, appearance: Array | None = None
) -> Array:
    """What the FiLM features of K IDs add to the last colour layer: ``[P, K, 3]`` for a
    :func:`condition_many` cond, at normalised ``xyz [P, 3]``.

    ``(γ_k ⊙ w + β_k) · E = w · (diag(γ_k) E) + β_k · E``: one ``[P, C] @ [C, 3K]`` product instead of the
    ``[P, K, C]`` features of :func:`extra_features` and their cotangent (K times the memory, each way).
    """
    w = raw_features(params, xyz, cfg, appearance)  # [P, C]
    out_extra = params["mlp"]["out_extra"]  # [C, 3]
    gamma, beta = cond["gamma"], cond["beta"]  # [K, C]
    k, c = gamma.shape
    scaled = jnp.transpose(gamma[:, :, None] * out_extra[None], (1, 0, 2)).reshape(c, 3 * k)
    return (w @ scaled).reshape(w.shape[0], k, 3) + (beta @ out_extra)[None]


def colour(
    params: Params, cond: Any, xyz: Array, viewdirs: Array, model_cfg: ModelConfig, cfg: WatermarkConfig
) -> Array:
    """Watermarked colour ``[P, 3]`` at normalised ``xyz [P, 3]`` along unit ``viewdirs [P, 3]``;
    ``[P, 3K]`` for a :func:`condition_many` cond of K IDs."""
    where = injection(cfg)
    features = field.appearance_features(params, xyz)
    if where == "first" and is_multi(cond):
        # The ID enters the first layer, so the K colours are K MLP passes. They run one at a time and are
        # recomputed in the backward pass (lax.map of a checkpointed pass): the memory of one ID's pass
        # whatever K, the same values and gradient as K passes side by side.
        def one_id(c: Any) -> Array:
            extra = extra_features(params, c, xyz, cfg, features)
            return field.colour_mlp(params["mlp"], features, viewdirs, model_cfg, extra_first=extra)

        rgb = jax.lax.map(jax.checkpoint(one_id), cond)  # [K, P, 3]
        return jnp.moveaxis(rgb, 0, 1).reshape(xyz.shape[0], -1)
    if where == "last" and uses_film(cfg) and is_multi(cond):
        logits = film_logits(params, cond, xyz, cfg, features)
        return field.colour_mlp(params["mlp"], features, viewdirs, model_cfg, extra_logits=logits)
    extra = extra_features(params, cond, xyz, cfg, features)
    return field.colour_mlp(
        params["mlp"],
        features,
        viewdirs,
        model_cfg,
        extra_last=extra if where == "last" else None,
        extra_first=extra if where == "first" else None,
    )


@dataclasses.dataclass(frozen=True)
class _Colour:
    model_cfg: ModelConfig
    cfg: WatermarkConfig

    def __call__(self, params: Params, cond: Any, xyz: Array, viewdirs: Array) -> Array:
        return colour(params, cond, xyz, viewdirs, self.model_cfg, self.cfg)


def field_fns(model_cfg: ModelConfig, cfg: WatermarkConfig) -> FieldFns:
    """FieldFns of the watermarked field (hashable: equal configs share compilations)."""
    return FieldFns(density=TensorfDensity(model_cfg), colour=_Colour(model_cfg, cfg))


@dataclasses.dataclass(frozen=True)
class _HeldIdColour:
    model_cfg: ModelConfig
    cfg: WatermarkConfig
    index: int

    def __call__(self, params: Params, cond: Any, xyz: Array, viewdirs: Array) -> Array:
        held = condition(params, self.index, self.cfg)  # from params: gradients reach Emb and Mod
        return colour(params, held, xyz, viewdirs, self.model_cfg, self.cfg)


def held_id_field_fns(model_cfg: ModelConfig, cfg: WatermarkConfig, index: int) -> FieldFns:
    """FieldFns of the watermarked field as ID ``index`` renders it, whatever ``cond`` the renderer passes:
    the ID's FiLM terms are computed from the params inside the colour function, so a fit that passes
    ``cond=None`` (``tensorf.fit``) trains the whole field, the watermark module with it."""
    return FieldFns(density=TensorfDensity(model_cfg), colour=_HeldIdColour(model_cfg, cfg, int(index)))


def watermark_param_count(params: Params) -> int:
    """Scalars added by the watermark module (``wm`` plus the MLP's extra rows)."""
    extra = [v for k, v in params.get("mlp", {}).items() if k in ("out_extra", "in_extra")]
    return int(field.param_count(params.get("wm", {})) + sum(math.prod(x.shape) for x in extra))
