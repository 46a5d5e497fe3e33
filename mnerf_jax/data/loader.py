"""``load_scene``: detect a scene's format, load its splits and attach the scene box and bounds."""

from __future__ import annotations

import os
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from mnerf_jax.core.config import DataConfig, RenderConfig
from mnerf_jax.data.blender import load_blender
from mnerf_jax.data.llff import NDC_AABB, NDC_NEAR_FAR, load_llff
from mnerf_jax.data.nerfstudio import CAPTURE_AABB, CAPTURE_NEAR_FAR, load_nerfstudio
from mnerf_jax.data.procedural import procedural_scene_dir
from mnerf_jax.data.types import DataError, DataWarning, Scene

DATASETS = ("auto", "blender", "llff", "nerfstudio", "procedural")
_MARKERS = (
    ("transforms_train.json", "blender"),
    ("poses_bounds.npy", "llff"),
    ("transforms.json", "nerfstudio"),
)


def detect_dataset(root: Path) -> str:
    """The format of the scene in ``root`` from its marker file."""
    for marker, kind in _MARKERS:
        if (root / marker).is_file():
            return kind
    looked = ", ".join(m for m, _ in _MARKERS)
    raise DataError(f"{root}: not a known scene layout (looked for {looked})")


def load_scene(
    path: str | os.PathLike | None,
    data_cfg: DataConfig,
    render_cfg: RenderConfig | None = None,
    splits: Sequence[str] = ("train", "test"),
    *,
    max_views: int | None = None,
) -> Scene:
    """Load a scene.

    path:       the scene directory (ignored, may be None, for the procedural scene)
    data_cfg:   format ("auto" detects it), downscale, background, LLFF factor / hold-out, NDC
    render_cfg: the scene box and near/far. None: RenderConfig's defaults, or TensoRF's NDC box
                [-1.5, -1.67, -1]..[1.5, 1.67, 1] with near/far 0, 1 for NDC scenes, or the box
                [-1.5, 1.5]^3 with near/far 0.05, 6 for normalised nerfstudio captures (the ``capture``
                preset's). A nerfstudio / instant-ngp file kept in its frame with ``aabb_scale``
                defines its own box.
    splits:     which splits to load
    max_views:  keep only ``max_views`` evenly spread views of each split (``view_indices``: quick looks,
                tests, evaluations of a few views, which then read only those images)
    """
    kind = data_cfg.dataset
    if kind not in DATASETS:
        raise DataError(f"unknown dataset {kind!r} (known: {', '.join(DATASETS)})")
    if not splits:
        raise DataError("no splits requested")
    if max_views is not None and max_views < 1:
        raise DataError(f"max_views must be >= 1, got {max_views}")
    if kind == "procedural":
        views = data_cfg.procedural_views
        root = procedural_scene_dir(
            data_cfg.procedural_seed, data_cfg.procedural_size, views, max(1, views // 2)
        )
    else:
        if path is None:
            raise DataError(f"dataset {kind!r} needs a scene directory")
        root = Path(path).expanduser()
        if not root.is_dir():
            raise DataError(f"{root}: no such scene directory")
        if kind == "auto":
            kind = detect_dataset(root)
    if data_cfg.ndc and kind != "llff":
        raise DataError(f"{root}: NDC rays need a forward-facing (llff) scene, this one is {kind}")

    render = render_cfg if render_cfg is not None else RenderConfig()
    aabb = np.asarray(render.aabb, np.float32).reshape(2, 3)
    near, far = render.near, render.far
    ndc_space = depth_bounds = transform = None
    downscale, white_bg = data_cfg.downscale, data_cfg.white_bg

    if kind in ("blender", "procedural"):
        loaded = load_blender(root, splits, white_bg, downscale, max_views)
    elif kind == "nerfstudio":
        loaded, file_aabb, transform = load_nerfstudio(
            root,
            splits,
            white_bg,
            data_cfg.llff_hold,
            downscale,
            max_views,
            orientation=data_cfg.orientation,
            centring=data_cfg.centring,
        )
        if file_aabb is not None:
            aabb = file_aabb.astype(np.float32)
        elif transform is not None and render_cfg is None:
            aabb = np.asarray(CAPTURE_AABB, np.float32)
            near, far = CAPTURE_NEAR_FAR
        if transform is not None:
            _warn_if_near_passes_the_centre(loaded, near)
    else:
        loaded, ndc_space, depth_bounds = load_llff(
            root,
            splits,
            data_cfg.llff_factor,
            data_cfg.llff_hold,
            white_bg,
            data_cfg.ndc,
            downscale,
            max_views,
        )
        if data_cfg.ndc:
            if render_cfg is None:
                aabb = np.asarray(NDC_AABB, np.float32)
                near, far = NDC_NEAR_FAR
            elif not 0.0 <= near < far <= 1.0:
                raise DataError(
                    f"{root}: NDC rays span t in [0, 1] but render near/far are {near}, {far} "
                    "(use the llff preset)"
                )
        elif render_cfg is None:
            near, far = 0.9 * depth_bounds[0], depth_bounds[1]
    if not np.all(aabb[1] > aabb[0]):
        raise DataError(f"scene box must have min < max on every axis, got {aabb.tolist()}")
    return Scene(
        kind=kind,
        splits=loaded,
        aabb=aabb,
        near=near,
        far=far,
        ndc=bool(data_cfg.ndc and kind == "llff"),
        white_bg=white_bg,
        ndc_space=ndc_space,
        depth_bounds=depth_bounds,
        root=root,
        transform=transform,
    )


def _warn_if_near_passes_the_centre(splits: dict[str, Any], near: float) -> None:
    """One warning when a normalised capture's rays start beyond the scene's centre for most cameras (a
    preset's near plane kept from a scene of another scale: the object at the origin would not be seen).
    Cameras at the centre itself (a single frame, say) leave nothing to judge."""
    centres = np.concatenate([split.cameras.centres for split in splits.values()])
    typical = float(np.median(np.linalg.norm(centres, axis=-1)))
    if typical > 1e-6 and near >= typical:
        warnings.warn(
            f"render.near = {near:g} is at least the cameras' typical distance to the normalised capture's "
            f"centre ({typical:.2f}): rays start past the object; the capture preset's near is "
            f"{CAPTURE_NEAR_FAR[0]:g}",
            DataWarning,
            stacklevel=3,
        )
