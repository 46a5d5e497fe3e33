"""The compiled watermark-embedding step: its static spec, optimiser groups, losses and one jitted step.

One step renders one training view with the FiLM conditioning of K IDs (``watermark.schedule.ids_per_step``;
one geometry pass for all of them) and back-propagates the mean of their two-phase objectives by deferred
back-propagation (:mod:`mnerf_jax.watermark.deferred`); :mod:`mnerf_jax.watermark.embed` drives it (the
objective and the phases are described there).
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from typing import Any

import flax.struct
import jax
import jax.numpy as jnp
import optax

from mnerf_jax.core import xla_cpu
from mnerf_jax.core.config import ModelConfig
from mnerf_jax.core.watermark_config import WatermarkConfig, normalised
from mnerf_jax.imaging import augment, losses
from mnerf_jax.imaging import metrics as metrics_lib
from mnerf_jax.reader import decoder as decoder_lib
from mnerf_jax.reader import dwt
from mnerf_jax.tensorf import raymarch, render
from mnerf_jax.watermark import model as watermark
from mnerf_jax.watermark import sample_cache
from mnerf_jax.watermark.deferred import PyTree, RenderFn, deferred_grad
from mnerf_jax.watermark.objective import (
    fidelity_loss,
    message_loss,
    patch_loss,
    perceptual_loss,
    split_renders,
    uses_clean_renders,
    uses_fidelity,
    windowed,
)


@flax.struct.dataclass
class EmbedState:
    """Everything the jitted embedding step reads and writes.

    Attributes:
      params: the watermarked field (``watermark.add_watermark`` layout).
      decoder: decoder variables ``{"params", "batch_stats"[, "pooling"]}``; only ``params`` train (phase 2),
        BatchNorm keeps its running statistics (eval mode).
      opt_state: optax state of :func:`make_optimizer` over ``{"field": params, "decoder": decoder params}``.
      step: ``[]`` int32, steps completed (phase 1 then phase 2).
      key: PRNG key of the run; step ``s`` uses ``fold_in(key, s)``.
    """

    params: PyTree
    decoder: PyTree
    opt_state: Any
    step: jax.Array
    key: jax.Array


@dataclasses.dataclass(frozen=True)
class StepSpec:
    """The static part of one embedding step (hashable: one compilation per distinct value)."""

    model: ModelConfig
    wm: WatermarkConfig
    adam_b1: float
    adam_b2: float
    phase: int
    height: int
    width: int
    density_budget: int
    colour_budget: int


def total_steps(cfg: WatermarkConfig) -> int:
    return sum(watermark.phase_steps(cfg))


def step_config(cfg: WatermarkConfig) -> WatermarkConfig:
    """``cfg`` as :class:`StepSpec` holds it: the fields only the host loop reads (``host`` metadata: keys,
    seeds, checkpoints, identification, the schedule's length, the time budget, phase 3) at their defaults,
    so runs that differ only there share one compilation of :func:`embed_step` (the phase itself is
    ``StepSpec.phase``; the rate decay's length is an argument of the compiled step)."""
    return normalised(cfg, "host")


def phase_of(step: int, cfg: WatermarkConfig) -> int:
    """1 for the first ``phase1_steps`` steps, 2 until the field's schedule ends, 3 after (the decoder alone,
    ``decoder_refit``)."""
    first, second = watermark.phase_steps(cfg)
    return 1 if step < first else 2 if step < first + second else 3


def param_labels(tree: PyTree, cfg: WatermarkConfig) -> PyTree:
    """Optimiser group of every leaf of ``{"field": params, "decoder": decoder params}``.

    ``grid``: the watermark VM factors (``lr_grid``); ``source_grid``: the fitted density and appearance
    factors (``lr_grid · lr_source_scale``); ``embedding``: Emb and Mod (``lr_embedding``: each ID's row of
    Emb only learns on the steps that draw that ID); ``network``: the MLP's extra rows and the position MLP
    (``lr_network``); ``source_network``: the fitted basis and MLP (``lr_network · lr_source_scale``);
    ``decoder`` (``lr_decoder``); ``frozen``: the whole fitted field of the frozen_geometry variant or with
    ``cache_source`` (the field is cached, so it cannot change).
    """
    frozen = not watermark.trains_source(cfg)
    grid_label = "frozen" if frozen else "source_grid"
    network_label = "frozen" if frozen else "source_network"

    def field_label(path: tuple[Any, ...], _: Any) -> str:
        names = [getattr(p, "key", getattr(p, "name", None)) for p in path]
        top = names[0] if names else None
        second = names[1] if len(names) > 1 else None
        if top == "wm":
            return "embedding" if second in ("emb", "mod") else "grid" if second == "grid" else "network"
        if top in ("density", "appearance"):
            return grid_label
        if top == "mlp" and second in ("out_extra", "in_extra"):
            return "network"
        return network_label

    return {
        "field": jax.tree_util.tree_map_with_path(field_label, tree["field"]),
        "decoder": jax.tree.map(lambda _: "decoder", tree["decoder"]),
    }


def make_optimizer(
    cfg: WatermarkConfig, adam_b1: float = 0.9, adam_b2: float = 0.99, total: int | jax.Array | None = None
) -> optax.GradientTransformation:
    """Adam per group with exponential decay ``lr · decay_ratio^(t / total)``; ``total`` (default: the
    schedule's steps, ``total_steps(cfg)``) may be traced."""
    total = jnp.maximum(total_steps(cfg) if total is None else total, 1)

    def group(lr: float) -> optax.GradientTransformation:
        decay = float(cfg.optim.lr_decay_ratio)
        return optax.chain(
            optax.scale_by_adam(b1=adam_b1, b2=adam_b2, eps=1e-8),
            optax.scale_by_schedule(lambda count: -lr * decay ** (count / total)),
        )

    transforms = {
        "grid": group(cfg.optim.lr_grid),
        "network": group(cfg.optim.lr_network),
        "source_grid": group(cfg.optim.lr_grid * cfg.optim.lr_source_scale),
        "source_network": group(cfg.optim.lr_network * cfg.optim.lr_source_scale),
        "decoder": group(cfg.optim.lr_decoder),
        "embedding": group(cfg.optim.lr_embedding),
        "frozen": optax.set_to_zero(),
    }
    return optax.multi_transform(transforms, functools.partial(param_labels, cfg=cfg))


def render_patch_fn(
    spec: StepSpec, geometry: raymarch.Geometry, ids: jax.Array, cache: dict[str, jax.Array] | None = None
) -> RenderFn:
    """Patch renders with the IDs ``ids [K]``: ``rgb [R, 3K]`` (ID ``ids[k]`` in columns ``3k:3k+3``).

    With ``cache`` (``watermark.schedule.cache_source``: the view's ``cache_*`` buffers) the render is the
    whole view from its cached samples (one patch covers it; the rays are not read)."""
    if cache is not None:
        return sample_cache.view_render_fn(spec.wm, geometry.white_bg, ids, cache)
    fns = watermark.field_fns(spec.model, spec.wm)

    def render_fn(params: PyTree, rays: PyTree, key: jax.Array) -> tuple[jax.Array, dict[str, jax.Array]]:
        # (γ, β) once per call from the ID, not per sample; gradients reach Emb and Mod through them.
        # One ID: the plain cond (exactly the one-ID render); several: one geometry pass for all of them.
        if ids.shape[0] == 1:
            cond = watermark.condition(params, ids[0], spec.wm)
        else:
            cond = watermark.condition_many(params, ids, spec.wm)
        out = render.render_rays(
            fns,
            params,
            cond,
            rays[0],
            rays[1],
            geometry,
            key,
            train=spec.wm.schedule.jitter,
            density_budget=spec.density_budget,
            colour_budget=spec.colour_budget,
        )
        return out["rgb"], {"density_count": out["density_count"], "colour_count": out["colour_count"]}

    return render_fn


def make_image_loss(
    spec: StepSpec,
    key: jax.Array,
    message: jax.Array,
    target_image: jax.Array,
    decoder_state: PyTree,
    vgg_params: Any = None,
    reference: jax.Array | None = None,
    keys: jax.Array | None = None,
    ids: jax.Array | None = None,
    fidelity_budget: jax.Array | None = None,
    null: jax.Array | None = None,
) -> Callable[[jax.Array, PyTree], tuple[jax.Array, dict[str, jax.Array]]]:
    """The image-level loss ``(image [H, W, 3K], decoder params) -> (loss, {"bce", "key", "perceptual"})``.

    ``image`` holds the K renders of one view side by side in its channels (:func:`split_renders`), one
    per row of ``message [K, L]``; each term is the mean over the K renders.
    Phase 2: ``augment_per_step`` random augmentations (``key``) → LL2 → decoder → BCE(T) against
    the render's message and (``lambda_key``) the key cross-entropy against every ID's message
    ``keys [N, L]`` given the renders' ``ids [K]`` (:func:`message_loss`), plus (``lambda_clean``) BCE(T) of
    the equally augmented unwatermarked view against the null word ``null [L]`` (``keys.null_message``, far
    from every key): ``target_image``, or the clean model's render
    ``reference [H, W, 3]`` (``clean_negative = "clean_model"``).
    Phase 1: no augmentation, plus the perceptual term against ``target_image``. Both phases, with the
    quality budget on: ``lambda_fidelity ·`` :func:`fidelity_loss` against ``reference`` (its MSE budget
    ``fidelity_budget``, this step's value of the ramp, or the config's constant one).
    ``decoder_state``: the decoder's variables (BatchNorm statistics, pooling); their ``params`` are replaced
    by the argument.
    """
    cfg = spec.wm
    if uses_clean_renders(cfg) and reference is None:
        raise ValueError("the quality budget and clean_negative='clean_model' need the clean model's render")
    negative = reference if cfg.losses.clean_negative == "clean_model" else target_image
    if spec.phase == 2 and cfg.losses.lambda_clean and null is None:
        raise ValueError("the clean term (watermark.losses.lambda_clean) needs the null word (null)")

    def seen_ll2(images: jax.Array) -> jax.Array:
        """The LL2 ``[B, h, w, 3]`` of ``images [B, H, W, 3]`` as the decoder sees them (augmented in phase 2:
        the same key, so the same augmentations for every call; their random parameters per image)."""
        seen = images
        if spec.phase == 2:
            seen = augment.configured_policy(key, seen, cfg.augment)
        return dwt.ll2(windowed(cfg, seen), cfg.reading.wavelet)

    def decode(images: jax.Array, dec_params: PyTree) -> jax.Array:
        """Logits ``[B, L]`` of ``images [B, H, W, 3]`` as the decoder sees them (:func:`seen_ll2`)."""
        return decoder_lib.apply_ll2({**decoder_state, "params": dec_params}, seen_ll2(images))

    def image_loss(image: jax.Array, dec_params: PyTree) -> tuple[jax.Array, dict[str, jax.Array]]:
        renders = split_renders(image)  # [K, H, W, 3]
        terms = message_loss(cfg, decode, renders, dec_params, message, keys, ids)
        loss = cfg.losses.lambda_message * terms.term + cfg.losses.lambda_key * terms.key
        if spec.phase == 2 and cfg.losses.lambda_clean:
            clean_logits = decode(negative[None], dec_params)
            loss = loss + cfg.losses.lambda_clean * losses.bce_with_logits(
                clean_logits, null, cfg.losses.bce_temperature
            )
        perc = jnp.zeros((), jnp.float32)
        if spec.phase == 1 and cfg.losses.lambda_perceptual:
            targets = jnp.broadcast_to(target_image, renders.shape)
            perc = perceptual_loss(cfg.losses.perceptual, renders, targets, vgg_params)
            loss = loss + cfg.losses.lambda_perceptual * perc
        aux = {"bce": terms.bce, "key": terms.key, "perceptual": perc, "logits": terms.logits}
        if uses_fidelity(cfg):
            aux["fidelity"], aux["mse_clean"] = fidelity_loss(cfg, renders, reference, fidelity_budget)
            loss = loss + cfg.fidelity.weight * aux["fidelity"]
        return loss, aux

    return image_loss


# The top-level step takes xla_cpu.xla_compiler_options(), as the fit's step does: without them XLA:CPU routes
# the renders' sampled-feature arithmetic through YNNPACK fusions, which are slower here.
@xla_cpu.jit_cpu_tuned(static_argnames=("spec",))
def embed_step(
    state: EmbedState,
    geometry: raymarch.Geometry,
    batch: dict[str, jax.Array],
    layout_index: jax.Array,
    layout_owner: jax.Array,
    vgg_params: Any,
    total: jax.Array,
    *,
    spec: StepSpec,
) -> tuple[EmbedState, dict[str, jax.Array]]:
    """One optimisation step on one view rendered with K IDs (deferred back-propagation).

    ``total``: int32 scalar, the steps of the whole schedule (the learning rates decay over it).

    batch: ``rays_o, rays_d, target [H·W, 3]``, ``message [K, L]`` (0/1 float), ``id [K]`` int32 (distinct),
    ``keys [N, L]`` every ID's message (read where ``lambda_key`` > 0), ``null [L]`` the word the clean
    term reads clean images as (``keys.null_message``),
    and where :func:`uses_clean_renders` ``reference [H·W, 3]``: the clean model's render of the view;
    with the quality budget, ``fidelity_mse []``: its MSE budget at this step (:func:`fidelity_budget_db`).
    Returns the new state and scalar metrics (loss terms, bit accuracy of the un-augmented renders, PSNR;
    means over the K renders; largest per-patch sample counts).
    """
    cfg = spec.wm
    h, w = spec.height, spec.width
    key = jax.random.fold_in(state.key, state.step)
    k_render, k_aug = jax.random.split(key)
    message = batch["message"]
    target_image = batch["target"].reshape(h, w, 3)
    rays = (batch["rays_o"], batch["rays_d"])
    reference = batch["reference"].reshape(h, w, 3) if "reference" in batch else None
    image_loss = make_image_loss(
        spec,
        k_aug,
        message,
        target_image,
        state.decoder,
        vgg_params,
        reference,
        batch.get("keys"),
        batch["id"],
        batch.get("fidelity_mse"),
        batch.get("null"),
    )
    ploss = functools.partial(patch_loss, cfg) if spec.phase == 2 else None
    cache = {k: v for k, v in batch.items() if k.startswith("cache_")} or None
    render_fn = render_patch_fn(spec, geometry, batch["id"], cache)
    loss, aux, image, g_field, g_dec = deferred_grad(
        render_fn,
        image_loss,
        ploss,
        state.params,
        state.decoder["params"],
        rays,
        batch["target"],
        layout_index,
        layout_owner,
        k_render,
        h,
        w,
    )
    if spec.phase == 1:
        g_dec = jax.tree.map(jnp.zeros_like, g_dec)  # the decoder is frozen in phase 1
    grads = {"field": g_field, "decoder": g_dec}
    values = {"field": state.params, "decoder": state.decoder["params"]}
    tx = make_optimizer(cfg, spec.adam_b1, spec.adam_b2, total)
    updates, opt_state = tx.update(grads, state.opt_state, values)
    new_values = optax.apply_updates(values, updates)
    # Bit accuracy of the renders as they are (no augmentation), with the decoder before this update: the
    # loss's own logits where its decoder saw them so, else one more decoder pass.
    renders = split_renders(image)
    logits = aux["logits"]
    if spec.phase == 2 and augment.draws_any(cfg.augment):
        logits = decoder_lib.apply_ll2(state.decoder, dwt.ll2(windowed(cfg, renders), cfg.reading.wavelet))
    metrics = {
        "loss": loss,
        "loss_image": aux["loss_image"],
        "loss_patch": aux["loss_patch"],
        "bce": aux["bce"],
        "key_ce": aux["key"],
        "perceptual": aux["perceptual"],
        "bit_acc": jnp.mean(((logits > 0).astype(jnp.float32) == message).astype(jnp.float32)),
        "psnr": metrics_lib.mse_to_psnr(jnp.mean(jnp.square(renders - target_image))),
        "density_count": aux["render_stats"]["density_count"],
        "colour_count": aux["render_stats"]["colour_count"],
    }
    if uses_fidelity(cfg):
        metrics["fidelity"] = aux["fidelity"]
        metrics["psnr_clean"] = metrics_lib.mse_to_psnr(aux["mse_clean"])
        if "fidelity_mse" in batch:
            metrics["psnr_budget"] = metrics_lib.mse_to_psnr(batch["fidelity_mse"])
    new_state = state.replace(
        params=new_values["field"],
        decoder={**state.decoder, "params": new_values["decoder"]},
        opt_state=opt_state,
        step=state.step + 1,
    )
    return new_state, metrics
