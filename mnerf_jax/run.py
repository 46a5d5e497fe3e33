"""Run directories: what they hold, refusing to overwrite another run, loading one for rendering.

A run directory holds::

    RUN/run.json        {"kind": "tensorf", "version": 1, "fingerprint": ..., "data": "/abs/scene/path"}
    RUN/config.json     the resolved config
    RUN/checkpoints/    orbax checkpoints (``checkpoint.CheckpointStore``)
    RUN/metrics.json    written by ``mnerf fit`` at the end
    RUN/tb/             TensorBoard scalars

``load_run(RUN)`` dispatches on ``run.json``'s ``kind`` to a loader registered with
``register_run_kind``; the TensoRF loader is built in, and the module that registers any other kind
(``LOADER_MODULES``, e.g. ``mnerf_jax.wm_run`` for watermarked runs) is imported on first use, so
``load_run`` works from every entry point without ``run`` importing those modules up front. A loader
returns a ``LoadedRun``: config, params, geometry, field functions and a conditioning pytree, which is all
rendering needs.
"""

from __future__ import annotations

import dataclasses
import importlib
import json
import math
import os
import tempfile
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from mnerf_jax import __version__
from mnerf_jax.checkpoint import CheckpointStore, config_fingerprint, fingerprint_differences
from mnerf_jax.config import Config, ConfigError, from_dict
from mnerf_jax.errors import MnerfError

RUN_MARKER = "run.json"
CONFIG_FILE = "config.json"
RUN_FORMAT_VERSION = 1
TENSORF_KIND = "tensorf"
WATERMARK_KIND = "multinerf"
# Modules that register a loader for a kind when imported (imported lazily: they import this module).
LOADER_MODULES: dict[str, str] = {WATERMARK_KIND: "mnerf_jax.wm_run"}


class RunError(MnerfError):
    """A run directory that is missing, holds something else, or cannot be loaded."""


# --------------------------------------------------------------------------------------------------
# Files
# --------------------------------------------------------------------------------------------------


def write_json_atomic(path: str | Path, data: Any) -> None:
    """Write JSON to ``path`` through a temporary file and a rename (never a half-written file)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(fd, "w") as f:
            json.dump(data, f, indent=2, sort_keys=True, allow_nan=True)
            f.write("\n")
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def read_marker(run_dir: str | Path) -> dict[str, Any] | None:
    """``run.json`` of a directory, None when it has none; RunError when it is unreadable."""
    path = Path(run_dir) / RUN_MARKER
    if not path.is_file():
        return None
    try:
        marker = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as err:
        raise RunError(f"{path}: unreadable run marker ({err})") from None
    if not isinstance(marker, dict) or "kind" not in marker:
        raise RunError(f"{path}: not a mnerf run marker")
    return marker


def read_run_config(run_dir: str | Path) -> Config:
    """The resolved config saved in ``RUN/config.json``."""
    path = Path(run_dir) / CONFIG_FILE
    try:
        return from_dict(json.loads(path.read_text()))
    except FileNotFoundError:
        raise RunError(f"{run_dir}: no {CONFIG_FILE}; is this a mnerf run directory?") from None
    except (json.JSONDecodeError, ConfigError) as err:
        raise RunError(f"{path}: unreadable config ({err})") from None


def prepare_output(out: str | Path, config: Config, *, resume: bool, kind: str = TENSORF_KIND) -> bool:
    """Check that ``out`` may receive this run; True when it continues a run already there.

    Refused (RunError, nothing written): ``out`` is a file; ``out`` holds files but no run; it holds
    a run of another kind or config; it holds this very run and ``resume`` is not set.
    """
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise RunError(f"--out {out} is a file, not a directory")
    if not out.exists() or not any(out.iterdir()):
        return False
    marker = read_marker(out)
    if marker is None:
        raise RunError(f"--out {out} is not empty and holds no mnerf run; choose a new or empty directory")
    if marker.get("kind") != kind:
        raise RunError(
            f"--out {out} holds a {marker.get('kind')!r} run, not a {kind!r} one; choose another directory"
        )
    if marker.get("fingerprint") != config_fingerprint(config):
        try:
            diffs = "; ".join(fingerprint_differences(read_run_config(out).to_dict(), config))
        except RunError:
            diffs = "its config.json is unreadable"
        # No differences under another digest: written before a field became bookkeeping.
        if diffs:
            raise RunError(f"--out {out} holds another run ({diffs}); choose another directory")
    if not resume:
        raise RunError(f"--out {out} already holds this run; pass --resume to continue it")
    return True


def write_run_files(out: str | Path, config: Config, *, data: str | Path | None, kind: str = TENSORF_KIND,
                    extra: dict[str, Any] | None = None) -> None:  # fmt: skip
    """Write ``config.json`` and the ``run.json`` marker (config first: a marker implies a config)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    write_json_atomic(out / CONFIG_FILE, config.to_dict())
    marker = {
        "kind": kind,
        "version": RUN_FORMAT_VERSION,
        "mnerf_version": __version__,
        "fingerprint": config_fingerprint(config),
        "config_name": config.name,
        "data": None if data is None else str(Path(data).expanduser().resolve()),
        **(extra or {}),
    }
    write_json_atomic(out / RUN_MARKER, marker)


# --------------------------------------------------------------------------------------------------
# Loading
# --------------------------------------------------------------------------------------------------


@dataclasses.dataclass
class LoadedRun:
    """A run ready to render.

    Attributes:
      run_dir: the run directory.
      kind: ``run.json``'s kind (``tensorf``; other modules register more).
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

    def load_scene(self, data: str | Path | None = None, splits: Sequence[str] = ("test",)) -> Any:
        """The run's scene (or another copy of it at ``data``) with ``splits``."""
        from mnerf_jax.data import load_scene

        path = data if data is not None else self.data_path
        if path is None and self.config.data.dataset != "procedural":
            raise RunError(f"{self.run_dir} does not record where its data is; pass --data")
        return load_scene(path, self.config.data, self.config.render, tuple(splits))


RunLoader = Callable[[Path, dict[str, Any], Config, "int | None"], LoadedRun]
_LOADERS: dict[str, RunLoader] = {}


def register_run_kind(kind: str, loader: RunLoader) -> None:
    """Make ``load_run`` load directories whose ``run.json`` says ``kind`` with ``loader``."""
    _LOADERS[kind] = loader


def _load_tensorf(run_dir: Path, marker: dict[str, Any], config: Config, step: int | None) -> LoadedRun:
    from mnerf_jax import fit_checkpoint, render

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
        run_dir=run_dir, kind=TENSORF_KIND, config=config, marker=marker, params=state.params,
        geometry=state.geometry, field_fns=render.tensorf_field_fns(config.model), cond=None,
        step=int(meta["step"]), meta=meta,
    )  # fmt: skip


register_run_kind(TENSORF_KIND, _load_tensorf)


def load_run(run_dir: str | Path, step: int | None = None) -> LoadedRun:
    """Load the run in ``run_dir`` at checkpoint ``step`` (default: the latest)."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise RunError(f"--run {run_dir}: no such directory")
    marker = read_marker(run_dir)
    if marker is None:
        raise RunError(f"{run_dir} is not a mnerf run (no {RUN_MARKER})")
    kind = marker["kind"]
    if kind not in _LOADERS and kind in LOADER_MODULES:
        importlib.import_module(LOADER_MODULES[kind])  # registers the loader
    if kind not in _LOADERS:
        raise RunError(f"{run_dir} holds a {kind!r} run, which this version cannot load")
    return _LOADERS[kind](run_dir, marker, read_run_config(run_dir), step)


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
    from mnerf_jax import budgets, chunked
    from mnerf_jax.data import camera_rays

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
        out = chunked.render_image(run.field_fns, run.params, run.cond, o, d, run.geometry, cameras.height,
                                  cameras.width, chunk=chunk, policy=policy)  # fmt: skip
        rgb = out["rgb"].astype(np.float32)
        images.append(rgb)
        if on_view is not None:
            on_view(int(i), rgb)
    return images


def view_indices(n: int, limit: int | None) -> list[int]:
    """``limit`` evenly spread view indices out of ``n`` (all when limit is None or >= n)."""
    if limit is None or limit <= 0 or limit >= n:
        return list(range(n))
    return sorted({int(round(v)) for v in np.linspace(0, n - 1, limit)})


def evaluate_split(
    run: LoadedRun,
    split: Any,
    *,
    max_views: int | None = None,
    lpips_net: str = "alex",
    on_view: Callable[[int, np.ndarray], None] | None = None,
) -> dict[str, Any]:
    """PSNR / SSIM / LPIPS of the run's renders against ``split``'s images (a ``data.SceneSplit``)."""
    from mnerf_jax import metrics

    indices = view_indices(len(split), max_views)
    preds = render_views(run, split.cameras, indices, on_view=on_view)
    result = metrics.image_metrics(np.stack(preds), split.images[indices], lpips_net=lpips_net)
    result["view_names"] = [split.names[i] for i in indices]
    return result
