"""A fitted TensoRF run loaded for rendering, and rendering or evaluating its views.

A ``LoadedRun`` holds config, params, geometry, field functions and a conditioning pytree, which is all
rendering needs; ``load_tensorf_run`` makes one from a fitted run directory (``watermark.run.load_run``
loads either kind).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from mnerf_jax.core.checkpoint import CheckpointStore
from mnerf_jax.core.config import Config
from mnerf_jax.core.rundir import TENSORF_KIND, RunError, read_run_config, require_marker
from mnerf_jax.data import PATH_SPLIT, camera_path, camera_rays, load_scene, view_indices
from mnerf_jax.imaging import metrics
from mnerf_jax.tensorf import budgets, chunked, render
from mnerf_jax.tensorf.fit import checkpoint as fit_checkpoint

# --------------------------------------------------------------------------------------------------
# Loading
# --------------------------------------------------------------------------------------------------


@dataclasses.dataclass
class LoadedRun:
    """A run ready to render.

    Attributes:
      run_dir: the run directory.
      kind: ``run.json``'s kind (``tensorf`` or ``multinerf``).
      config: the run's config.
      marker: ``run.json``.
      params: field params.
      geometry: ``raymarch.Geometry`` (aabb, alpha mask, samples per ray).
      field_fns: ``render.FieldFns``.
      cond: conditioning pytree for ``field_fns.colour`` (None for TensoRF).
      step: the checkpoint's step.
      meta: the checkpoint's JSON item.
      extras: anything a run kind needs besides (for example per-ID conditioning).
    """

    run_dir: Path
    kind: str
    config: Config
    marker: dict[str, Any]
    params: Any
    geometry: Any
    field_fns: Any
    cond: Any = None
    step: int = 0
    meta: dict[str, Any] = dataclasses.field(default_factory=dict)
    extras: dict[str, Any] = dataclasses.field(default_factory=dict)

    @property
    def data_path(self) -> str | None:
        return self.marker.get("data")

    def load_scene(
        self,
        data: str | Path | None = None,
        splits: Sequence[str] = ("test",),
        max_views: int | None = None,
    ) -> Any:
        """The run's scene (or another copy of it at ``data``) with ``splits``, each ``max_views`` evenly
        spread views of it (None: all; ``data.view_indices``)."""
        path = data if data is not None else self.data_path
        if path is None and self.config.data.dataset != "procedural":
            raise RunError(f"{self.run_dir} does not record where its data is; pass --data")
        return load_scene(
            path, self.config.data, self.config.render, tuple(splits), max_views=max_views or None
        )

    def split_views(
        self, split: str, data: str | Path | None = None, max_views: int | None = None
    ) -> tuple[Any, list[int], list[str], np.ndarray | None]:
        """The cameras, view indices, view names and ground truth ``[V, H, W, 3]`` float32 of ``split``'s
        ``max_views`` evenly spread views (0 or None: all); for ``data.PATH_SPLIT``, ``max_views`` frames
        along ``data.camera_path`` of the training cameras, named ``frame_NNNN``, with no ground truth."""
        if split == PATH_SPLIT:
            cameras = camera_path(self.load_scene(data, splits=("train",)), max_views or 0)
            indices = list(range(len(cameras)))
            return cameras, indices, [f"frame_{i:04d}" for i in indices], None
        scene_split = self.load_scene(data, splits=(split,), max_views=max_views).split(split)
        indices = view_indices(len(scene_split), max_views or None)
        names = [scene_split.names[i] for i in indices]
        return scene_split.cameras, indices, names, np.asarray(scene_split.images[indices], np.float32)


def load_tensorf_run(run_dir: str | Path, step: int | None = None) -> LoadedRun:
    """Load the fitted TensoRF run in ``run_dir`` at checkpoint ``step`` (default: the latest)."""
    run_dir = Path(run_dir)
    marker = require_marker(run_dir)
    if marker["kind"] != TENSORF_KIND:
        raise RunError(f"{run_dir} holds a {marker['kind']!r} run, not a fitted TensoRF")
    config = read_run_config(run_dir)
    store = CheckpointStore(run_dir, keep=config.train.keep_checkpoints, create=False)
    try:
        if store.latest_step() is None:
            raise RunError(
                f"{run_dir} holds no checkpoint yet (was the fit interrupted before the first one?)"
            )
        state, meta, _ = fit_checkpoint.restore_state(config, store, step)
    finally:
        store.close()
    return LoadedRun(
        run_dir=run_dir,
        kind=TENSORF_KIND,
        config=config,
        marker=marker,
        params=state.params,
        geometry=state.geometry,
        field_fns=render.tensorf_field_fns(config.model),
        cond=None,
        step=int(meta["step"]),
        meta=meta,
    )


# --------------------------------------------------------------------------------------------------
# Rendering and evaluating views
# --------------------------------------------------------------------------------------------------


def render_views(
    run: LoadedRun,
    cameras: Any,
    indices: Sequence[int] | None = None,
    *,
    chunk: int | None = None,
    on_view: Callable[[int, np.ndarray], None] | None = None,
) -> list[np.ndarray]:
    """Render cameras ``indices`` (default all) of ``cameras`` -> list of ``[H, W, 3]`` float32 in [0, 1]."""
    indices = range(len(cameras)) if indices is None else indices
    chunk = chunk or run.config.render.chunk
    # Equal chunks that tile the image: no padded rays, one compiled shape per image size.
    pixels = cameras.width * cameras.height
    chunk = math.ceil(pixels / math.ceil(pixels / max(chunk, 1)))
    # Budgets settle after a few chunks; a short patience lets them shrink early.
    policy = budgets.BudgetPolicy(patience=4)
    images = []
    for i in indices:
        o, d = camera_rays(cameras, int(i))
        out = chunked.render_image(
            run.field_fns,
            run.params,
            run.cond,
            o,
            d,
            run.geometry,
            cameras.height,
            cameras.width,
            chunk=chunk,
            policy=policy,
        )
        rgb = out["rgb"].astype(np.float32)
        images.append(rgb)
        if on_view is not None:
            on_view(int(i), rgb)
    return images


def evaluate_split(
    run: LoadedRun,
    split: Any,
    *,
    max_views: int | None = None,
    lpips_net: str = "alex",
    on_view: Callable[[int, np.ndarray], None] | None = None,
) -> dict[str, Any]:
    """PSNR / SSIM / LPIPS of the run's renders against ``split``'s images (a ``data.SceneSplit``)."""
    indices = view_indices(len(split), max_views)
    preds = render_views(run, split.cameras, indices, on_view=on_view)
    result = metrics.image_metrics(np.stack(preds), split.images[indices], lpips_net=lpips_net)
    result["view_names"] = [split.names[i] for i in indices]
    return result
