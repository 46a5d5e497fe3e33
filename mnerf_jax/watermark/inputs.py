"""What each embedding step reads: the training views checked as RGB, the IDs and view of each step, the
step's batch and the clean model's renders of the training views (the quality budget's reference).

``embed`` drives these; they hold no state, so a resumed run draws and reads exactly what an uninterrupted one
does.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from mnerf_jax.data import camera_rays
from mnerf_jax.imaging import metrics
from mnerf_jax.reader import keys as keys_lib
from mnerf_jax.tensorf import run as runs
from mnerf_jax.watermark.run import EmbedError


def check_rgb_images(images: np.ndarray, where: str) -> np.ndarray:
    """``images [N, H, W, 3]`` float32 in [0, 1], or EmbedError naming what is wrong."""
    arr = np.asarray(images)
    if arr.ndim != 4 or arr.shape[-1] != 3:
        raise EmbedError(f"{where}: images must be RGB [N, H, W, 3], got shape {arr.shape}")
    if not np.issubdtype(arr.dtype, np.floating):
        raise EmbedError(f"{where}: images must be float in [0, 1], got {arr.dtype}")
    return arr.astype(np.float32)


def step_batch(
    split: Any,
    view: int,
    messages: np.ndarray,
    ids: Sequence[int],
    references: np.ndarray | None = None,
    null: np.ndarray | None = None,
) -> dict[str, jax.Array]:
    """One step's inputs: the view's rays and pixels, the ``K`` IDs with their messages ``[K, L]``, every
    ID's message ``keys [N, L]``, the word clean images are read as ``null [L]`` (``keys_lib.null_message``
    of the keys, when not given), and the clean model's render of the view when ``references`` (the quality
    budget) are given."""
    o, d = camera_rays(split.cameras, view)
    batch = {
        "rays_o": jnp.asarray(o),
        "rays_d": jnp.asarray(d),
        "target": jnp.asarray(split.images[view].reshape(-1, 3), jnp.float32),
        "message": jnp.asarray(messages[np.asarray(ids)], jnp.float32),
        "id": jnp.asarray(ids, jnp.int32),
        "keys": jnp.asarray(messages, jnp.float32),
        "null": jnp.asarray(keys_lib.null_message(messages) if null is None else null, jnp.float32),
    }
    if references is not None:
        batch["reference"] = jnp.asarray(references[view].reshape(-1, 3), jnp.float32)
    return batch


def clean_references(source: runs.LoadedRun, split: Any, progress: bool = False) -> np.ndarray:
    """The clean model's renders of every training view, ``[V, H, W, 3]`` float16 (the quality budget's
    reference; rendered once, without sample jitter, as evaluation renders it).

    The embedding's renders jitter their samples; a clean field's jittered and unjittered renders differ far
    less than any useful budget allows. float16 holds [0, 1] to 2.4e-4 and halves the memory.
    """
    bar = tqdm(
        total=len(split.cameras), disable=not progress, desc="clean renders", unit="view", dynamic_ncols=True
    )
    try:
        images = runs.render_views(source, split.cameras, on_view=lambda *_: bar.update(1))
    finally:
        bar.close()
    return np.stack(images).astype(np.float16)


def source_psnr(references: np.ndarray, images: np.ndarray) -> float:
    """The clean model's mean per-view PSNR (dB) on its training views: ``references [V, H, W, 3]`` (its
    renders, :func:`clean_references`) against ``images [V, H, W, 3]`` (the ground truth, in [0, 1])."""
    # One view at a time, as evaluation scores them (metrics.psnr), so memory stays one view's.
    per_view = [
        float(metrics.psnr(jnp.asarray(render, jnp.float32), jnp.asarray(truth, jnp.float32)))
        for render, truth in zip(references, images, strict=True)
    ]
    return float(np.mean(per_view))


def step_choice(
    seed: int, step: int, num_ids: int, num_views: int, ids_per_step: int = 1
) -> tuple[tuple[int, ...], int]:
    """``(IDs, training view)`` of step ``step``: ``ids_per_step`` distinct IDs and one view, uniform and
    deterministic in ``(seed, step)`` (so resumable). One ID per step draws as the ID-at-a-time runs did."""
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x1D, int(step)]))
    if ids_per_step == 1:
        ids: tuple[int, ...] = (int(rng.integers(num_ids)),)
    else:
        ids = tuple(int(i) for i in rng.choice(num_ids, size=ids_per_step, replace=False))
    return ids, int(rng.integers(num_views))
