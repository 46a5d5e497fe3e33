"""Training a HiDDeN watermark decoder (and the encoder that teaches it), then PCA-whitening it.

Recipe (CPU-sized; every step is one jitted function over a small batch of crops):

1. **Informed stage** (``informed_steps``). The decoder learns against its own gradient watermark
   (``informed.informed_embed``): the residual is the message gradient through the decoder, scaled to a PSNR
   rising from ``informed_start_psnr`` to ``target_psnr``; the decoder reads the encoded image (through the
   augmentation layer after ``clean_fraction`` of the steps). Image sides take turns (``informed_sizes``).
2. **Joint training** (``steps``; 0 in the default recipe). An encoder hides a random message in each image;
   the decoder reads it back from the LL2 sub-band of the encoded image after the augmentation layer. The
   encoder works at LL2 resolution (cheap): it maps ``LL2(image)/4`` and the message (broadcast over space,
   ±1) through conv-BN-ReLU blocks to an LL2-domain pattern ``R``, which reaches the image through the adjoint
   of the LL2 transform (a smooth ×4 upsampling) and is scaled per image to a fixed RMS, so that every encoded
   image has PSNR ≥ ``target_psnr`` against its original (clipping to [0, 1] only lowers the error).
   Curriculum: the residual starts strong (``start_psnr``) and weakens to ``target_psnr``; the first
   ``clean_fraction`` of the steps see no augmentation, the rest go through ``augment.random_policy`` (Low, 2
   augmentations, p = 0.75).
3. **Whitening.** The decoder's raw outputs over clean training crops give ``W = diag(e^-1/2)·Vᵀ``,
   ``b = −W·mean``: unwatermarked images then decode to white (zero-mean, identity-covariance) logits.
4. **Encoder training** (``finetune_steps``) through the frozen, whitened decoder (whitening rotates the
   logits, so an encoder from stage 2 has to re-fit; after stage 1 alone the encoder learns here from
   scratch).
5. **Evaluation** on held-out crops (photographs and procedural images never used in training): bit accuracy
   of the encoder's images and of informed embeddings, with no attack and under the Low policy, and PSNR.

Images come from ``decoder_images``. Every step's batch is drawn from
``numpy.random.default_rng([seed, step])``, so a resumed run sees the same data as an uninterrupted one.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import os
import platform
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import flax.linen as nn
import flax.serialization
import jax
import jax.numpy as jnp
import numpy as np
import optax

from mnerf_jax import decoder as dec
from mnerf_jax import dwt, informed
from mnerf_jax.decoder_images import (
    EVAL_SEED,
    TRAIN_PHOTOS,
    ImageSource,
    heldout_images,
    heldout_messages,
    load_folder,
    load_photos,
)
from mnerf_jax.errors import MnerfError

# The parts of the training state that are arrays (and go through the jitted steps); the rest is bookkeeping.
ARRAY_KEYS = ("encoder", "decoder", "opt", "opt_ft", "opt_inf")
MAX_SKIPPED = 20  # consecutive steps with non-finite gradients before a run is declared diverged
# Config fields that only change the final evaluation: a finished run can be re-evaluated with --resume.
EVAL_FIELDS = ("eval_images", "eval_sizes", "eval_augment_draws", "eval_informed_iterations", "check_images")


@dataclasses.dataclass(frozen=True)
class DecoderTrainConfig:
    """Everything that decides the trajectory of a decoder training run (compared on ``--resume``)."""

    bits: int = 16
    informed_steps: int = 4000  # decoder steps against the informed (gradient) encoder, first
    informed_sizes: tuple[int, ...] = (64, 128)  # image sides of the informed steps, in turn
    informed_start_psnr: float = 28.0  # curriculum of the informed steps (reaches target_psnr like the joint)
    steps: int = 0  # joint encoder+decoder steps, after the informed ones
    finetune_steps: int = 1500  # encoder-only steps through the whitened decoder
    size: int = 64  # side in pixels of the images the decoder sees in training (LL2 side = size / 4)
    crop_margin: int = 0  # images are encoded at size + margin; the decoder sees a random size × size window
    batch: int = 16
    seed: int = 0
    lr: float = 1e-3
    lr_finetune: float = 5e-4
    warmup_steps: int = 200
    weight_decay: float = 1e-4
    clean_fraction: float = 0.25  # curriculum: no augmentation for this fraction of the joint steps
    augment_strength: str = "low"
    augment_k: int = 2
    augment_p: float = 0.75
    temperature: float = 1.0  # BCE temperature during training (whitening fixes the final scale anyway)
    target_psnr: float = 35.5  # each encoded image's PSNR against its original is at least this
    start_psnr: float = 20.0  # curriculum: the residual starts this strong ...
    anneal_fraction: float = 0.4  # ... and reaches target_psnr after this fraction of the joint steps
    encoder_channels: int = 32
    encoder_depth: int = 3
    procedural_fraction: float = 0.35  # share of each batch drawn from procedural images
    whiten_images: int = 1024  # clean training crops used to fit the whitening
    eval_images: int = 128  # held-out crops per evaluation size
    eval_sizes: tuple[int, ...] = (64, 128, 256)  # held-out image sides (pixels)
    eval_augment_draws: int = 4  # Low-policy draws per held-out image (0: no attacked evaluation)
    eval_informed_iterations: tuple[int, ...] = (1, 10)  # informed embeddings evaluated (iterations each)
    check_images: int = 8  # encoded held-out images stored (uint8) beside the decoder
    wavelet: str = "bior4.4"
    images_dir: str = ""  # extra training images (every image file under it)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def trajectory(self) -> dict[str, Any]:
        """The fields that decide the training trajectory (what ``--resume`` compares)."""
        return {k: v for k, v in self.to_dict().items() if k not in EVAL_FIELDS}


# ------------------------------------------------------------------------------------------------------------
# Encoder


class ConvBNReLU(nn.Module):
    features: int
    kernel: int = 3

    @nn.compact
    def __call__(self, x: jax.Array, train: bool) -> jax.Array:
        x = nn.Conv(self.features, (self.kernel, self.kernel), padding=self.kernel // 2)(x)
        x = nn.BatchNorm(use_running_average=not train, momentum=0.9, epsilon=1e-3)(x)
        return nn.relu(x)


class LL2Encoder(nn.Module):
    """HiDDeN encoder at LL2 resolution: ``(LL2/4 [B, h, w, 3], bits ±1 [B, L]) → pattern R [B, h, w, 3]``.

    Conv-BN-ReLU features of the image, the message broadcast over space and concatenated to them, two more
    blocks and a 1×1 convolution to three channels.
    """

    channels: int = 32
    depth: int = 3

    @nn.compact
    def __call__(self, ll2_scaled: jax.Array, signs: jax.Array, train: bool) -> jax.Array:
        f = ll2_scaled
        for _ in range(self.depth):
            f = ConvBNReLU(self.channels)(f, train)
        msg = jnp.broadcast_to(signs[:, None, None, :], (*ll2_scaled.shape[:-1], signs.shape[-1]))
        f = jnp.concatenate([msg, f, ll2_scaled], axis=-1)
        f = ConvBNReLU(self.channels)(f, train)
        f = ConvBNReLU(self.channels)(f, train)
        return nn.Conv(3, (1, 1))(f)


def init_encoder(key: jax.Array, bits: int, channels: int = 32, depth: int = 3) -> dict[str, Any]:
    module = LL2Encoder(channels=channels, depth=depth)
    init = jax.jit(lambda k: module.init(k, jnp.zeros((1, 8, 8, 3)), jnp.zeros((1, bits)), train=False))
    return dict(init(key))


def encode(
    enc_vars: dict[str, Any],
    images: jax.Array,
    bits: jax.Array,
    cfg: DecoderTrainConfig,
    train: bool = False,
    psnr: jax.Array | float | None = None,
) -> tuple[jax.Array, Any]:
    """Encoded images ``[B, H, W, 3]`` (clipped to [0, 1]) and the encoder's updated batch stats.

    The residual is scaled to the RMS of ``psnr`` dB (default ``cfg.target_psnr``) before clipping.
    """
    psnr = cfg.target_psnr if psnr is None else psnr
    module = LL2Encoder(channels=cfg.encoder_channels, depth=cfg.encoder_depth)
    ll2 = dwt.ll2(images, cfg.wavelet)
    signs = 2.0 * bits.astype(images.dtype) - 1.0
    variables = {"params": enc_vars["params"], "batch_stats": enc_vars["batch_stats"]}
    if train:
        pattern, upd = module.apply(variables, ll2 / 4.0, signs, train=True, mutable=["batch_stats"])
        stats = upd["batch_stats"]
    else:
        pattern, stats = module.apply(variables, ll2 / 4.0, signs, train=False), enc_vars["batch_stats"]
    # The adjoint of the (linear) LL2 transform carries the pattern to image resolution as a smooth residual.
    adjoint = jax.linear_transpose(lambda x: dwt.ll2(x, cfg.wavelet), images)
    (residual,) = adjoint(pattern)
    rms = jnp.sqrt(jnp.mean(residual**2, axis=(-3, -2, -1), keepdims=True) + 1e-12)
    residual = residual * (10.0 ** (-jnp.asarray(psnr, images.dtype) / 20.0) / rms)
    return jnp.clip(images + residual, 0.0, 1.0), stats


def training_source(cfg: DecoderTrainConfig) -> ImageSource:
    """The training images of a run: the training photographs, ``cfg.images_dir``, procedural images."""
    pool = load_photos(TRAIN_PHOTOS)
    if cfg.images_dir:
        pool += load_folder(cfg.images_dir)
    return ImageSource(pool, cfg.size + cfg.crop_margin, cfg.procedural_fraction)


# ------------------------------------------------------------------------------------------------------------
# Steps


def _augmenter(cfg: DecoderTrainConfig) -> Callable[[jax.Array, jax.Array], jax.Array]:
    from mnerf_jax import augment

    def apply(key: jax.Array, images: jax.Array) -> jax.Array:
        return augment.random_policy(
            key, images, strength=cfg.augment_strength, k=cfg.augment_k, p=cfg.augment_p
        )

    return apply


def _message_loss(logits: jax.Array, bits: jax.Array, temperature: float) -> jax.Array:
    from mnerf_jax import losses

    return losses.bce_with_logits(logits, bits, temperature=temperature)


def _bit_acc(logits: jax.Array, bits: jax.Array) -> jax.Array:
    return jnp.mean((logits > 0) == (bits > 0.5))


def _psnr(a: jax.Array, b: jax.Array) -> jax.Array:
    mse = jnp.mean((a - b) ** 2, axis=(-3, -2, -1))
    return jnp.mean(-10.0 * jnp.log10(jnp.maximum(mse, 1e-12)))


def random_windows(key: jax.Array, images: jax.Array, size: int) -> jax.Array:
    """A random ``size × size`` window of each image ``[B, H, W, C]`` (one offset per image).

    The decoder then never sees the encoder's image borders at a fixed place, so a watermark that leans on
    them (zero padding tells a small network where the border is) does not survive: the watermark has to be
    stationary, and it then decodes at any image size.
    """
    b, h, w, c = images.shape
    if (h, w) == (size, size):
        return images
    ky, kx = jax.random.split(key)
    ys = jax.random.randint(ky, (b,), 0, h - size + 1)
    xs = jax.random.randint(kx, (b,), 0, w - size + 1)
    crop = lambda image, y, x: jax.lax.dynamic_slice(image, (y, x, 0), (size, size, c))
    return jax.vmap(crop)(images, ys, xs)


def _all_finite(tree: Any) -> jax.Array:
    return jnp.all(jnp.stack([jnp.all(jnp.isfinite(leaf)) for leaf in jax.tree.leaves(tree)]))


def _unless_finite(grads: Any, new: dict[str, Any], old: dict[str, Any]) -> dict[str, Any]:
    """``new`` where every gradient is finite, else ``old`` (the step is skipped).

    A rare batch can give a non-finite gradient through an augmentation (seen once in a 16-bit run: Gaussian
    blur followed by the HSV saturation change); one such step must not poison the weights.
    """
    ok = _all_finite(grads)
    return jax.tree.map(lambda n, o: jnp.where(ok, n, o), new, old)


def _metrics(loss: jax.Array, aux: dict[str, Any], grads: Any) -> dict[str, jax.Array]:
    skipped = 1.0 - _all_finite(grads).astype(jnp.float32)
    return {"loss": loss, "acc": aux["acc"], "psnr": aux["psnr"], "skipped": skipped}


def make_joint_step(cfg: DecoderTrainConfig, tx: optax.GradientTransformation, augmented: bool) -> Callable:
    """Jitted joint step: ``(state, images, bits, key, psnr) → (state, metrics)``."""
    augment_fn = _augmenter(cfg) if augmented else None

    def loss_fn(params, state, images, bits, key, psnr):
        enc = {"params": params["encoder"], "batch_stats": state["encoder"]["batch_stats"]}
        encoded, enc_stats = encode(enc, images, bits, cfg, train=True, psnr=psnr)
        k_crop, k_aug = jax.random.split(key)
        seen = random_windows(k_crop, encoded, cfg.size)
        seen = augment_fn(k_aug, seen) if augment_fn is not None else seen
        dec_vars = {"params": params["decoder"], "batch_stats": state["decoder"]["batch_stats"]}
        logits, dec_stats = dec.apply_ll2_train(dec_vars, dwt.ll2(seen, cfg.wavelet))
        loss = _message_loss(logits, bits, cfg.temperature)
        aux = {
            "enc_stats": enc_stats,
            "dec_stats": dec_stats,
            "acc": _bit_acc(logits, bits),
            "psnr": _psnr(encoded, images),
        }
        return loss, aux

    def step(state, images, bits, key, psnr):
        params = {"encoder": state["encoder"]["params"], "decoder": state["decoder"]["params"]}
        (loss, aux), grads = jax.value_and_grad(loss_fn, has_aux=True)(params, state, images, bits, key, psnr)
        updates, opt = tx.update(grads, state["opt"], params)
        params = optax.apply_updates(params, updates)
        new = dict(state)
        new["encoder"] = {"params": params["encoder"], "batch_stats": aux["enc_stats"]}
        new["decoder"] = {"params": params["decoder"], "batch_stats": aux["dec_stats"]}
        new["opt"] = opt
        return _unless_finite(grads, new, state), _metrics(loss, aux, grads)

    return jax.jit(step, donate_argnums=0)


def make_finetune_step(cfg: DecoderTrainConfig, tx: optax.GradientTransformation) -> Callable:
    """Jitted encoder-only step through the frozen (eval-mode, whitened) decoder.

    Half of the steps see the augmented encoded images, unless the run never augments (``clean_fraction`` 1).
    """
    augment_fn = _augmenter(cfg) if cfg.clean_fraction < 1.0 else (lambda key, images: images)

    def loss_fn(enc_params, state, images, bits, key):
        enc = {"params": enc_params, "batch_stats": state["encoder"]["batch_stats"]}
        encoded, enc_stats = encode(enc, images, bits, cfg, train=True)
        k_apply, k_aug, k_crop = jax.random.split(key, 3)
        window = random_windows(k_crop, encoded, cfg.size)
        # Half the steps see the clean encoded image: the no-attack accuracy matters as much as robustness.
        seen = jnp.where(jax.random.uniform(k_apply) < 0.5, augment_fn(k_aug, window), window)
        logits = dec.apply_ll2(state["decoder"], dwt.ll2(seen, cfg.wavelet))
        loss = _message_loss(logits, bits, cfg.temperature)
        return loss, {"enc_stats": enc_stats, "acc": _bit_acc(logits, bits), "psnr": _psnr(encoded, images)}

    def step(state, images, bits, key, psnr):
        del psnr  # always the target
        enc_params = state["encoder"]["params"]
        (loss, aux), grads = jax.value_and_grad(loss_fn, has_aux=True)(enc_params, state, images, bits, key)
        updates, opt = tx.update(grads, state["opt_ft"], enc_params)
        new = dict(state)
        new["encoder"] = {"params": optax.apply_updates(enc_params, updates), "batch_stats": aux["enc_stats"]}
        new["opt_ft"] = opt
        return _unless_finite(grads, new, state), _metrics(loss, aux, grads)

    return jax.jit(step, donate_argnums=0)


def make_informed_step(cfg: DecoderTrainConfig, tx: optax.GradientTransformation) -> Callable:
    """Jitted decoder step against the informed encoder: ``(state, images, bits, key, psnr, augmented)``.

    The watermark is the decoder's own (train-mode) message gradient scaled to ``psnr`` dB
    (``informed.informed_embed``, one iteration); the decoder then reads the encoded images, through the
    augmentation layer where ``augmented`` is true, and both uses of the decoder are differentiated.
    """
    augment_fn = _augmenter(cfg)

    def loss_fn(params, state, images, bits, key, psnr, augmented):
        stats = state["decoder"]["batch_stats"]
        read = lambda x: dec.apply_ll2_train(
            {"params": params, "batch_stats": stats}, dwt.ll2(x, cfg.wavelet)
        )
        encoded = informed.informed_embed(lambda x: read(x)[0], images, bits, psnr)
        seen = jnp.where(augmented, augment_fn(key, encoded), encoded)
        logits, dec_stats = read(seen)
        loss = _message_loss(logits, bits, cfg.temperature)
        return loss, {"dec_stats": dec_stats, "acc": _bit_acc(logits, bits), "psnr": _psnr(encoded, images)}

    def step(state, images, bits, key, psnr, augmented):
        params = state["decoder"]["params"]
        (loss, aux), grads = jax.value_and_grad(loss_fn, has_aux=True)(
            params, state, images, bits, key, psnr, augmented
        )
        updates, opt = tx.update(grads, state["opt_inf"], params)
        new = dict(state)
        new["decoder"] = {"params": optax.apply_updates(params, updates), "batch_stats": aux["dec_stats"]}
        new["opt_inf"] = opt
        return _unless_finite(grads, new, state), _metrics(loss, aux, grads)

    return jax.jit(step, donate_argnums=0)


def informed_psnr(cfg: DecoderTrainConfig, step: int) -> float:
    """Residual strength at an informed step: ``informed_start_psnr`` rising linearly to ``target_psnr``."""
    span = cfg.anneal_fraction * cfg.informed_steps
    if step >= span or span <= 0 or cfg.informed_start_psnr >= cfg.target_psnr:
        return cfg.target_psnr
    return cfg.informed_start_psnr + (cfg.target_psnr - cfg.informed_start_psnr) * step / span


def informed_batch(cfg: DecoderTrainConfig, step: int) -> tuple[int, int]:
    """``(side, batch)`` of an informed step: the sides take turns, each batch holds about as many pixels."""
    side = cfg.informed_sizes[step % len(cfg.informed_sizes)]
    return side, max(1, round(cfg.batch * (cfg.size / side) ** 2))


def psnr_schedule(cfg: DecoderTrainConfig, step: int) -> float:
    """Residual strength (PSNR in dB) at a joint step: ``start_psnr`` rising linearly to ``target_psnr``."""
    span = cfg.anneal_fraction * cfg.steps
    if step >= span or span <= 0 or cfg.start_psnr >= cfg.target_psnr:
        return cfg.target_psnr
    return cfg.start_psnr + (cfg.target_psnr - cfg.start_psnr) * step / span


def make_optimizers(
    cfg: DecoderTrainConfig,
) -> tuple[optax.GradientTransformation, optax.GradientTransformation, optax.GradientTransformation]:
    """AdamW with linear warmup + cosine decay for the joint and for the informed steps, and a shorter
    cosine for the encoder fine-tuning."""

    def cosine(steps: int) -> optax.Schedule:
        warmup = min(cfg.warmup_steps, max(steps // 4, 1))
        return optax.warmup_cosine_decay_schedule(0.0, cfg.lr, warmup, max(steps, warmup + 1), cfg.lr * 0.01)

    ft_warm = max(min(50, cfg.finetune_steps // 5), 1)
    finetune = optax.warmup_cosine_decay_schedule(
        0.0, cfg.lr_finetune, ft_warm, max(cfg.finetune_steps, ft_warm + 1), cfg.lr_finetune * 0.01
    )
    make = lambda schedule: optax.chain(
        optax.clip_by_global_norm(1.0), optax.adamw(schedule, weight_decay=cfg.weight_decay)
    )
    return make(cosine(cfg.steps)), make(finetune), make(cosine(cfg.informed_steps))


def init_state(cfg: DecoderTrainConfig) -> tuple[dict[str, Any], tuple]:
    k_enc, k_dec = jax.random.split(jax.random.PRNGKey(cfg.seed))
    encoder = init_encoder(k_enc, cfg.bits, cfg.encoder_channels, cfg.encoder_depth)
    decoder = dec.init_decoder(k_dec, cfg.bits)
    tx_joint, tx_ft, tx_inf = make_optimizers(cfg)
    state = {
        "step": 0,
        "whitened": False,
        "elapsed_s": 0.0,
        "whitening_report": {"bit_acc_none_raw_decoder": 0.0, "bit_acc_none_whitened_before_finetune": 0.0},
        "encoder": encoder,
        "decoder": decoder,
        "opt": jax.jit(tx_joint.init)({"encoder": encoder["params"], "decoder": decoder["params"]}),
        "opt_ft": jax.jit(tx_ft.init)(encoder["params"]),
        "opt_inf": jax.jit(tx_inf.init)(decoder["params"]),
    }
    return state, (tx_joint, tx_ft, tx_inf)


# ------------------------------------------------------------------------------------------------------------
# Checkpoints (msgpack, no pickle; written to a temporary file and renamed)


def save_checkpoint(path: Path, state: dict[str, Any], cfg: DecoderTrainConfig) -> None:
    payload = {
        "config": json.dumps(cfg.to_dict(), sort_keys=True),
        "state": flax.serialization.to_state_dict(jax.device_get(state)),
    }
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(flax.serialization.msgpack_serialize(payload))
    os.replace(tmp, path)


def load_checkpoint(path: Path, template: dict[str, Any], cfg: DecoderTrainConfig) -> dict[str, Any]:
    try:
        payload = flax.serialization.msgpack_restore(path.read_bytes())
    except Exception as err:  # msgpack raises several unrelated types for damaged input
        raise MnerfError(
            f"checkpoint {path} is unreadable ({type(err).__name__}); delete it to start over"
        ) from None
    saved = json.loads(payload["config"])
    current = json.loads(json.dumps(cfg.trajectory()))  # tuples read back as lists
    diffs = [f"{k}: {saved.get(k)} -> {current[k]}" for k in sorted(current) if saved.get(k) != current[k]]
    if diffs:
        raise MnerfError(
            f"checkpoint {path} was written with other settings ({'; '.join(diffs[:3])}); "
            "use the same settings or another --out"
        )
    saved_state = dict(payload["state"])
    for name, value in flax.serialization.to_state_dict(template).items():
        saved_state.setdefault(name, value)  # fields added since the checkpoint was written
    state = flax.serialization.from_state_dict(template, saved_state)
    for name in ARRAY_KEYS:
        state[name] = jax.tree.map(jnp.asarray, state[name])
    state["step"] = int(state["step"])
    state["whitened"] = bool(state["whitened"])
    state["elapsed_s"] = float(state["elapsed_s"])
    state["whitening_report"] = {k: float(v) for k, v in state["whitening_report"].items()}
    return state


# ------------------------------------------------------------------------------------------------------------
# Evaluation


def evaluate(
    cfg: DecoderTrainConfig,
    enc_vars: dict[str, Any],
    dec_vars: dict[str, Any],
    images: np.ndarray,
    bits: np.ndarray,
    batch: int = 32,
) -> dict[str, float]:
    """Bit accuracy with no attack and under the augmentation policy (several draws), and PSNR, on a set."""
    draws = cfg.eval_augment_draws
    augment_fn = _augmenter(cfg) if draws > 0 else None

    # The variables are arguments, not closed-over constants (XLA would fold them at length).
    @jax.jit
    def run(enc_vars, dec_vars, x, m, key):
        encoded, _ = encode(enc_vars, x, m, cfg, train=False)
        clean = dec.apply_ll2(dec_vars, dwt.ll2(encoded, cfg.wavelet))
        acc_clean = jnp.mean((clean > 0) == (m > 0.5), axis=-1)
        if augment_fn is None:
            acc_low = jnp.full_like(acc_clean, jnp.nan)
        else:
            # lax.map, not vmap: a batched policy index would run every augmentation branch.
            attacked = jax.lax.map(
                lambda k: dec.apply_ll2(dec_vars, dwt.ll2(augment_fn(k, encoded), cfg.wavelet)),
                jax.random.split(key, draws),
            )
            acc_low = jnp.mean((attacked > 0) == (m > 0.5)[None], axis=(0, -1))
        mse = jnp.mean((encoded - x) ** 2, axis=(-3, -2, -1))
        return acc_clean, acc_low, -10.0 * jnp.log10(jnp.maximum(mse, 1e-12))

    acc_clean, acc_low, psnr = [], [], []
    for i in range(0, len(images), batch):
        a, b, p = run(
            enc_vars,
            dec_vars,
            jnp.asarray(images[i : i + batch]),
            jnp.asarray(bits[i : i + batch]),
            jax.random.fold_in(jax.random.PRNGKey(EVAL_SEED), i),
        )
        acc_clean.append(np.asarray(a))
        acc_low.append(np.asarray(b))
        psnr.append(np.asarray(p))
    acc_clean, acc_low, psnr = map(np.concatenate, (acc_clean, acc_low, psnr))
    low = float(acc_low.mean())
    return {
        "bit_acc_none": float(acc_clean.mean()),
        "bit_acc_low": None if math.isnan(low) else low,
        "psnr_mean": float(psnr.mean()),
        "psnr_min": float(psnr.min()),
        "images": int(len(images)),
        "informed": {
            f"{n}_iterations": evaluate_informed(cfg, dec_vars, images, bits, n, batch)
            for n in cfg.eval_informed_iterations
        },
    }


def evaluate_informed(
    cfg: DecoderTrainConfig,
    dec_vars: dict[str, Any],
    images: np.ndarray,
    bits: np.ndarray,
    iterations: int,
    batch: int = 32,
) -> dict[str, float | None]:
    """Bit accuracy (no attack, Low) and PSNR of informed embeddings (``informed.informed_embed``) of a set.

    This is how a radiance field carries the watermark (it follows the decoder's gradient), so these figures
    predict MultiNeRF's; the encoder's figures (``evaluate``) are the HiDDeN protocol.
    """
    draws = cfg.eval_augment_draws
    augment_fn = _augmenter(cfg)

    @jax.jit
    def run(dec_vars, x, m, key):
        read = lambda y: dec.apply_ll2(dec_vars, dwt.ll2(y, cfg.wavelet))
        encoded = informed.informed_embed(read, x, m, cfg.target_psnr, iterations)
        acc_clean = jnp.mean((read(encoded) > 0) == (m > 0.5), axis=-1)
        attacked = jax.lax.map(lambda k: read(augment_fn(k, encoded)), jax.random.split(key, max(draws, 1)))
        acc_low = jnp.mean((attacked > 0) == (m > 0.5)[None], axis=(0, -1))
        mse = jnp.mean((encoded - x) ** 2, axis=(-3, -2, -1))
        return acc_clean, acc_low, -10.0 * jnp.log10(jnp.maximum(mse, 1e-12))

    parts = [
        run(
            dec_vars,
            jnp.asarray(images[i : i + batch]),
            jnp.asarray(bits[i : i + batch]),
            jax.random.fold_in(jax.random.PRNGKey(EVAL_SEED), i),
        )
        for i in range(0, len(images), batch)
    ]
    acc_clean, acc_low, psnr = (np.concatenate([np.asarray(p[j]) for p in parts]) for j in range(3))
    return {
        "bit_acc_none": float(acc_clean.mean()),
        "bit_acc_low": float(acc_low.mean()) if draws > 0 else None,
        "psnr_mean": float(psnr.mean()),
        "psnr_min": float(psnr.min()),
    }


def encode_batch(
    cfg: DecoderTrainConfig, enc_vars: dict[str, Any], images: np.ndarray, bits: np.ndarray
) -> np.ndarray:
    """Encoded images as float32 in [0, 1] (eval mode)."""
    return np.asarray(_encode_eval(enc_vars, jnp.asarray(images), jnp.asarray(bits), cfg))


@functools.partial(jax.jit, static_argnames=("cfg",))
def _encode_eval(
    enc_vars: dict[str, Any], images: jax.Array, bits: jax.Array, cfg: DecoderTrainConfig
) -> jax.Array:
    return encode(enc_vars, images, bits, cfg)[0]


# ------------------------------------------------------------------------------------------------------------
# The run


def _batches(
    cfg: DecoderTrainConfig, source: ImageSource, start: int, stop: int
) -> Iterator[tuple[int, str, np.ndarray, np.ndarray]]:
    """``(step, stage, images, bits)`` for steps ``start..stop-1``; stage is informed, joint or finetune."""
    informed_sources: dict[int, ImageSource] = {}
    for step in range(start, stop):
        rng = np.random.default_rng([cfg.seed, step])
        if step < cfg.informed_steps:
            side, batch = informed_batch(cfg, step)
            if side not in informed_sources:
                informed_sources[side] = ImageSource(source.pool, side, cfg.procedural_fraction)
            images, stage = informed_sources[side].sample(rng, batch), "informed"
        else:
            batch = cfg.batch
            stage = "joint" if step < cfg.informed_steps + cfg.steps else "finetune"
            images = source.sample(rng, batch)
        bits = rng.integers(0, 2, size=(batch, cfg.bits)).astype(np.float32)
        yield step, stage, images, bits


def _machine() -> str:
    cpu = f"{platform.machine()} {platform.processor() or ''}".strip()
    return f"{cpu}, {os.cpu_count()} CPU cores, JAX {jax.__version__} on {jax.default_backend()}"


def train_decoder(
    cfg: DecoderTrainConfig,
    out_dir: str | Path,
    resume: bool = False,
    progress: bool = True,
    checkpoint_every: int = 250,
    log: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """Run the whole recipe into ``out_dir``; returns the metrics (also written to ``out_dir/metrics.json``).

    Writes ``decoder.npz`` (whitened; the metadata records the config, wall time and held-out figures),
    ``encoder.npz``, ``check.npz`` (a small fixed batch of encoded held-out images as uint8, their messages
    and the decoder's accuracy on them), ``metrics.json``, ``log.jsonl`` and ``checkpoint.msgpack``.
    """
    from tqdm import tqdm

    if cfg.bits not in dec.SUPPORTED_BITS:
        raise MnerfError(f"--bits must be one of {', '.join(map(str, dec.SUPPORTED_BITS))}, got {cfg.bits}")
    if cfg.size % 4 or cfg.size < 16:
        raise MnerfError(f"--size must be a multiple of 4 and at least 16, got {cfg.size}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    ckpt = out / "checkpoint.msgpack"
    log = log or (lambda line: None)
    state, (tx_joint, tx_ft, tx_inf) = init_state(cfg)
    if resume and ckpt.is_file():
        state = load_checkpoint(ckpt, state, cfg)
        log(f"resumed from {ckpt} at step {state['step']}")
    elif ckpt.is_file() and not resume:
        raise MnerfError(f"{ckpt} exists; pass --resume to continue that run or choose another --out")

    source = training_source(cfg)
    eval_images = heldout_images(cfg.eval_images, cfg.size)
    eval_bits = heldout_messages(cfg.eval_images, cfg.bits)
    total = cfg.informed_steps + cfg.steps + cfg.finetune_steps
    clean_steps = int(round(cfg.clean_fraction * cfg.steps))
    clean_informed = int(round(cfg.clean_fraction * cfg.informed_steps))
    steps_fns: dict[str, Callable] = {}
    started = time.time()
    elapsed0 = float(state["elapsed_s"])
    history = open(out / "log.jsonl", "a")

    def record(entry: dict[str, Any]) -> None:
        history.write(json.dumps(entry) + "\n")
        history.flush()

    def checkpoint() -> None:
        state["elapsed_s"] = elapsed0 + time.time() - started
        save_checkpoint(ckpt, state, cfg)

    bar = tqdm(
        total=total,
        initial=int(state["step"]),
        disable=not progress,
        dynamic_ncols=True,
        desc=f"train-decoder L={cfg.bits}",
    )
    try:
        running: dict[str, float] = {}
        skipped = 0
        for step, stage, images, bits in _batches(cfg, source, int(state["step"]), total):
            extra: tuple = (jnp.float32(psnr_schedule(cfg, max(step - cfg.informed_steps, 0))),)
            if stage == "informed":
                if "informed" not in steps_fns:
                    steps_fns["informed"] = make_informed_step(cfg, tx_inf)
                fn = steps_fns["informed"]
                extra = (jnp.float32(informed_psnr(cfg, step)), jnp.bool_(step >= clean_informed))
            elif stage == "joint":
                phase = "clean" if step - cfg.informed_steps < clean_steps else "augmented"
                if phase not in steps_fns:
                    steps_fns[phase] = make_joint_step(cfg, tx_joint, augmented=phase == "augmented")
                fn = steps_fns[phase]
            else:
                if not state["whitened"]:
                    state["whitening_report"] = whiten_state(cfg, state, source, eval_images, eval_bits)
                    record({"step": step, "event": "whitened", **state["whitening_report"]})
                    log(f"step {step}: whitening fitted {state['whitening_report']}")
                    checkpoint()
                if "finetune" not in steps_fns:
                    steps_fns["finetune"] = make_finetune_step(cfg, tx_ft)
                fn = steps_fns["finetune"]
            key = jax.random.fold_in(jax.random.PRNGKey(cfg.seed + 1), step)
            arrays, metrics = fn(
                {k: state[k] for k in ARRAY_KEYS},
                jnp.asarray(images),
                jnp.asarray(bits),
                key,
                *extra,
            )
            state.update(arrays)
            state["step"] = step + 1
            values = {k: float(v) for k, v in metrics.items()}
            skipped = skipped + 1 if values.pop("skipped") else 0
            if skipped:
                record({"step": step, "event": "skipped (non-finite gradient)", "loss": values["loss"]})
                if skipped >= MAX_SKIPPED:
                    raise MnerfError(
                        f"training diverged at step {step}: {skipped} steps in a row had non-finite gradients"
                        " (the last checkpoint is kept; try a lower learning rate)"
                    )
            else:
                running = {k: 0.9 * running.get(k, v) + 0.1 * v for k, v in values.items()}
            bar.update(1)
            if step % 10 == 0:
                bar.set_postfix(
                    loss=f"{running['loss']:.3f}", acc=f"{running['acc']:.3f}", psnr=f"{running['psnr']:.1f}"
                )
            if (step + 1) % checkpoint_every == 0 or step + 1 == total:
                record({"step": step + 1, **running, "elapsed_s": elapsed0 + time.time() - started})
                checkpoint()
        if not state["whitened"]:  # finetune_steps == 0
            state["whitening_report"] = whiten_state(cfg, state, source, eval_images, eval_bits)
            checkpoint()
    finally:
        bar.close()
        history.close()
    wall = elapsed0 + time.time() - started
    return finish(cfg, state, out, wall)


def _clean_accuracy(
    cfg: DecoderTrainConfig,
    enc_vars: dict[str, Any],
    dec_vars: dict[str, Any],
    images: np.ndarray,
    bits: np.ndarray,
) -> float:
    encoded = encode_batch(cfg, enc_vars, images, bits)
    logits = dec.decode_logits(dec_vars, jnp.asarray(encoded), cfg.wavelet)
    return float(jnp.mean((logits > 0) == (jnp.asarray(bits) > 0.5)))


def whiten_state(
    cfg: DecoderTrainConfig,
    state: dict[str, Any],
    source: ImageSource,
    eval_images: np.ndarray,
    eval_bits: np.ndarray,
) -> dict[str, float]:
    """Fit the whitening on clean training crops (a fixed draw) and mark the state whitened.

    Returns the held-out no-attack accuracy of the current encoder through the decoder before and after
    whitening (the second is typically near chance: the encoder has not been fine-tuned yet).
    """
    before = _clean_accuracy(cfg, state["encoder"], state["decoder"], eval_images, eval_bits)
    rng = np.random.default_rng([cfg.seed, 1_000_000_007])
    batches = []
    n = cfg.whiten_images
    for i in range(0, n, 64):
        images = source.sample(rng, min(64, n - i))[:, : cfg.size, : cfg.size]
        batches.append(dwt.ll2(jnp.asarray(images), cfg.wavelet))
    state["decoder"] = dec.fit_whitening(state["decoder"], batches)
    state["whitened"] = True
    after = _clean_accuracy(cfg, state["encoder"], state["decoder"], eval_images, eval_bits)
    return {"bit_acc_none_raw_decoder": before, "bit_acc_none_whitened_before_finetune": after}


def evaluate_sizes(
    cfg: DecoderTrainConfig, enc_vars: dict[str, Any], dec_vars: dict[str, Any]
) -> dict[str, Any]:
    """Held-out figures at every side in ``cfg.eval_sizes``: ``{"64px": {...}, "256px": {...}}``."""
    out = {}
    for size in cfg.eval_sizes:
        images = heldout_images(cfg.eval_images, size)
        out[f"{size}px"] = evaluate(
            cfg, enc_vars, dec_vars, images, heldout_messages(cfg.eval_images, cfg.bits)
        )
    return out


def finish(cfg: DecoderTrainConfig, state: dict[str, Any], out: Path, wall: float) -> dict[str, Any]:
    """Evaluate on the held-out sets, write decoder/encoder/check files and metrics.json."""
    enc_vars, dec_vars = state["encoder"], state["decoder"]
    heldout = evaluate_sizes(cfg, enc_vars, dec_vars)
    # The check batch: encoded held-out images quantised to 8 bits, as a saved PNG would hold them.
    check_size = max(cfg.eval_sizes) if max(cfg.eval_sizes) <= 128 else 128
    check_bits = heldout_messages(cfg.check_images, cfg.bits)
    check_images = encode_batch(cfg, enc_vars, heldout_images(cfg.check_images, check_size), check_bits)
    check_images = np.round(check_images * 255.0).astype(np.uint8)
    check_logits = dec.decode_logits(dec_vars, jnp.asarray(check_images, jnp.float32) / 255.0, cfg.wavelet)
    check_acc = float(jnp.mean((check_logits > 0) == (jnp.asarray(check_bits) > 0.5)))
    training = {
        "recipe": "mnerf train-decoder",
        "config": cfg.to_dict(),
        "wall_time_s": round(wall, 1),
        "machine": _machine(),
        "steps": cfg.steps + cfg.finetune_steps,
    }
    evaluation = {
        "heldout": heldout,
        "check_batch_bit_acc": check_acc,
        "check_batch_size": check_size,
        "whitening": {k: float(v) for k, v in state.get("whitening_report", {}).items()},
    }
    meta = dec.save_decoder(
        out / "decoder.npz",
        dec_vars,
        {"whitened": True, "training": training, "eval": evaluation},
        wavelet=cfg.wavelet,
    )
    metrics = {
        "bits": cfg.bits,
        "decoder": "whitened",
        "fingerprint": meta["fingerprint"],
        **training,
        **evaluation,
    }
    flat = dec._flatten({"params": enc_vars["params"], "batch_stats": enc_vars["batch_stats"]})
    np.savez_compressed(
        out / "encoder.npz",
        **{k: np.asarray(v, np.float32) for k, v in flat.items()},
        __metadata__=np.frombuffer(json.dumps({"config": cfg.to_dict()}).encode(), np.uint8),
    )
    np.savez_compressed(
        out / "check.npz",
        images=check_images,
        bits=check_bits.astype(np.uint8),
        bit_acc=np.float64(check_acc),
    )
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2, sort_keys=True))
    return metrics


def load_encoder(path: str | Path) -> tuple[dict[str, Any], DecoderTrainConfig]:
    """The encoder variables and the training config from an ``encoder.npz`` written by a run."""
    arrays, meta = {}, {}
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {name: np.array(data[name]) for name in data.files}
        meta = json.loads(arrays.pop("__metadata__").tobytes().decode())
    except (OSError, ValueError, KeyError) as err:
        raise MnerfError(f"encoder file {path} is unreadable ({err})") from None
    known = {f.name for f in dataclasses.fields(DecoderTrainConfig)}
    values = {k: tuple(v) if isinstance(v, list) else v for k, v in meta["config"].items() if k in known}
    return jax.tree.map(jnp.asarray, dec._unflatten(arrays)), DecoderTrainConfig(**values)
