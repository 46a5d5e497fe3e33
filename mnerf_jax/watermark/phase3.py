"""Phase 3 of ``mnerf embed`` (not in the paper): the decoder alone, refitted on the finished field's renders.

In phase 2 the decoder learns one view per step, from renders that keep changing under it. Once the field is
fixed, every training view rendered with every ID is a labelled set of exactly the images the decoder will be
given, and a decoder step on it costs a fraction of a field step (no render, no back-propagation into the
field). Phase 3 renders that set once (``watermark.phase3.views`` more views around the training cameras: on
their sphere for object-centred scenes, on the spiral render path for forward-facing ones), then trains the
decoder's weights alone on it: the message BCE and the key term of phase 2 on every render, and
``phase3_lambda_clean`` · BCE against the null word (``keys.null_message``, far from every key) on
unwatermarked 8-bit images under attack (the training views' photographs, the clean model's renders of
every view used, and a third as many images from outside the scene); half of the renders are rounded to 8
bits as a saved PNG is, and the run's phase-2 augmentations apply to them when it has them. With
``phase3.attacked`` that share of the renders and of the negatives is read after real attacks instead
(codecs, noise, colour, blur, warps; ``imaging.training_attacks``), each image's drawn once when the set is
rendered: no gradient passes through an image here, so the attacks need not be differentiable. With
``phase3.negative_noise`` a quarter of the negatives also carry Gaussian noise up to that σ. The field,
and so the PSNR, does not change (results: docs/experiments/).
"""

from __future__ import annotations

import functools
import time
from collections.abc import Callable
from typing import Any

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np
import optax
from tqdm.auto import tqdm

from mnerf_jax.core import xla_cpu
from mnerf_jax.core.watermark_config import AugmentConfig, WatermarkConfig
from mnerf_jax.data.types import Cameras
from mnerf_jax.imaging import attacks, augment, losses, training_attacks
from mnerf_jax.reader import decoder as decoder_lib
from mnerf_jax.reader import dwt, read_window
from mnerf_jax.reader import keys as keys_lib
from mnerf_jax.reader.train import cover_images
from mnerf_jax.tensorf import run as runs
from mnerf_jax.watermark import model as watermark
from mnerf_jax.watermark import run as wm_run
from mnerf_jax.watermark import time_budget as embed_budget
from mnerf_jax.watermark.novel_views import novel_cameras

PyTree = Any
# A batch holds phase3_batch renders and a quarter as many unwatermarked images (8 per 32, as in the sweep of
# docs/experiments/).
NEGATIVES_PER_BATCH_DIVISOR = 4


# Under a time budget, the share of the time left at phase 3's start that rendering its novel views may take
# (the rest is the decoder's): past it no further chunk of them is rendered.
NOVEL_VIEWS_SHARE = 0.5
# Views rendered (every ID) and reduced to what the decoder reads at a time: the full-size renders held.
VIEWS_PER_CHUNK = 8
# Images from outside the scene among the negatives, per scene negative: a decoder refitted on one scene's
# images alone reads photographs and textures as keys the longer it trains (docs/experiments/).
GENERIC_PER_SCENE_NEGATIVE = 1 / 3
GENERIC_SEED = 0x6E6E  # their draw: fixed, and apart from the false-claims measurement's
ATTACK_STREAM = 0xA77  # the real attacks' draws (phase3.attacked), apart from the novel views' stream
NOISE_STREAM = 0xB01  # the noisy negatives' draws (phase3.negative_noise): the other draws stay as they were
# The share of the negatives given phase3.negative_noise's noise: enough to cover its range every step, most
# left to the attack policy.
NOISY_NEGATIVES_SHARE = 0.25


@flax.struct.dataclass
class RefitSet:
    """What phase 3 trains on.

    Attributes:
      renders: ``[N, V, H, W, 3]`` float32 in [0, 1], view ``v`` rendered with ID ``n``; ``compact``:
        ``[N, V, 2, S, S', 3]``, what the decoder reads of each (:func:`reads_of`).
      messages: ``[N, L]`` 0/1, each ID's key.
      negatives: ``[G, H, W, 3]`` uint8, unwatermarked images as a verifier receives them (8-bit), kept whole
        in either layout: each step attacks them (:func:`negative_attacks`) before reading them.
      null: ``[L]`` 0/1, the word the negatives are decoded against (``keys.null_message`` of the keys).
      compact: the images are kept as their reads (:func:`keeps_reads_only`), not as images.
      attacked: ``[N, V, S, S', 3]`` float16, what the decoder reads of each render after a real attack
        (:func:`attacked_reads`), or None (``phase3.attacked`` 0).
      attacked_negatives: ``[G, S, S', 3]`` float16, the same of each negative, or None.
    """

    renders: Any
    messages: Any
    negatives: Any
    null: Any = None
    compact: bool = flax.struct.field(pytree_node=False, default=False)
    attacked: Any = None
    attacked_negatives: Any = None


def negative_attacks(cfg: WatermarkConfig) -> AugmentConfig:
    """The attacks phase 3's negatives go through, whatever the run trains its renders with: two a step (one
    when the run names one), each with probability 0.75, at ``phase3.negative_strength``, from the run's
    ``augment.names`` (all 14 when empty). A verifier meets clean renders a platform re-encoded or
    colour-graded; a decoder that saw them only untouched reads such images as keys (docs/experiments/,
    false claims)."""
    per_step = min(2, len(cfg.augment.names or augment.AUGMENTATION_NAMES))  # a run may name only one
    return AugmentConfig(
        strength=cfg.phase3.negative_strength, names=cfg.augment.names, per_step=per_step, prob=0.75
    )


def noisy_negatives(key: jax.Array, images: jax.Array, sigma_max: float) -> jax.Array:
    """``images [B, H, W, 3]`` (float in [0, 1]) with :data:`NOISY_NEGATIVES_SHARE` of them, drawn per
    image, given ``+ N(0, σ²)`` per pixel and channel, ``σ ~ U(0, sigma_max)`` per image, clipped to [0, 1]:
    the range of noise a verifier's clean images may carry, where the attack policy has one σ."""
    k_noise, k_sigma, k_use = jax.random.split(key, 3)
    per_image = (images.shape[0], 1, 1, 1)
    sigma = jax.random.uniform(k_sigma, per_image, maxval=sigma_max)
    noisy = jnp.clip(images + sigma * jax.random.normal(k_noise, images.shape), 0.0, 1.0)
    return jnp.where(jax.random.bernoulli(k_use, NOISY_NEGATIVES_SHARE, per_image), noisy, images)


def keeps_reads_only(cfg: WatermarkConfig) -> bool:
    """True when phase 3 can keep each image as what the decoder reads of it (its read window at
    ``reading.max_side``), so that its memory follows the read's size, not the images': when no
    augmentation stands between an image and its read (``augment.prob`` 0)."""
    return not augment.draws_any(cfg.augment)


def reads_of(images: np.ndarray, cfg: WatermarkConfig) -> np.ndarray:
    """``[B, 2, S, S', 3]`` float32: the read window (``reading.window`` at ``reading.max_side``) of each of
    ``images [B, H, W, 3]`` as it is (``[:, 0]``) and rounded to 8 bits first (``[:, 1]``), as phase 3's
    step reads an image of either kind; in chunks of :data:`VIEWS_PER_CHUNK` images."""
    return _reads(images, cfg, with_rounded=True)


def _reads(images: np.ndarray, cfg: WatermarkConfig, with_rounded: bool) -> np.ndarray:
    """:func:`reads_of`, or (not ``with_rounded``) only the as-is reads ``[B, S, S', 3]``."""
    read = _window_reader(read_window.of_config(cfg.reading), with_rounded)
    parts = [
        np.asarray(read(jnp.asarray(images[i : i + VIEWS_PER_CHUNK], jnp.float32)))
        for i in range(0, len(images), VIEWS_PER_CHUNK)
    ]
    return np.concatenate(parts)


def attacked_reads(images: np.ndarray, cfg: WatermarkConfig, rng: np.random.Generator) -> np.ndarray:
    """``[B, S, S', 3]`` float16 (half the memory; it holds an 8-bit level to 2.4e-4): what the decoder
    reads (:func:`reads_of`) of each of ``images [B, H, W, 3]`` (float in [0, 1], or uint8) rounded to 8
    bits and put through one or two real attacks drawn from ``rng`` (``imaging.training_attacks``), as a
    verifier receives an image a platform has edited."""
    if images.dtype != np.uint8:
        images = attacks.to_uint8(np.asarray(images, np.float32))
    attacked = training_attacks.random_attacks(images, rng)
    # 8-bit already: its rounded read would be the same.
    return _reads(attacked.astype(np.float32) / 255.0, cfg, with_rounded=False).astype(np.float16)


@functools.cache
def _window_reader(options: read_window.ReadOptions, with_rounded: bool) -> Callable[[jax.Array], jax.Array]:
    """:func:`_reads`' jitted step for one reading setting."""

    @jax.jit
    def read(images: jax.Array) -> jax.Array:
        if not with_rounded:
            return read_window.window_of(images, options)
        rounded = jnp.round(images * 255.0) / 255.0
        both = jnp.stack([images, rounded], axis=1)  # [B, 2, H, W, 3]
        flat = both.reshape(-1, *images.shape[1:])
        out = read_window.window_of(flat, options)
        return out.reshape(images.shape[0], 2, *out.shape[1:])

    return read


def generic_count(scene_negatives: int) -> int:
    """How many images from outside the scene join ``scene_negatives`` of the scene's own."""
    return max(1, round(GENERIC_PER_SCENE_NEGATIVE * scene_negatives))


def generic_negatives(count: int, height: int, width: int, seed: int = GENERIC_SEED) -> np.ndarray:
    """``[count, height, width, 3]`` uint8 images that are no render of the scene: crops of the decoder
    training's photographs (``cover_images.TRAIN_PHOTOS``; the held-out ones stay unseen) and procedural
    textures, alternately, each made square at the longer side and cut to the render's aspect."""
    rng = np.random.default_rng([seed, height, width])
    photos = cover_images.load_photos(cover_images.TRAIN_PHOTOS)
    side = max(height, width)
    y, x = (side - height) // 2, (side - width) // 2
    out = np.empty((count, height, width, 3), np.uint8)
    for i in range(count):
        if i % 2:
            image = cover_images.procedural_image(rng, side)
        else:
            image = cover_images.random_crop(rng, photos[int(rng.integers(0, len(photos)))], side)
        out[i] = np.round(np.clip(image[y : y + height, x : x + width], 0, 1) * 255)
    return out


def render_refit_set(
    run: Any,
    cameras: Cameras,
    cfg: WatermarkConfig,
    ground_truth: np.ndarray,
    clean_model: Any = None,
    progress: bool = False,
    clean_renders: np.ndarray | None = None,
    training_renders: dict[int, np.ndarray] | None = None,
    depth_bounds: tuple[float, float] | None = None,
    render_more: Callable[[], bool] = lambda: True,
) -> RefitSet:
    """Phase 3's training set from a loaded watermarked run (``wm_run.load_watermarked_run``): every ID's
    renders of ``cameras`` (the training views) and of ``watermark.phase3.views`` novel views
    (:func:`novel_cameras`, seeded by ``watermark.seed``), rendered as evaluation renders them (no jitter).
    The negatives: ``ground_truth [V, H, W, 3]`` (the training images) and, given the run it was embedded
    into (``clean_model``, a loaded TensoRF run), its renders of the same views: an unwatermarked render is
    what a verifier must answer "no watermark" for, and it lies far nearer the watermarked renders than the
    photographs do; with the photographs alone the refitted decoder claims clean renders as IDs. Then a third
    as many images from outside the scene (:func:`generic_negatives`).
    ``clean_renders [V, H, W, 3]``: the clean model's
    renders of ``cameras`` when the caller has them already (the quality budget's references), so that only
    the novel views are rendered again (a clean render costs about as much as all 16 IDs' renders of a view:
    the geometry pass dominates). ``training_renders``: every ID's renders of ``cameras``, ``{ID: [V, H, W,
    3]}``, when the caller has them (``sample_cache.every_id_renders``), so that only the novel views are
    rendered. ``depth_bounds``: the scene's (nearest, farthest) depth, which a forward-facing scene's novel
    views need (``Scene.depth_bounds``). ``render_more()`` is asked before each chunk of novel views after the
    first (the time budget's share for them): False ends the set there. With ``phase3.attacked`` > 0 each
    render and each negative is also kept as read after real attacks (:func:`attacked_reads`, drawn from
    ``watermark.seed``)."""

    if clean_renders is not None and len(clean_renders) != len(cameras):
        raise ValueError(f"{len(clean_renders)} clean renders for {len(cameras)} training views")
    keys = run.extras["keys"]
    sets = [cameras]
    if cfg.phase3.views:
        sets.append(
            novel_cameras(
                cameras,
                int(cfg.phase3.views),
                int(cfg.seed),
                cfg.phase3.view_density,
                cfg.phase3.elevation_margin,
                depth_bounds,
            )
        )
    to_draw = sets if training_renders is None else sets[1:]
    compact = keeps_reads_only(cfg)
    keep = (lambda x: reads_of(np.asarray(x), cfg)) if compact else (lambda x: np.asarray(x, np.float32))  # noqa: E731
    keep_clean = lambda x: np.round(np.clip(np.asarray(x, np.float32), 0, 1) * 255).astype(np.uint8)  # noqa: E731
    views = sum(len(c) for c in to_draw)
    bar = tqdm(
        total=views * keys.num_ids,
        disable=not progress,
        desc="embed phase 3 (renders)",
        unit="render",
        dynamic_ncols=True,
    )
    tick = lambda _, rgb: bar.update(rgb.shape[-1] // 3)  # noqa: E731  (a view's renders: one per ID)
    rng = np.random.default_rng(np.random.SeedSequence([int(cfg.seed), ATTACK_STREAM]))
    attack = (lambda x: attacked_reads(x, cfg, rng)) if cfg.phase3.attacked else None  # noqa: E731
    parts = [] if training_renders is None else [{n: keep(r) for n, r in training_renders.items()}]
    attacked = []
    if attack is not None and training_renders is not None:
        attacked.append({n: attack(r) for n, r in training_renders.items()})
    negatives = [keep_clean(ground_truth)]
    # A frozen source's clean renders come from the watermarked pass itself (one geometry pass, not two).
    null_is_clean = watermark.null_renders_source(run.config.watermark)
    if clean_model is not None and clean_renders is not None:
        negatives.append(keep_clean(clean_renders))  # the training views' (sets[0]), given
    try:
        for index, cams in enumerate(sets):
            novel = index > 0
            for first in range(0, len(cams), VIEWS_PER_CHUNK):  # only a chunk's full-size renders at once
                if novel and first and not render_more():
                    break
                chunk = range(first, min(first + VIEWS_PER_CHUNK, len(cams)))
                wants_clean = clean_model is not None and (novel or clean_renders is None)
                clean = None
                if novel or training_renders is None:
                    if wants_clean and null_is_clean:
                        rendered, clean = wm_run.render_every_id_and_clean(run, cams, chunk, on_view=tick)
                    else:
                        rendered = wm_run.render_every_id(run, cams, chunk, on_view=tick)
                    parts.append({n: keep(r) for n, r in rendered.items()})
                    if attack is not None:
                        attacked.append({n: attack(r) for n, r in rendered.items()})
                if wants_clean:
                    if clean is None:
                        clean = np.stack(runs.render_views(clean_model, cams, chunk))
                    negatives.append(keep_clean(clean))
    finally:
        bar.close()
    renders = np.stack([np.concatenate([part[n] for part in parts]) for n in range(keys.num_ids)])
    messages = np.asarray(keys.messages, np.uint8)
    null = keys_lib.null_message(messages)
    scene_negatives = np.concatenate(negatives)
    generic = generic_negatives(generic_count(len(scene_negatives)), *scene_negatives.shape[1:3])
    negatives_all = np.concatenate([scene_negatives, generic])
    attacked_renders = attacked_negatives = None
    if attack is not None:
        attacked_renders = np.stack(
            [np.concatenate([part[n] for part in attacked]) for n in range(keys.num_ids)]
        )
        attacked_negatives = attack(negatives_all)
    return RefitSet(
        renders.astype(np.float32),
        messages,
        negatives_all,
        null,
        compact=compact,
        attacked=attacked_renders,
        attacked_negatives=attacked_negatives,
    )


def refit_rate(cfg: WatermarkConfig, step: Any, total: Any) -> jax.Array:
    """Phase 3's learning rate at ``step`` (0-based) of a ``total``-step schedule (ints or traced scalars):
    a linear warm-up over the first 10 % (at least one step), then cosine decay to 0 at ``total`` (optax's
    ``warmup_cosine_decay_schedule``, with the length as data so that :func:`refit_decoder` can size it to
    the minutes left). The decoder's Adam state starts empty, and a full-rate start on a fitted decoder first
    unlearns it."""
    s = jnp.asarray(step, jnp.float32)
    n = jnp.maximum(jnp.asarray(total, jnp.float32), 1.0)
    warm = jnp.maximum(jnp.floor(n / 10.0), 1.0)
    rise = s / warm
    fall = 0.5 * (1.0 + jnp.cos(jnp.pi * jnp.clip((s - warm) / jnp.maximum(n - warm, 1.0), 0.0, 1.0)))
    return cfg.phase3.lr * jnp.where(s < warm, rise, fall)


def refit_schedule(cfg: WatermarkConfig) -> optax.Schedule:
    """:func:`refit_rate` over the configured ``phase3.steps``."""
    return lambda count: refit_rate(cfg, count, max(int(cfg.phase3.steps), 1))


def refit_optimizer(cfg: WatermarkConfig) -> optax.GradientTransformation:
    """Phase 3's Adam moments over the decoder's weights; the step scales them by :func:`refit_rate`."""
    del cfg  # the rate is the step's argument (its schedule's length may change during the run)
    return optax.scale_by_adam()


def make_refit_step(
    cfg: WatermarkConfig, decoder_state: PyTree
) -> Callable[[PyTree, Any, jax.Array, RefitSet, Any, Any], tuple[PyTree, Any, jax.Array]]:
    """A jitted ``(decoder params, Adam state, key, data, step, total) -> (params, state, loss)`` over
    batches of ``data`` (a :class:`RefitSet` of arrays: arguments, not constants baked into the compiled
    step), at :func:`refit_rate` of ``step`` in a ``total``-step schedule (int32 scalars, data too).

    A batch: ``phase3_batch`` renders (ID and view uniform), each rounded to 8 bits with probability ½ and
    through the run's augmentations when phase 2 had them (``augment_prob > 0``), and a quarter as many
    negatives (8-bit) through :func:`negative_attacks` (and :func:`noisy_negatives` with
    ``phase3.negative_noise``); then the read window, LL2 and the decoder (eval-mode BatchNorm, as phase
    2). With ``data.attacked``, each render and each negative is read after its real attacks instead with
    probability ``phase3.attacked``.
    """
    batch = int(cfg.phase3.batch)
    n_neg = max(batch // NEGATIVES_PER_BATCH_DIVISOR, 1) if cfg.phase3.lambda_clean else 0
    reading = read_window.of_config(cfg.reading)  # phase 3 reads as phase 2
    tx = refit_optimizer(cfg)
    negative_policy = negative_attacks(cfg)

    def prepare(key: jax.Array, images: jax.Array, compact: bool) -> jax.Array:
        """The read windows ``[B, S, S', 3]`` of a batch of renders (before LL2)."""
        k_round, k_aug = jax.random.split(key)
        if compact:  # [B, 2, S, S', 3]: each image's read as it is and rounded (reads_of), drawn as below
            rounded = jax.random.bernoulli(k_round, 0.5, (images.shape[0],)).astype(jnp.int32)
            return images[jnp.arange(images.shape[0]), rounded]
        rounded = jnp.round(images * 255.0) / 255.0
        images = jnp.where(jax.random.bernoulli(k_round, 0.5, (images.shape[0], 1, 1, 1)), rounded, images)
        images = augment.configured_policy(k_aug, images, cfg.augment)
        return read_window.window_of(images, reading)

    def logits_of(params: PyTree, ll2: jax.Array) -> jax.Array:
        return decoder_lib.apply_ll2({**decoder_state, "params": params}, ll2)

    @xla_cpu.jit_cpu_tuned
    def step(
        params: PyTree, opt_state: Any, key: jax.Array, data: RefitSet, index: Any, total: Any
    ) -> tuple[PyTree, Any, jax.Array]:
        k_id, k_view, k_neg, k_pos, k_clean = jax.random.split(key, 5)
        k_att, k_att_neg = jax.random.split(jax.random.fold_in(key, ATTACK_STREAM))  # draws above unchanged
        n_ids, n_views = data.renders.shape[:2]
        ids = jax.random.randint(k_id, (batch,), 0, n_ids)
        views = jax.random.randint(k_view, (batch,), 0, n_views)
        seen = prepare(k_pos, data.renders[ids, views], data.compact)
        if data.attacked is not None:  # the reads are chosen before the one LL2 of the batch
            use = jax.random.bernoulli(k_att, cfg.phase3.attacked, (batch, 1, 1, 1))
            seen = jnp.where(use, data.attacked[ids, views].astype(jnp.float32), seen)
        seen = dwt.ll2(seen, cfg.reading.wavelet)
        if n_neg:  # an empty batch would reach the augmentations' convolutions (a zero group count)
            if data.null is None:
                raise ValueError("phase 3's negatives need the word they are read as (RefitSet.null)")
            null = data.null.astype(jnp.float32)
            drawn = jax.random.randint(k_neg, (n_neg,), 0, data.negatives.shape[0])
            attacked = augment.configured_policy(
                k_clean, data.negatives[drawn].astype(jnp.float32) / 255.0, negative_policy
            )
            if cfg.phase3.negative_noise:
                k_noise = jax.random.fold_in(key, NOISE_STREAM)
                attacked = noisy_negatives(k_noise, attacked, cfg.phase3.negative_noise)
            clean = read_window.window_of(attacked, reading)
            if data.attacked_negatives is not None:
                use = jax.random.bernoulli(k_att_neg, cfg.phase3.attacked, (n_neg, 1, 1, 1))
                clean = jnp.where(use, data.attacked_negatives[drawn].astype(jnp.float32), clean)
            clean = dwt.ll2(clean, cfg.reading.wavelet)
        messages = data.messages.astype(jnp.float32)

        def loss_fn(p: PyTree) -> jax.Array:
            z = logits_of(p, seen)
            loss = cfg.losses.lambda_message * losses.bce_with_logits(
                z, messages[ids], cfg.losses.bce_temperature
            )
            if cfg.losses.lambda_key:
                loss = loss + cfg.losses.lambda_key * losses.key_cross_entropy(
                    z, messages, ids, cfg.losses.bce_temperature
                )
            if n_neg:
                z_clean = logits_of(p, clean)
                clean_bce = losses.bce_with_logits(z_clean, null, cfg.losses.bce_temperature)
                loss = loss + cfg.phase3.lambda_clean * clean_bce
            return loss

        loss, grads = jax.value_and_grad(loss_fn)(params)
        moments, opt_state = tx.update(grads, opt_state, params)
        rate = refit_rate(cfg, index, total)
        return jax.tree.map(lambda p, m: p - rate * m, params, moments), opt_state, loss

    return step


def refit_decoder(
    cfg: WatermarkConfig,
    decoder_vars: PyTree,
    data: RefitSet,
    *,
    keep_going: Callable[[], bool] = lambda: True,
    seconds_left: Callable[[], float] | None = None,
    progress: bool = False,
    clock: Callable[[], float] = time.perf_counter,
) -> tuple[PyTree, dict[str, float]]:
    """Up to ``phase3.steps`` decoder steps on ``data`` from ``decoder_vars`` (``{"params", "batch_stats",
    ...}``; only ``params`` change). ``keep_going()`` is asked before each step (the time budget).

    ``seconds_left()`` (the time budget's, when it has one): the schedule is sized to the steps that fit
    in it (``embed_budget.ScheduleSizer``, timed by ``clock``, seconds), so that its warm-up and cosine
    decay end inside the budget, not cut off at a high rate where steps run slower. Without it, or when
    all the steps fit, the schedule is ``phase3.steps`` long and the run deterministic in
    ``watermark.seed``. Returns the new variables and ``{"steps",
    "scheduled", "loss"}`` (steps taken, the schedule's length, the last step's loss).
    """
    step = make_refit_step(cfg, decoder_vars)
    # Committed to the device as the step's outputs are: otherwise the second step compiles again (another
    # cache key), and a timed step that compiles would shorten the sized schedule.
    device = jax.devices()[0]
    arrays = jax.device_put(jax.tree.map(jnp.asarray, data), device)
    params = jax.device_put(decoder_vars["params"], device)
    opt_state = jax.device_put(refit_optimizer(cfg).init(params), device)
    key = jax.random.fold_in(jax.random.key(int(cfg.seed)), 0xDEC3)
    loss = jnp.full((), jnp.nan)
    total = int(cfg.phase3.steps)
    sizer = None if seconds_left is None else embed_budget.ScheduleSizer(total, seconds_left, clock=clock)
    done = 0
    bar = tqdm(
        total=total, disable=not progress, desc="embed phase 3 (decoder)", unit="step", dynamic_ncols=True
    )
    try:
        while done < total:
            if not keep_going():
                break
            if sizer is not None and sizer.due(done):
                jax.block_until_ready(loss)  # the steps dispatched so far have run
                total = bar.total = sizer.size(done)
                bar.refresh()
            timing = sizer is not None and sizer.times(done)
            tick = clock() if timing else 0.0
            params, opt_state, loss = step(
                params, opt_state, jax.random.fold_in(key, done), arrays, jnp.int32(done), jnp.int32(total)
            )
            if sizer is not None and timing:
                jax.block_until_ready(loss)
                sizer.record(clock() - tick)
            done += 1
            if done % 25 == 0:  # reading the loss waits for the step: not every step
                bar.set_postfix(loss=f"{float(loss):.4f}")
            bar.update(1)
    finally:
        bar.close()
    return {**decoder_vars, "params": params}, {
        "steps": float(done),
        "scheduled": float(total),
        "loss": float(loss),
    }
