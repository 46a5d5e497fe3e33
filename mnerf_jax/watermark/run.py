"""A watermarked run (``WMRUN``) on disk: its checkpoint layout, loading it, its keys and decoder, its IDs.

``WMRUN`` holds ``run.json`` (kind ``multinerf``, the source run, the decoder it started from),
``config.json``, ``checkpoints/`` (field, decoder, optimiser, step, PRNG key, geometry), ``keys.json`` (tied
to the fingerprint of ``decoder.npz``, the decoder as fine-tuned with the field) and ``embed.json``
(progress). :func:`load_run` loads a run of either kind; a watermarked one comes as a
``tensorf.run.LoadedRun`` set to render ID 0, and :func:`with_id` picks another. ``embed`` writes these runs.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax

from mnerf_jax.core import config as config_lib
from mnerf_jax.core import rundir
from mnerf_jax.core.checkpoint import CheckpointStore
from mnerf_jax.core.config import Config, TrainConfig
from mnerf_jax.core.errors import MnerfError
from mnerf_jax.core.watermark_config import WatermarkConfig, normalised
from mnerf_jax.reader import decoder as decoder_lib
from mnerf_jax.reader import decoder_io
from mnerf_jax.reader import keys as keys_lib
from mnerf_jax.tensorf import field, raymarch
from mnerf_jax.tensorf import run as runs
from mnerf_jax.watermark import model as watermark

WM_KIND = rundir.WATERMARK_KIND
STATE_VERSION = 1
META_FILE = "embed.json"
DECODER_FILE = "decoder.npz"
OptimizerFactory = Callable[[WatermarkConfig], optax.GradientTransformation]


class EmbedError(MnerfError):
    """Bad input to the embedding (a source that is not a fitted TensoRF, an unusable WMRUN, bad images)."""


def fingerprint_config(config: Config) -> Config:
    """The config with everything that does not change the embedding's trajectory at its default
    (``trajectory`` metadata: the time budget, phase 3, how renders are read, checkpointing), so a run may be
    resumed with those changed; and the fit's schedule, which the embedding does not read."""
    return dataclasses.replace(
        config, train=TrainConfig(), watermark=normalised(config.watermark, "trajectory")
    )


def normalised_meta(meta: dict[str, Any]) -> dict[str, Any]:
    """Checkpoint meta whose config is normalised like ``fingerprint_config``, so its fields compare
    equal to the current config's even when its digest was computed under older fingerprint rules."""
    try:
        saved = fingerprint_config(config_lib.from_dict(meta["config"]))
    except (KeyError, TypeError, config_lib.ConfigError):  # check_compatible reports it
        return meta
    return {**meta, "config": saved.to_dict()}


SECTIONS = ("data", "model", "render", "watermark")


def state_target(
    config: Config, meta: dict[str, Any], optimizer: OptimizerFactory | None = None
) -> dict[str, Any]:
    """Pytree structure of an embedding checkpoint (the shapes come from the checkpoint); with the state of
    ``optimizer(config.watermark)`` when given (resuming), without it otherwise (loading for rendering)."""
    cfg = config.watermark
    resolution = tuple(meta["resolution"])

    def init() -> tuple[Any, Any]:
        base = field.init_field(jax.random.key(0), config.model, resolution)
        params = watermark.add_watermark(jax.random.key(1), base, cfg, int(meta["num_ids"]))
        return params, decoder_lib.init_decoder(jax.random.key(2), int(meta["bits"]))

    params, dec = jax.eval_shape(init)
    scalar = jax.ShapeDtypeStruct((), jnp.float32)
    target = {
        "params": params,
        "decoder": dec,
        "step": jax.ShapeDtypeStruct((), jnp.int32),
        "key": jax.ShapeDtypeStruct((2,), jnp.uint32),
        "geometry": dict.fromkeys(raymarch.GEOMETRY_ARRAYS, scalar),
    }
    if optimizer is not None:
        values = {"field": params, "decoder": dec["params"]}
        target["opt_state"] = jax.eval_shape(optimizer(cfg).init, values)
    return target


def restore(
    store: CheckpointStore, run_dir: Path, step: int | None = None, optimizer: OptimizerFactory | None = None
) -> tuple[Config, dict, dict]:
    """``(config, checkpoint tree, meta)`` of an embedding checkpoint (with the optimiser state when
    ``optimizer``, the embedding's ``make_optimizer``, is given)."""
    meta = store.read_meta(step)
    if meta.get("kind") != WM_KIND:
        raise EmbedError(f"{run_dir}: its checkpoint holds a {meta.get('kind')!r} model, not a watermark")
    config = config_lib.from_dict(meta["config"])
    tree, meta = store.restore(state_target(config, meta, optimizer), int(meta["step"]))
    return config, tree, meta


def restore_field_end(run_dir: Path, cfg: WatermarkConfig, step: int | None = None) -> tuple[int, dict]:
    """``(step, checkpoint tree)`` of the checkpoint phase 3 starts from: ``step`` when given, else the last
    one within the field's schedule (``cfg``'s phases 1 and 2). EmbedError when there is none."""
    store = CheckpointStore(run_dir, create=False)
    try:
        field_end = sum(watermark.phase_steps(cfg))
        kept = store.all_steps()
        within = [s for s in kept if s <= field_end]
        chosen = step if step is not None else (max(within) if within else None)
        if chosen is None or chosen not in kept:
            raise EmbedError(
                f"{run_dir}: no checkpoint {chosen} within the field's {field_end} steps (kept: {kept})"
            )
        _, tree, _ = restore(store, run_dir, chosen)
    finally:
        store.close()
    return chosen, tree


def _keys_and_decoder(run_dir: Path) -> tuple[keys_lib.KeySet, decoder_io.LoadedDecoder]:
    """``keys.json`` and ``decoder.npz`` of a watermarked run, checked against each other."""
    if not (run_dir / DECODER_FILE).is_file():
        raise EmbedError(f"{run_dir} has no {DECODER_FILE} (the embedding has not written a checkpoint yet)")
    dec = decoder_io.load_decoder(run_dir / DECODER_FILE)
    keys = keys_lib.load_keys(run_dir, decoder_fingerprint=dec.fingerprint, expect_bits=dec.bits)
    return keys, dec


def _load_multinerf(run_dir: Path, marker: dict[str, Any], step: int | None) -> runs.LoadedRun:
    """A watermarked run loaded for rendering: ``cond`` renders ID 0; ``extras`` hold the keys, the
    decoder, the source run and the number of IDs (see :func:`with_id`)."""
    keys, dec = _keys_and_decoder(run_dir)
    store = CheckpointStore(run_dir, create=False)
    try:
        if store.latest_step() is None:
            raise EmbedError(f"{run_dir} holds no checkpoint yet")
        config, tree, meta = restore(store, run_dir, step)
    finally:
        store.close()
    if int(meta["num_ids"]) != keys.num_ids or int(meta["bits"]) != keys.bits:
        raise EmbedError(
            f"{run_dir}: keys.json ({keys.num_ids} IDs × {keys.bits} bits) does not match the "
            f"checkpoint ({meta['num_ids']} × {meta['bits']})"
        )
    params = jax.tree.map(jnp.asarray, tree["params"])
    loaded = runs.LoadedRun(
        run_dir=run_dir,
        kind=WM_KIND,
        config=config,
        marker=marker,
        params=params,
        geometry=raymarch.geometry_from_checkpoint(tree["geometry"], meta["geometry"]),
        field_fns=watermark.field_fns(config.model, config.watermark),
        cond=None,
        step=int(meta["step"]),
        meta=meta,
        extras={
            "keys": keys,
            "decoder": dec,
            "num_ids": keys.num_ids,
            "id": None,
            "source_run": marker.get("source_run"),
        },
    )
    return with_id(loaded, 0)


def load_run(run_dir: str | Path, step: int | None = None) -> runs.LoadedRun:
    """Load the run in ``run_dir``, fitted or watermarked, at checkpoint ``step`` (default: the latest)."""
    run_dir = Path(run_dir)
    marker = rundir.require_marker(run_dir)
    if marker["kind"] == rundir.TENSORF_KIND:
        return runs.load_tensorf_run(run_dir, step)
    if marker["kind"] == WM_KIND:
        return _load_multinerf(run_dir, marker, step)
    raise rundir.RunError(f"{run_dir} holds a {marker['kind']!r} run, which this version cannot load")


def is_watermarked(run: runs.LoadedRun) -> bool:
    return run.kind == WM_KIND


def with_id(run: runs.LoadedRun, index: Any) -> runs.LoadedRun:
    """The loaded watermarked run set to render ID ``index`` (``mnerf render --id K``).

    KeysError for an ID outside ``[0, N)``; EmbedError for a run without watermarks.
    """
    if not is_watermarked(run):
        raise EmbedError(f"{run.run_dir} is not a watermarked run: it has no IDs to choose from")
    index = keys_lib.check_id(index, int(run.extras["num_ids"]))
    cond = watermark.condition(run.params, index, run.config.watermark)
    return dataclasses.replace(run, cond=cond, extras={**run.extras, "id": index})


def render_with_ids(
    run: runs.LoadedRun,
    ids: Sequence[int],
    cameras: Any,
    indices: Sequence[int] | None = None,
    *,
    on_view: Callable[[int, np.ndarray], None] | None = None,
    **kwargs: Any,
) -> dict[int, list[np.ndarray]]:
    """Evaluation renders of ``cameras`` for several IDs at once: ``{ID: [[H, W, 3], ...]}``.

    One geometry pass per view serves every ID in ``ids`` (the IDs differ only in the colour MLP's last
    layer, ``watermark.condition_many``); each ID's images equal :func:`render_with_id`'s to float rounding.
    ``on_view(view, rgb [H, W, 3K])`` once per view.
    """
    if not is_watermarked(run):
        raise EmbedError(f"{run.run_dir} is not a watermarked run: it has no IDs to choose from")
    ids = [keys_lib.check_id(i, int(run.extras["num_ids"])) for i in ids]
    if len(ids) == 1:
        return {ids[0]: render_with_id(run, ids[0], cameras, indices, on_view=on_view, **kwargs)}
    return _render_columns(run, ids, False, cameras, indices, on_view, **kwargs)[0]


def _render_columns(
    run: runs.LoadedRun,
    ids: Sequence[int],
    with_clean: bool,
    cameras: Any,
    indices: Sequence[int] | None,
    on_view: Callable[[int, np.ndarray], None] | None,
    **kwargs: Any,
) -> tuple[dict[int, list[np.ndarray]], list[np.ndarray] | None]:
    """One geometry pass per view for the IDs ``ids`` and, with ``with_clean``, the null conditioning after
    them: ``({ID: [[H, W, 3], ...]}, clean [[H, W, 3], ...] or None)``; ``on_view`` sees the IDs' columns."""
    cond = watermark.condition_many(run.params, np.asarray(ids, np.int32), run.config.watermark)
    if with_clean:
        cond = watermark.with_null_condition(cond)
    width = 3 * len(ids)
    view_cb = None if on_view is None else (lambda v, rgb: on_view(v, rgb[..., :width]))  # noqa: E731
    stacked = runs.render_views(
        dataclasses.replace(run, cond=cond), cameras, indices, on_view=view_cb, **kwargs
    )
    renders = {n: [img[..., 3 * k : 3 * k + 3] for img in stacked] for k, n in enumerate(ids)}
    return renders, [img[..., width:] for img in stacked] if with_clean else None


# IDs rendered together by render_every_id: one geometry pass per view serves them all.
IDS_PER_RENDER = 16


def render_every_id(
    run: runs.LoadedRun,
    cameras: Any,
    indices: Sequence[int] | None = None,
    *,
    on_view: Callable[[int, np.ndarray], None] | None = None,
) -> dict[int, np.ndarray]:
    """Evaluation renders of ``cameras`` by every ID of the run, :data:`IDS_PER_RENDER` IDs per geometry pass
    (one at a time where renders do not depend on the ID): ``{ID: [V, H, W, 3]}``. ``on_view`` as
    :func:`render_with_ids`."""
    return _render_every_id(run, cameras, indices, on_view, with_clean=False)[0]


def render_every_id_and_clean(
    run: runs.LoadedRun,
    cameras: Any,
    indices: Sequence[int] | None = None,
    *,
    on_view: Callable[[int, np.ndarray], None] | None = None,
) -> tuple[dict[int, np.ndarray], np.ndarray]:
    """:func:`render_every_id` plus the fitted field's own render of each view ``[V, H, W, 3]``, taken from
    the first geometry pass as one more column (the null conditioning), for a run where that is exact
    (``watermark.null_renders_source``): a separate render of the clean model costs a whole geometry pass."""
    if not watermark.null_renders_source(run.config.watermark):
        raise EmbedError(f"{run.run_dir}: its fitted field trained, so no conditioning renders the source")
    renders, clean = _render_every_id(run, cameras, indices, on_view, with_clean=True)
    assert clean is not None  # the first group always renders the null column
    return renders, clean


def _render_every_id(
    run: runs.LoadedRun,
    cameras: Any,
    indices: Sequence[int] | None,
    on_view: Callable[[int, np.ndarray], None] | None,
    with_clean: bool,
) -> tuple[dict[int, np.ndarray], np.ndarray | None]:
    """Every ID's renders in groups of :data:`IDS_PER_RENDER`, with ``with_clean`` the null column in the
    first group's pass: ``({ID: [V, H, W, 3]}, clean [V, H, W, 3] or None)``."""
    n_ids = int(run.extras["num_ids"])
    group = IDS_PER_RENDER if watermark.uses_ids(run.config.watermark) else 1
    renders: dict[int, np.ndarray] = {}
    clean = None
    for first in range(0, n_ids, group):
        ids = list(range(first, min(first + group, n_ids)))
        if with_clean and first == 0:
            out, views = _render_columns(run, ids, True, cameras, indices, on_view)
            clean = np.stack(views)
        else:
            out = render_with_ids(run, ids, cameras, indices, on_view=on_view)
        renders.update({n: np.stack(images) for n, images in out.items()})
    return renders, clean


def require_watermarked(run_dir: str | Path) -> dict[str, Any]:
    """``run.json`` of a watermarked run directory; EmbedError saying what ``run_dir`` holds otherwise."""
    run_dir = Path(run_dir)
    marker = rundir.read_marker(run_dir) if run_dir.is_dir() else None
    if marker is not None and marker.get("kind") == WM_KIND:
        return marker
    if marker is not None:
        raise EmbedError(
            f"{run_dir} holds a {marker.get('kind')!r} run without watermarks "
            f"(make one with `mnerf embed --from {run_dir} --out WMRUN`)"
        )
    if (run_dir / keys_lib.KEYS_FILE).is_file():
        raise EmbedError(f"{run_dir} has keys but no {rundir.RUN_MARKER}: not a complete watermarked run")
    raise EmbedError(f"{run_dir} is not a watermarked run (make one with `mnerf embed`)")


def load_watermarked_run(run_dir: str | Path, step: int | None = None) -> runs.LoadedRun:
    """``run.load_run`` for a directory that must hold a watermarked run."""
    require_watermarked(run_dir)
    return load_run(run_dir, step)


def load_keys_and_decoder(run_dir: str | Path) -> tuple[keys_lib.KeySet, decoder_io.LoadedDecoder]:
    """The keys and the (fine-tuned) decoder of a watermarked run, without restoring its field."""
    require_watermarked(run_dir)
    return _keys_and_decoder(Path(run_dir))


def render_with_id(
    run: runs.LoadedRun, index: int, cameras: Any, indices: Sequence[int] | None = None, **kwargs: Any
) -> list[np.ndarray]:
    """Evaluation renders ``[H, W, 3]`` of ``cameras`` (``data.Cameras``) for ID ``index``."""
    return runs.render_views(with_id(run, index), cameras, indices, **kwargs)
