"""Estimated cost of a study's cells (``mnerf study --dry-run``): a count of rendered pixels, no timing.

The model, in millions of pixels (Mpx; one pixel is one ray marched and coloured):

- fit: ``train.n_iters × train.batch_size`` rays, once per scene (none for a scene given as a fitted run);
- embedding: ``(phase-1 + phase-2 steps) × H × W × k`` with ``k`` the IDs a step renders
  (``watermark.schedule.ids_per_step``, 0: every ID up to 16): an upper bound, as the IDs of a step share
  its ray marching; phase 3's decoder steps are left out;
- evaluation: ``views × (IDs + 1) × H × W`` (every ID and the clean model render each view).

``H × W`` is the scene's image size after ``data.downscale`` (read from the procedural config, the first
training image's header, or a nerfstudio file's ``w``, ``h``); the views, from the split's frame count where
the layout tells it. A figure that cannot be read is left out (shown as ``?``). Dividing by a machine's
measured pixel rate (``--rate``) turns the counts into hours.

Shards balance a weight closer to time (``shard_weights``): an embedding step costs as if it rendered
``STEP_OVERHEAD_IDS`` more IDs (the decoder's read, the optimiser and the ray marching the IDs share), an
evaluated pixel ``EVAL_PIXEL_WEIGHT`` of an embedding's (no backward pass); an ID entering the first colour
layer (``early``, ``waterf_mod``) ``FIRST_LAYER_ID_WEIGHT`` IDs of a last-layer variant (it runs the whole
MLP on every sample, nothing shared and nothing cached); the shared fit is left out.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

from PIL import Image

from mnerf_jax.core.config import Config
from mnerf_jax.core.errors import MnerfError
from mnerf_jax.study import grid
from mnerf_jax.study.grid import Cell
from mnerf_jax.study.spec import StudySpec
from mnerf_jax.watermark import model as watermark

# Fitted to the seconds of the paper_cpu study's cells of 1 to 8 IDs (docs/results/paper_cpu/README.md).
STEP_OVERHEAD_IDS = 34.0
EVAL_PIXEL_WEIGHT = 4.0
# Fitted to a waterf_mod step of 16 IDs beside those cells' steps (docs/results/paper_cpu/README.md).
FIRST_LAYER_ID_WEIGHT = 15.0

_IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".JPG", ".PNG", ".JPEG")


@dataclasses.dataclass(frozen=True)
class SceneShape:
    """A scene's rendered image size ``height × width`` (pixels) and the evaluated split's view count."""

    height: int | None
    width: int | None
    views: int | None

    @property
    def pixels(self) -> int | None:
        return None if self.height is None or self.width is None else self.height * self.width


def _image_size(path: Path) -> tuple[int, int] | None:
    """``(height, width)`` of an image file from its header, None when unreadable."""
    try:
        with Image.open(path) as image:
            width, height = image.size
    except OSError:
        return None
    return height, width


def _blender_shape(data: Path, split: str) -> tuple[tuple[int, int] | None, int | None]:
    size, views = None, None
    try:
        frames = json.loads((data / "transforms_train.json").read_text())["frames"]
        first = data / frames[0]["file_path"]
        size = _image_size(first if first.suffix else first.with_suffix(".png"))
        views = len(json.loads((data / f"transforms_{split}.json").read_text())["frames"])
    except (OSError, KeyError, IndexError, TypeError, json.JSONDecodeError):
        pass
    return size, views


def _nerfstudio_size(data: Path) -> tuple[int, int] | None:
    try:
        meta = json.loads((data / "transforms.json").read_text())
        frame = meta.get("frames", [{}])[0]
        return int(frame.get("h", meta["h"])), int(frame.get("w", meta["w"]))
    except (OSError, KeyError, IndexError, TypeError, ValueError, json.JSONDecodeError):
        return None


def _first_image_size(folder: Path) -> tuple[int, int] | None:
    if not folder.is_dir():
        return None
    files = sorted(p for p in folder.iterdir() if p.suffix in _IMAGE_SUFFIXES)
    return _image_size(files[0]) if files else None


def scene_shape(config: Config, data: Path | None, split: str) -> SceneShape:
    """The rendered size and the split's view count of the scene ``config`` reads from ``data``."""
    d = config.data
    if d.dataset == "procedural":
        views = d.procedural_views // 2 if split != "train" else d.procedural_views
        return SceneShape(d.procedural_size, d.procedural_size, views)
    if data is None:
        return SceneShape(None, None, None)
    size, views = None, None
    if (data / "transforms_train.json").is_file():
        size, views = _blender_shape(data, split)
    elif (data / "transforms.json").is_file():
        size = _nerfstudio_size(data)
    elif (data / "poses_bounds.npy").is_file():
        size = _first_image_size(data / f"images_{d.llff_factor}") or _first_image_size(data / "images")
    if size is None:
        return SceneShape(None, None, views)
    height, width = (max(1, round(side / d.downscale)) for side in size)
    return SceneShape(height, width, views)


def _mpx(value: float | None) -> float | None:
    return None if value is None else value / 1e6


def fit_mpx(config: Config, fitted: bool) -> float:
    """The fit's rays in Mpx (0 for a scene given as a fitted run)."""
    return 0.0 if fitted else float(_mpx(config.train.n_iters * config.train.batch_size) or 0.0)


def cell_mpx(cell: Cell, config: Config, shape: SceneShape, views: int) -> dict[str, Any]:
    """``{"embed": Mpx, "evaluate": Mpx or None}`` of one cell under the resolved embedding ``config``
    (``views``: the spec's evaluated views, 0: all of the split)."""
    wm = config.watermark
    steps = wm.schedule.phase1_steps + wm.schedule.phase2_steps
    per_step = watermark.ids_per_step_of(wm, cell.num_ids)
    pixels = shape.pixels
    n_views = views or shape.views
    if views and shape.views is not None:
        n_views = min(views, shape.views)
    return {
        "embed": _mpx(None if pixels is None else steps * pixels * per_step),
        "evaluate": _mpx(
            None if pixels is None or n_views is None else n_views * (cell.num_ids + 1) * pixels
        ),
    }


def format_mpx(value: float | None) -> str:
    return "?" if value is None else f"{value:,.1f}"


def fit_setup(
    cell: Cell, split: str, cache: dict[str, tuple[Config, SceneShape]]
) -> tuple[Config, SceneShape]:
    """The config the cell's scene is fitted with and its image size and ``split``'s views, kept in
    ``cache`` per fit. MnerfError when the scene's preset cannot load."""
    key = grid.fit_id(cell.scene)
    if key not in cache:
        config = grid.fit_config(cell.scene)
        cache[key] = (config, scene_shape(config, cell.scene.data_path(), split))
    return cache[key]


def cell_weight(cell: Cell, config: Config, shape: SceneShape, views: int) -> float | None:
    """The cell's cost for balancing shards, in embedding pixel-equivalents (module docstring); None when
    the image size is unknown."""
    mpx = cell_mpx(cell, config, shape, views)
    if mpx["embed"] is None:
        return None
    per_step = watermark.ids_per_step_of(config.watermark, cell.num_ids)
    id_weight = FIRST_LAYER_ID_WEIGHT if watermark.injection(config.watermark) == "first" else 1.0
    embed = mpx["embed"] * (id_weight * per_step + STEP_OVERHEAD_IDS) / per_step
    return embed + EVAL_PIXEL_WEIGHT * (mpx["evaluate"] or 0.0)


def shard_weights(spec: StudySpec, cells: list[Cell]) -> dict[str, float]:
    """Each cell's ``cell_weight`` (cell ID -> weight) for ``grid.assign_shards``; a cell whose cost cannot be
    estimated (it cannot run, or its image size is unknown) weighs the mean of the others (1 if none can)."""
    setups: dict[str, tuple[Config, SceneShape]] = {}
    weights: dict[str, float | None] = {}
    for cell in cells:
        try:
            config, shape = fit_setup(cell, spec.measure.split, setups)
            weights[cell.id] = cell_weight(cell, grid.embed_config(cell, config), shape, spec.measure.views)
        except MnerfError:
            weights[cell.id] = None
    known = [w for w in weights.values() if w is not None]
    fallback = sum(known) / len(known) if known else 1.0
    return {cid: fallback if w is None else w for cid, w in weights.items()}
