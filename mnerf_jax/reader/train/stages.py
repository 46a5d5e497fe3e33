"""Training a HiDDeN watermark decoder (and the encoder that teaches it), then PCA-whitening it.

Recipe (CPU-sized; every step is one jitted function over a small batch of crops):

0. **Decoder start** (``decoder_init``): ``filterbank`` (``decoder.filterbank_init``: signed 3×3 DCT
   patterns on opponent colours in the first block, the middle blocks near identity) or ``random``.
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
4. **Encoder training** (``finetune_steps``) through the whitened decoder (whitening rotates the
   logits, so an encoder from stage 2 has to re-fit; after stage 1 alone the encoder learns here from
   scratch). The decoder is frozen, or with ``finetune_decoder_lr`` learns too after
   ``finetune_decoder_start`` of the steps (HiDDeN's joint training from a decoder that already reads); its
   whitening rotation stays and its offset and scale are re-fitted on clean crops at the end.
5. **Evaluation** on held-out crops (photographs and procedural images never used in training): bit accuracy
   of the encoder's images and of informed embeddings, with no attack and under the Low policy, and PSNR.

Images come from ``decoder_images``. Every step's batch is drawn from
``numpy.random.default_rng([seed, step])``, so a resumed run sees the same data as an uninterrupted one.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax

from mnerf_jax.core import machine
from mnerf_jax.core.errors import MnerfError
from mnerf_jax.reader import decoder as dec
from mnerf_jax.reader import decoder_io, dwt
from mnerf_jax.reader.train.checkpoint import ARRAY_KEYS, load_checkpoint, save_checkpoint
from mnerf_jax.reader.train.cover_images import ImageSource, heldout_images, heldout_messages
from mnerf_jax.reader.train.evaluation import clean_accuracy, evaluate_sizes, reader
from mnerf_jax.reader.train.hidden_encoder import encode_batch, init_encoder, load_encoder, save_encoder
from mnerf_jax.reader.train.recipe import (
    DecoderTrainConfig,
    finetune_decoder_start_step,
    finetune_sides,
    informed_batch,
    informed_psnr,
    psnr_schedule,
    side_and_batch,
    training_source,
)
from mnerf_jax.reader.train.steps import make_finetune_step, make_informed_step, make_joint_step

MAX_SKIPPED = 20  # consecutive steps with non-finite gradients before a run is declared diverged


def make_optimizers(cfg: DecoderTrainConfig) -> tuple[optax.GradientTransformation, ...]:
    """AdamW with linear warmup + cosine decay for the joint and for the informed steps, a shorter cosine
    for the encoder fine-tuning, and one for the decoder over the fine-tuning steps it learns in (all clipped
    at global norm 1): ``(joint, finetune, informed, finetune decoder)``."""

    def cosine(steps: int) -> optax.Schedule:
        warmup = min(cfg.warmup_steps, max(steps // 4, 1))
        return optax.warmup_cosine_decay_schedule(0.0, cfg.lr, warmup, max(steps, warmup + 1), cfg.lr * 0.01)

    def short_cosine(peak: float, steps: int) -> optax.Schedule:
        warm = max(min(50, steps // 5), 1)
        return optax.warmup_cosine_decay_schedule(0.0, peak, warm, max(steps, warm + 1), peak * 0.01)

    make = lambda schedule: optax.chain(
        optax.clip_by_global_norm(1.0), optax.adamw(schedule, weight_decay=cfg.weight_decay)
    )
    decoder_steps = cfg.finetune_steps - finetune_decoder_start_step(cfg)
    return (
        make(cosine(cfg.steps)),
        make(short_cosine(cfg.lr_finetune, cfg.finetune_steps)),
        make(cosine(cfg.informed_steps)),
        make(short_cosine(cfg.finetune_decoder_lr, decoder_steps)),
    )


def decoder_from_file(cfg: DecoderTrainConfig) -> dict[str, Any]:
    """The whitened decoder of ``cfg.decoder_from``, checked against the run's bits, wavelet and pool."""
    loaded = decoder_io.load_decoder(cfg.decoder_from, expect_bits=cfg.bits)
    if not loaded.metadata.get("whitened", False):
        raise MnerfError(f"--decoder-from {cfg.decoder_from}: the decoder is not whitened")
    if loaded.wavelet != cfg.wavelet:
        raise MnerfError(
            f"--decoder-from {cfg.decoder_from} reads the {loaded.wavelet} LL2, the run uses {cfg.wavelet}"
        )
    if dec.pool_margin(loaded.variables) != cfg.pool_margin:
        raise MnerfError(
            f"--decoder-from {cfg.decoder_from} pools with margin {dec.pool_margin(loaded.variables)}; "
            f"pass --pool-margin {dec.pool_margin(loaded.variables)}"
        )
    return dict(jax.tree.map(jnp.asarray, loaded.variables))


def encoder_from_file(cfg: DecoderTrainConfig) -> dict[str, Any]:
    """The encoder of ``cfg.encoder_from``, checked against the run's bits and architecture."""
    encoder, saved = load_encoder(cfg.encoder_from)
    ours = (cfg.bits, cfg.encoder_channels, cfg.encoder_depth)
    theirs = (saved.bits, saved.encoder_channels, saved.encoder_depth)
    if theirs != ours:
        raise MnerfError(
            f"--encoder-from {cfg.encoder_from} is a {theirs[0]}-bit encoder of {theirs[1]} channels and "
            f"depth {theirs[2]}; the run's is {ours[0]}-bit, {ours[1]} channels, depth {ours[2]}"
        )
    return dict(encoder)


def init_state(cfg: DecoderTrainConfig) -> tuple[dict[str, Any], tuple]:
    k_enc, k_dec = jax.random.split(jax.random.PRNGKey(cfg.seed))
    if cfg.encoder_from:
        encoder = encoder_from_file(cfg)
    else:
        encoder = init_encoder(k_enc, cfg.bits, cfg.encoder_channels, cfg.encoder_depth)
    if cfg.decoder_from:
        decoder = decoder_from_file(cfg)
    else:
        decoder = dec.init_decoder(k_dec, cfg.bits)
        if cfg.decoder_init == "filterbank":
            decoder = dec.filterbank_init(decoder)
        decoder = dec.with_pool_margin(decoder, cfg.pool_margin)
    tx_joint, tx_ft, tx_inf, tx_ft_dec = make_optimizers(cfg)
    state = {
        "step": 0,
        "whitened": bool(cfg.decoder_from),
        "elapsed_s": 0.0,
        "whitening_report": {"bit_acc_none_raw_decoder": 0.0, "bit_acc_none_whitened_before_finetune": 0.0},
        "encoder": encoder,
        "decoder": decoder,
        "opt": jax.jit(tx_joint.init)({"encoder": encoder["params"], "decoder": decoder["params"]}),
        "opt_ft": jax.jit(tx_ft.init)(encoder["params"]),
        "opt_inf": jax.jit(tx_inf.init)(decoder["params"]),
        "opt_ft_dec": jax.jit(tx_ft_dec.init)(decoder["params"]),
    }
    return state, (tx_joint, tx_ft, tx_inf, tx_ft_dec)


# ------------------------------------------------------------------------------------------------------------
# The run


def _batches(
    cfg: DecoderTrainConfig, source: ImageSource, start: int, stop: int
) -> Iterator[tuple[int, str, np.ndarray, np.ndarray]]:
    """``(step, stage, images, bits)`` for steps ``start..stop-1``; stage is informed, joint or finetune."""
    sources: dict[int, ImageSource] = {cfg.size + cfg.crop_margin: source}

    def sample(rng: np.random.Generator, side: int, batch: int) -> np.ndarray:
        if side not in sources:
            sources[side] = ImageSource(source.pool, side, cfg.procedural_fraction)
        return sources[side].sample(rng, batch)

    for step in range(start, stop):
        rng = np.random.default_rng([cfg.seed, step])
        if step < cfg.informed_steps:
            side, batch = informed_batch(cfg, step)
            images, stage = sample(rng, side + cfg.informed_margin, batch), "informed"
        elif step < cfg.informed_steps + cfg.steps:
            batch, stage = cfg.batch, "joint"
            images = source.sample(rng, batch)
        else:
            stage_step = step - cfg.informed_steps - cfg.steps
            side, batch = side_and_batch(cfg, finetune_sides(cfg), stage_step, cfg.read_side)
            images, stage = sample(rng, side + cfg.crop_margin, batch), "finetune"
        bits = rng.integers(0, 2, size=(batch, cfg.bits)).astype(np.float32)
        yield step, stage, images, bits


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
    if cfg.decoder_init not in dec.DECODER_INITS:
        choices = ", ".join(dec.DECODER_INITS)
        raise MnerfError(f"--decoder-init must be one of {choices}, got {cfg.decoder_init!r}")
    if cfg.size % 4 or cfg.size < 16:
        raise MnerfError(f"--size must be a multiple of 4 and at least 16, got {cfg.size}")
    if cfg.encoder_channels < 1 or cfg.encoder_depth < 0:
        raise MnerfError(
            f"--encoder-channels must be ≥ 1 and --encoder-depth ≥ 0, got {cfg.encoder_channels}"
            f" and {cfg.encoder_depth}"
        )
    if cfg.decoder_from and (cfg.informed_steps or cfg.steps):
        raise MnerfError(
            "--decoder-from trains an encoder for a finished decoder: pass --informed-steps 0 --steps 0"
        )
    smallest = min(cfg.size, *cfg.informed_sizes) if cfg.informed_steps else cfg.size
    smallest = min(smallest, *finetune_sides(cfg))
    if cfg.pool_margin < 0 or (cfg.pool_margin and smallest // 4 <= 2 * cfg.pool_margin):
        raise MnerfError(
            f"--pool-margin {cfg.pool_margin} leaves no positions to pool in {smallest}-px training images "
            f"(the LL2 side, {smallest // 4}, must exceed twice the margin; raise --size / --informed-sizes)"
        )
    if cfg.encoder_from and not cfg.decoder_from:
        raise MnerfError("--encoder-from refits an encoder for a finished decoder: pass --decoder-from too")
    if cfg.decoder_from:
        decoder_from_file(cfg)  # a wrong file fails here, before anything is written
    if cfg.encoder_from:
        encoder_from_file(cfg)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    ckpt = out / "checkpoint.msgpack"
    log = log or (lambda line: None)
    if ckpt.is_file() and not resume:
        raise MnerfError(f"{ckpt} exists; pass --resume to continue that run or choose another --out")
    state, (tx_joint, tx_ft, tx_inf, tx_ft_dec) = init_state(cfg)
    if resume and ckpt.is_file():
        state = load_checkpoint(ckpt, state, cfg)
        log(f"resumed from {ckpt} at step {state['step']}")

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
            if stage == "informed":
                phase = "informed, augmented" if step >= clean_informed else "informed, clean"
                if phase not in steps_fns:
                    steps_fns[phase] = make_informed_step(cfg, tx_inf, augmented=phase.endswith("augmented"))
                fn, psnr = steps_fns[phase], informed_psnr(cfg, step)
            elif stage == "joint":
                phase = "clean" if step - cfg.informed_steps < clean_steps else "augmented"
                if phase not in steps_fns:
                    steps_fns[phase] = make_joint_step(cfg, tx_joint, augmented=phase == "augmented")
                fn, psnr = steps_fns[phase], psnr_schedule(cfg, step - cfg.informed_steps)
            else:
                if not state["whitened"]:
                    state["whitening_report"] = whiten_state(cfg, state, source, eval_images, eval_bits)
                    record({"step": step, "event": "whitened", **state["whitening_report"]})
                    log(f"step {step}: whitening fitted {state['whitening_report']}")
                    checkpoint()
                ft_step = step - cfg.informed_steps - cfg.steps
                learns = ft_step >= finetune_decoder_start_step(cfg)
                phase = "finetune, decoder" if learns else "finetune"
                if phase not in steps_fns:
                    steps_fns[phase] = make_finetune_step(cfg, tx_ft, tx_ft_dec if learns else None)
                fn, psnr = steps_fns[phase], cfg.target_psnr
            key = jax.random.fold_in(jax.random.PRNGKey(cfg.seed + 1), step)
            arrays, metrics = fn(
                {k: state[k] for k in ARRAY_KEYS},
                jnp.asarray(images),
                jnp.asarray(bits),
                key,
                jnp.float32(psnr),
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
        if decoder_learned(cfg) and "recentred_max_abs_mean" not in state["whitening_report"]:
            state["whitening_report"].update(recentre_state(cfg, state, source))
            record({"step": total, "event": "whitening re-centred", **state["whitening_report"]})
            checkpoint()
    finally:
        bar.close()
        history.close()
    wall = elapsed0 + time.time() - started
    return finish(cfg, state, out, wall)


def decoder_learned(cfg: DecoderTrainConfig) -> bool:
    """Whether stage 4 trained the decoder (then its whitening offset and scale are re-fitted at the end)."""
    return finetune_decoder_start_step(cfg) < cfg.finetune_steps  # the whole stage when the rate is 0


def whitening_batches(cfg: DecoderTrainConfig, source: ImageSource) -> list[jax.Array]:
    """LL2 sub-bands of the clean training crops the whitening is fitted on (a fixed draw)."""
    rng = np.random.default_rng([cfg.seed, 1_000_000_007])
    batches = []
    n = cfg.whiten_images
    for i in range(0, n, 64):
        images = source.sample(rng, min(64, n - i))[:, : cfg.size, : cfg.size]
        batches.append(dwt.ll2(jnp.asarray(images), cfg.wavelet))
    return batches


def recentre_state(cfg: DecoderTrainConfig, state: dict[str, Any], source: ImageSource) -> dict[str, float]:
    """Re-centre and re-scale the whitening of a decoder that learned in stage 4
    (``decoder.recentre_whitening``) on the whitening's clean crops; returns how far the clean logits had
    drifted from white."""
    state["decoder"], report = dec.recentre_whitening(state["decoder"], whitening_batches(cfg, source))
    return {f"recentred_{k}": v for k, v in report.items()}


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
    before = clean_accuracy(cfg, state["encoder"], state["decoder"], eval_images, eval_bits)
    batches = whitening_batches(cfg, source)
    state["decoder"] = dec.fit_whitening(state["decoder"], batches)
    state["whitened"] = True
    after = clean_accuracy(cfg, state["encoder"], state["decoder"], eval_images, eval_bits)
    return {"bit_acc_none_raw_decoder": before, "bit_acc_none_whitened_before_finetune": after}


def finish(cfg: DecoderTrainConfig, state: dict[str, Any], out: Path, wall: float) -> dict[str, Any]:
    """Evaluate on the held-out sets, write decoder/encoder/check files and metrics.json."""
    enc_vars, dec_vars = state["encoder"], state["decoder"]
    heldout = evaluate_sizes(cfg, enc_vars, dec_vars)
    # The check batch: encoded held-out images quantised to 8 bits, as a saved PNG would hold them.
    check_size = max(cfg.eval_sizes) if max(cfg.eval_sizes) <= 128 else 128
    check_bits = heldout_messages(cfg.check_images, cfg.bits)
    check_images = encode_batch(
        cfg, enc_vars, heldout_images(cfg.check_images, check_size), check_bits, cfg.read_side
    )
    check_images = np.round(check_images * 255.0).astype(np.uint8)
    check_logits = reader(cfg, dec_vars, cfg.read_side)(jnp.asarray(check_images, jnp.float32) / 255.0)
    check_acc = float(jnp.mean((check_logits > 0) == (jnp.asarray(check_bits) > 0.5)))
    this_run = {
        "recipe": "mnerf train-decoder",
        "config": cfg.to_dict(),
        "wall_time_s": round(wall, 1),
        "machine": machine.describe(),
        "steps": cfg.steps + cfg.finetune_steps,
    }
    training = this_run
    if cfg.decoder_from:  # the decoder is the file's (perhaps trained on): keep its record, add this run's
        original = decoder_io.load_decoder(cfg.decoder_from, expect_bits=cfg.bits).metadata
        stage = "joint_refit" if decoder_learned(cfg) else "encoder_refit"
        training = {**original.get("training", {}), stage: this_run}
    evaluation = {
        "heldout": heldout,
        "check_batch_bit_acc": check_acc,
        "check_batch_size": check_size,
        "whitening": {k: float(v) for k, v in state.get("whitening_report", {}).items()},
    }
    meta = decoder_io.save_decoder(
        out / "decoder.npz",
        dec_vars,
        {"whitened": True, "training": training, "eval": evaluation},
        wavelet=cfg.wavelet,
    )
    metrics = {
        "bits": cfg.bits,
        "decoder": "whitened",
        "fingerprint": meta["fingerprint"],
        **this_run,  # the decoder file's metadata holds the whole record
        **evaluation,
    }
    save_encoder(out / "encoder.npz", enc_vars, cfg)
    np.savez_compressed(
        out / "check.npz",
        images=check_images,
        bits=check_bits.astype(np.uint8),
        bit_acc=np.float64(check_acc),
    )
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2, sort_keys=True))
    return metrics
