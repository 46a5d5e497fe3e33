"""Two-phase watermark embedding with deferred back-propagation.

The objective of one training step, for one image of ``H × W`` pixels rendered with one watermark ID, is

    L(θ, φ) = L_img(I(θ), φ) + Σ_p L_patch(R_p(θ), T_p)

where ``I(θ) [H, W, 3]`` is the rendered image, ``φ`` the decoder parameters, ``R_p(θ) [S, S, 3]`` the render
of square patch ``p`` (``P`` patches of side ``S`` that cover the image), and ``T_p`` the ground truth there.
The patch losses add up over patches, as WateRF back-propagates each chunk's loss on its own: their weight
against the image loss grows with the number of patches.
Phase 1: ``L_img = λ_m·BCE(D(LL2(I)), m) + λ_i·Watson(I, GT)``, no patch term, decoder frozen.
Phase 2: ``L_img = λ_m·BCE(D(LL2(A(I))), m)`` with two random augmentations ``A``, and
``L_patch = λ_rgb·L1 + λ_TV·TV + λ_SSIM·(1 − SSIM)``; the decoder trains too.

Deferred back-propagation (ARF) computes ``∇θ L`` without ever holding the graph of the full render:

1. render ``I`` patch by patch without a graph (peak memory: one patch);
2. ``g_I = ∂L_img/∂I`` and ``∂L_img/∂φ`` from the image-level loss alone (cheap: no renderer inside);
3. re-render each patch with ``jax.vjp`` and pull back ``g_I`` restricted to the patch plus ``∂L_patch/∂R_p``;
   the parameter gradients add up over patches.

Because rendering is per ray, step 3 gives exactly the gradient of differentiating ``L`` through the full
render. Patches are square and all ``S × S`` (static shapes under jit); the last row / column of patches is
shifted back to end at the image border, so patches may overlap there. Each pixel is *owned* by one patch: its
image value and its image-loss gradient come from that patch only, while patch losses see whole patches. The
same per-patch PRNG keys are used in steps 1 and 3, so a jittered render is reproduced exactly.

Each step draws one training view and ``watermark.schedule.ids_per_step`` distinct IDs (default: every ID, at
most 16), deterministically from the seed and the step so that a resumed run follows the same path, renders
the view with each ID's FiLM conditioning and takes one optimiser step on the mean of their objectives (Adam,
per-group learning rates, exponential decay over both phases). The IDs share one render's geometry and every
colour layer but the last (``watermark.condition_many``), so each ID learns more often for much less than
K renders' cost.

Phase 3 (not in the paper; ``watermark.phase3.steps`` > 0): once the field's schedule has ended, or the time
budget has ended the field in time to keep ``phase3.reserve_min`` for it, the decoder alone learns on the
field's renders of every training view (and of novel views) with every ID (``decoder_refit``); the field
does not change. :func:`refit_phase` runs it and checkpoints at step ``phase-1 + phase-2 + phase-3 steps``.

A watermarked run (``WMRUN``) is written by :func:`embed` and read by ``wm_run`` (its layout, the loader
registered with ``run.load_run``, the keys and decoder, choosing the ID to render).
"""

from __future__ import annotations

import dataclasses
import sys
import time
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp

from mnerf_jax.core import config as config_lib
from mnerf_jax.core import embed_defaults, rundir
from mnerf_jax.core.checkpoint import CheckpointStore, check_compatible
from mnerf_jax.core.config import Config
from mnerf_jax.core.watermark_config import check_fraction
from mnerf_jax.imaging import augment, losses
from mnerf_jax.reader import decoder_io, dwt
from mnerf_jax.reader import keys as keys_lib
from mnerf_jax.tensorf import budgets, raymarch
from mnerf_jax.tensorf import run as runs
from mnerf_jax.watermark import model as watermark
from mnerf_jax.watermark import phase3 as decoder_refit
from mnerf_jax.watermark import run as wm_run
from mnerf_jax.watermark import sample_cache
from mnerf_jax.watermark.deferred import patch_layout, tiling_patch_size, whole_view_layout
from mnerf_jax.watermark.inputs import check_rgb_images, clean_references, source_psnr
from mnerf_jax.watermark.loop import EmbedLoop, EmbedResult, seed_budgets
from mnerf_jax.watermark.objective import budget_end_db, uses_clean_renders, uses_fidelity
from mnerf_jax.watermark.run import WM_KIND, EmbedError
from mnerf_jax.watermark.step import EmbedState, make_optimizer, total_steps

# The embedding run: sources, config, setting up the loop (embed_loop; the jitted step and its optimiser:
# wm_step).
# ==========================================================================================================


# run.json's record of the settings --config auto chose (replayed by --resume).
AUTO_RECORD = "auto"

# --------------------------------------------------------------------------------------------- sources


def load_source(run_dir: str | Path) -> runs.LoadedRun:
    """The latest checkpoint of a fitted TensoRF run; EmbedError if ``run_dir`` is not one."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise EmbedError(f"--from {run_dir}: no such run directory")
    marker = rundir.read_marker(run_dir)
    if marker is None:
        raise EmbedError(
            f"--from {run_dir} is not a fitted TensoRF run (no {rundir.RUN_MARKER}; make one with "
            "`mnerf fit`)"
        )
    if marker.get("kind") != rundir.TENSORF_KIND:
        raise EmbedError(
            f"--from {run_dir} holds a {marker.get('kind')!r} run, not a fitted TensoRF "
            "(watermark the TensoRF run it came from)"
        )
    return wm_run.load_run(run_dir)


def load_decoder_for(bits: int, path: str | Path | None) -> decoder_io.LoadedDecoder:
    """``--decoder FILE`` or the shipped decoder for ``bits``; MnerfError on a bit-length mismatch."""
    if path is None:
        return decoder_io.load_decoder(decoder_io.shipped_decoder_path(bits), expect_bits=bits)
    loaded = decoder_io.load_decoder(path)
    if loaded.bits != bits:
        raise EmbedError(f"--decoder {path} reads {loaded.bits}-bit messages, not --bits {bits}")
    return loaded


def resolve_config(
    source: runs.LoadedRun, preset: str | None, overrides: Sequence[str], num_ids: int, bits: int
) -> Config:
    """The embedding config: the source run's data/model/render, the watermark section from ``preset``
    (default: the source's), then ``--set`` overrides, then ``num_ids`` and ``bits``."""
    base = source.config
    if preset is not None:
        base = dataclasses.replace(base, watermark=config_lib.load_preset(preset).watermark)
    config = config_lib.apply_overrides(base, overrides)
    if config.model != source.config.model or config.data != source.config.data:
        raise EmbedError(
            "--set may not change model.* or data.* of a fitted run (the embedding keeps its "
            "arrays and scene)"
        )
    config = dataclasses.replace(
        config, watermark=dataclasses.replace(config.watermark, num_ids=int(num_ids), bits=int(bits))
    )
    config.watermark.check_ids()
    keys_lib.check_sizes(int(num_ids), int(bits))
    # The run's config records the schedule it ran, not -1.
    phase1, phase2 = watermark.phase_steps(config.watermark)
    schedule = dataclasses.replace(config.watermark.schedule, phase1_steps=phase1, phase2_steps=phase2)
    config = dataclasses.replace(config, watermark=dataclasses.replace(config.watermark, schedule=schedule))
    cfg = config.watermark
    try:
        augment.resolve_names(cfg.augment.names or None, cfg.augment.per_step)
    except augment.AugmentError as err:
        raise EmbedError(f"watermark.augment.names / per_step: {err}") from None
    if cfg.reading.wavelet not in dwt.DEC_LO:
        raise EmbedError(
            f"unknown watermark.reading.wavelet {cfg.reading.wavelet!r} ({' | '.join(dwt.DEC_LO)})"
        )
    if cfg.reading.window:
        check_fraction(cfg.reading.window, "watermark.reading.window")
    if cfg.reading.jitter < 0 or (cfg.reading.jitter and not cfg.reading.window):
        raise EmbedError(
            f"watermark.reading.jitter is a radius in pixels ≥ 0 that moves the read window, and "
            f"needs watermark.reading.window > 0; got {cfg.reading.jitter} with read_window "
            f"{cfg.reading.window}"
        )
    if total_steps(config.watermark) < 1:
        raise EmbedError("watermark.schedule.phase1_steps + watermark.schedule.phase2_steps must be ≥ 1")
    return config


def watermark_defaults_drift(run_dir: str | Path, overrides: Iterable[str] = ()) -> list[str]:
    """Fields where the ``[watermark]`` section a fitted run recorded differs from its preset's today.

    A fit records the whole config, watermark section included, and ``embed --from`` takes that section as
    its base (the run is the record). After an upgrade that changed a default, the recorded value is the
    old one: ``["lr_decoder 0.0001 (today 0.001)", ...]``, for a note. Fields that ``overrides`` (the
    command's ``--set`` items) set are left out: neither value is used. ``[]`` when they agree, when the
    run's preset is not a shipped one, or when ``run_dir`` is not a fitted run (``embed`` says so).
    """
    overridden = config_lib.parse_overrides(overrides).get("watermark", {})
    run_dir = Path(run_dir)
    marker = rundir.read_marker(run_dir) if run_dir.is_dir() else None
    if marker is None or marker.get("kind") != rundir.TENSORF_KIND:
        return []
    recorded = rundir.read_run_config(run_dir)
    try:
        today = config_lib.load_preset(recorded.name).watermark
    except config_lib.ConfigError:
        return []
    was, now = config_lib.flat_items(recorded.watermark), config_lib.flat_items(today)
    skip = set(config_lib.flat_items(overridden))
    return [
        f"{name} {was[name]!r} (today {now[name]!r})"
        for name in now
        if name not in skip and was[name] != now[name]
    ]


def choose_embedding(
    source: runs.LoadedRun, scene: Any, out: Path, num_ids: int, resume: bool
) -> embed_defaults.Choice | None:
    """``--config auto``: when resuming ``out``, the choice it recorded, or None (the fitted run's section)
    for a run embedded otherwise; else a choice made for this scene and machine (``core.embed_defaults``)."""
    marker = rundir.read_marker(out) if resume and out.is_dir() else None
    if marker is not None:
        record = marker.get(AUTO_RECORD)
        return None if record is None else embed_defaults.Choice.from_dict(record)
    images = scene.split("train").images
    facts = embed_defaults.SceneFacts(
        fit_preset=source.config.name,
        height=int(images.shape[1]),
        width=int(images.shape[2]),
        views=int(images.shape[0]),
        backdrop=embed_defaults.backdrop_of(scene.kind, bool(scene.white_bg)),
        num_ids=int(num_ids),
        backend=jax.default_backend(),
        memory_bytes=embed_defaults.free_memory_bytes(),
    )
    return embed_defaults.choose(facts)


def _has_checkpoints(out: Path) -> bool:
    folder = out / "checkpoints"
    return folder.is_dir() and any(p.name.isdigit() for p in folder.iterdir())


def embed(
    source_run: str | Path,
    out_dir: str | Path,
    num_ids: int,
    bits: int,
    *,
    preset: str | None = None,
    overrides: Sequence[str] = (),
    decoder_path: str | Path | None = None,
    data_path: str | Path | None = None,
    resume: bool = False,
    stop_at: int | None = None,
    progress: bool = True,
    on_step: Callable[[int, dict[str, float]], None] | None = None,
) -> EmbedResult:
    """Embed ``num_ids`` keyed ``bits``-bit watermarks into the TensoRF of ``source_run``; write ``out_dir``.

    Everything that can be checked is checked before anything is written (source run, config, decoder,
    scene images, output directory).

    Args:
      source_run: a fitted TensoRF run (``mnerf fit``).
      out_dir: the watermarked run: ``run.json``, ``config.json``, ``checkpoints/``, ``keys.json``,
        ``decoder.npz`` (the decoder as fine-tuned with the field, then refitted alone in phase 3 when
        ``watermark.phase3.steps`` > 0), ``embed.json`` (progress).
      num_ids, bits: ``N`` IDs with ``L``-bit messages (the decoder must read ``L`` bits).
      preset, overrides: the watermark config (``--config``, ``--set``): a preset's ``[watermark]`` section;
        None or ``"run"``: the section the fitted run recorded; ``"auto"``: chosen for the scene and the
        machine (``core.embed_defaults``; printed, and recorded in ``run.json`` for ``--resume``).
      decoder_path: the decoder to start from (default: the shipped one for ``bits``); ``"fresh"``: a
        random-init decoder whitened on the scene's training images (``decoder_io.fresh_decoder``).
      data_path: the scene (default: the one the source run recorded).
      resume: continue from ``out_dir``'s latest checkpoint (a fresh start when there is none).
      stop_at: stop after this many steps in all (a checkpoint is written there).
      on_step: called after every step with ``(step, metrics)``.
    """
    started = time.perf_counter()  # the run's clock, and its time budget's (watermark.time_budget.minutes)
    out = Path(out_dir)
    source = load_source(source_run)
    scene = source.load_scene(data_path, splits=("train",))
    split = scene.split("train")
    check_rgb_images(split.images, f"{data_path or source.data_path or 'procedural scene'} (train split)")
    choice = None
    if preset == embed_defaults.AUTO:
        choice = choose_embedding(source, scene, out, num_ids, resume)
        if choice is not None:
            preset, overrides = choice.preset, [*choice.settings, *overrides]
    if preset in (embed_defaults.AUTO, embed_defaults.FROM_RUN):
        preset = None
    config = resolve_config(source, preset, overrides, num_ids, bits)
    cfg = config.watermark
    fresh = decoder_path is not None and str(decoder_path) == decoder_io.FRESH
    loaded = None if fresh else load_decoder_for(bits, decoder_path)
    resuming = rundir.prepare_output(out, config, resume=resume, kind=WM_KIND) and _has_checkpoints(out)
    keys = None
    if resuming:
        keys = keys_lib.load_keys(out, expect_bits=bits)  # a WMRUN without keys stops here
        if keys.num_ids != num_ids:
            raise EmbedError(f"{out} embeds {keys.num_ids} IDs, not --num-ids {num_ids}")
    if choice is not None:  # said once the input has passed its checks
        print(f"mnerf embed: {choice.describe()}", file=sys.stderr)
    if loaded is None:
        loaded = decoder_io.fresh_decoder(bits, split.images, seed=cfg.seed, wavelet=cfg.reading.wavelet)
    decoder_source = decoder_io.FRESH if fresh else str(Path(loaded.path).resolve())
    height, width = int(split.images.shape[1]), int(split.images.shape[2])
    # The layout tiles the image with the fewest patches of at most patch_size (no overlap where it divides).
    # A cached source renders the whole view from its cached samples: one patch, whatever patch_size says
    # (the view's own shape, so non-square views such as LLFF's too).
    if cfg.schedule.cache_source:
        layout = whole_view_layout(height, width)
    else:
        layout = patch_layout(
            height, width, tiling_patch_size(height, width, cfg.schedule.patch_size, losses.SSIM_WINDOW)
        )
    if cfg.losses.lambda_ssim and layout.size < losses.SSIM_WINDOW:
        window = losses.SSIM_WINDOW
        raise EmbedError(
            f"patches of {layout.size} px (images {height}×{width}, watermark.schedule.patch_size "
            f"{cfg.schedule.patch_size}) are below SSIM's {window}×{window} window"
        )

    store = CheckpointStore(out, keep=max(cfg.keep_checkpoints, 1))
    # A fitted field keeps most of its in-mask samples for colour, so the colour buffer starts as large as the
    # density one: the first step cannot overflow (a redo is a compilation). Both are fitted after that one
    # step: a step at the full budgets costs many fitted steps, more than a later overflow would.
    policy = budgets.BudgetPolicy(colour_fraction=1.0, fresh_calls=1)
    n_rays, n_samples = layout.rays, source.geometry.n_samples
    try:
        if resuming:
            meta = store.read_meta()
            if meta.get("kind") != WM_KIND:
                raise EmbedError(f"{out}: its checkpoint holds a {meta.get('kind')!r} model, not a watermark")
            saved = wm_run.normalised_meta(meta)
            check_compatible(saved, wm_run.fingerprint_config(config), out, wm_run.SECTIONS)
            check_phase3_unchanged(meta, config, out)
            started -= float(meta.get("run_seconds", 0.0))  # the earlier processes' time counts
            _, tree, meta = wm_run.restore(store, out, optimizer=make_optimizer)
            state = EmbedState(
                params=jax.tree.map(jnp.asarray, tree["params"]),
                decoder=jax.tree.map(jnp.asarray, tree["decoder"]),
                opt_state=jax.tree.map(jnp.asarray, tree["opt_state"]),
                step=jnp.asarray(tree["step"], jnp.int32),
                key=jax.random.wrap_key_data(jnp.asarray(tree["key"], jnp.uint32)),
            )
            geometry = raymarch.geometry_from_checkpoint(tree["geometry"], meta["geometry"])
            seed_budgets(policy, n_rays, n_samples, meta["budgets"])
        else:
            keys = keys_lib.generate_keys(num_ids, bits, cfg.min_hamming, cfg.key_seed, loaded.fingerprint)
            root = jax.random.key(cfg.seed)
            params = watermark.add_watermark(jax.random.fold_in(root, 0x3A7), source.params, cfg, num_ids)
            dec_vars = dict(loaded.variables)  # params, BatchNorm statistics, pooling margin if any
            tx = make_optimizer(cfg, config.train.adam_b1, config.train.adam_b2)
            state = EmbedState(
                params=params,
                decoder=dec_vars,
                opt_state=tx.init({"field": params, "decoder": dec_vars["params"]}),
                step=jnp.zeros((), jnp.int32),
                key=jax.random.fold_in(root, 0xE3B),
            )
            geometry = source.geometry
            data = data_path if data_path is not None else source.data_path
            rundir.write_run_files(
                out,
                config,
                data=data,
                kind=WM_KIND,
                extra={
                    "source_run": str(source.run_dir.resolve()),
                    "source_step": source.step,
                    "num_ids": num_ids,
                    "bits": bits,
                    "variant": cfg.variant,
                    "decoder_source": decoder_source,
                    "decoder_source_fingerprint": loaded.fingerprint,
                    **({AUTO_RECORD: choice.to_dict()} if choice is not None else {}),
                },
            )
            keys_lib.save_keys(out, keys)
        vgg = losses.vgg_params() if cfg.losses.perceptual == "vgg" and cfg.losses.lambda_perceptual else None
        # Committed to the device from the start, as every later step's state is (a step's outputs are): an
        # uncommitted first state is another cache key for jit, so the first step compiled twice.
        state = jax.device_put(state, jax.devices()[0])
        cache = None
        if cfg.schedule.cache_source:
            cache = sample_cache.build_cache(state.params, geometry, config.model, split.cameras, progress)
        references = None
        if uses_clean_renders(cfg):  # from the cached samples when there are some: the same renders
            references = (
                clean_references(source, split, progress)
                if cache is None
                else sample_cache.clean_renders(cache, geometry.white_bg).reshape(split.images.shape)
            )
        end_db = None
        if references is not None and uses_fidelity(cfg) and cfg.fidelity.over_source:
            trained = source_psnr(references, split.images)
            end_db = budget_end_db(cfg, trained)
            print(
                f"mnerf embed: the source reads {trained:.2f} dB on its training views; "
                f"the quality budget ends at {end_db:.2f} dB against its renders",
                file=sys.stderr,
            )
        loop = EmbedLoop(
            config,
            split,
            keys,
            layout,
            geometry,
            policy,
            store,
            out,
            progress,
            on_step,
            vgg,
            references,
            cache=cache,
            budget_end_db=end_db,
            run_started=started,
        )
        result = loop.run(state, stop_at)
        cfg = loop.config.watermark  # the budget may have sized the field's schedule
        field_done = result.steps == total_steps(cfg) and (stop_at is None or stop_at > result.steps)
        # A field the time budget ended still gets phase 3, in the minutes the budget kept for it.
        cut = result.stopped_by_budget and loop.clock is not None and loop.clock.kept_s > 0
        if cfg.phase3.steps and (field_done or cut):
            result = refit_phase(loop, result, split, source, progress, scene.depth_bounds)
        return result
    finally:
        store.close()


def check_phase3_unchanged(meta: dict[str, Any], config: Config, out: Path) -> None:
    """EmbedError when the checkpoint is past the field's schedule (its phase 3 ran) under other phase-3
    settings than ``config``'s: a run's decoder is refitted once."""
    if int(meta["step"]) <= total_steps(config.watermark):
        return
    # A key the run's version did not have ran at its default (phase3_lambda_clean came later).
    ran = config_lib.from_dict(meta["config"]).watermark.phase3
    now = config.watermark.phase3
    if ran != now:
        raise EmbedError(
            f"{out} has finished its phase 3 (step {meta['step']}) with {ran}, not {now}; "
            "a decoder is refitted once: resume with those settings, or embed anew"
        )


def refit_phase(
    loop: EmbedLoop,
    result: EmbedResult,
    split: Any,
    source: runs.LoadedRun,
    progress: bool,
    depth_bounds: tuple[float, float] | None = None,
) -> EmbedResult:
    """Phase 3 on the field ``result`` ended with (saved in ``loop.out``; the time budget may have ended it
    before its schedule did): the decoder alone (``decoder_refit``, its schedule sized to the budget's
    minutes left), then a checkpoint at step ``phase-1 + phase-2 steps`` (the field's schedule, wherever the
    field stopped) ``+ phase-3 steps``, past the field's schedule, so that ``--resume`` finds the run
    finished. It is one unit: a run killed inside it redoes it on ``--resume``. ``depth_bounds``: the scene's
    (a forward-facing scene's novel views lie on its spiral path)."""
    tick = time.perf_counter()
    cfg = loop.config.watermark
    clock = loop.clock
    run = wm_run.load_watermarked_run(loop.out)
    seen = None  # the training views' renders, from the cached samples when the source was cached
    if loop.cache is not None:
        seen = sample_cache.every_id_renders(
            loop.cache, run.params, cfg, loop.keys.num_ids, run.geometry.white_bg
        )
        seen = {n: r.reshape(split.images.shape) for n, r in seen.items()}
    render_more = lambda: True  # noqa: E731
    if clock is not None:
        floor = (1.0 - decoder_refit.NOVEL_VIEWS_SHARE) * clock.seconds_left(time.perf_counter())
        render_more = lambda: clock.seconds_left(time.perf_counter()) > floor  # noqa: E731
    data = decoder_refit.render_refit_set(
        run,
        split.cameras,
        cfg,
        split.images,
        source,
        progress,
        loop.references,
        seen,
        depth_bounds,
        render_more=render_more,
    )
    keep_going, seconds_left = lambda: True, None
    if clock is not None:
        keep_going = lambda: clock.room_for(0.0, time.perf_counter())  # noqa: E731
        seconds_left = lambda: clock.seconds_left(time.perf_counter())  # noqa: E731
    decoder, metrics = decoder_refit.refit_decoder(
        cfg, result.state.decoder, data, keep_going=keep_going, seconds_left=seconds_left, progress=progress
    )
    if not metrics["steps"]:  # no time for a decoder step: the run stays the field it was (resumable)
        return result
    steps = total_steps(cfg) + int(metrics["steps"])
    state = result.state.replace(decoder=decoder, step=jnp.asarray(steps, jnp.int32))
    rundir.write_json_atomic(loop.out / rundir.CONFIG_FILE, loop.config.to_dict())  # now with its phase 3
    loop.save(state)
    last = {
        **result.last_metrics,
        "phase": 3.0,
        "phase3_loss": metrics["loss"],
        "field_steps": result.steps,
        "phase3_steps": metrics["steps"],
        "phase3_scheduled": metrics["scheduled"],
    }
    return dataclasses.replace(
        result,
        steps=steps,
        seconds=result.seconds + time.perf_counter() - tick,
        run_seconds=time.perf_counter() - loop.run_started,
        last_metrics=last,
        state=state,
    )
