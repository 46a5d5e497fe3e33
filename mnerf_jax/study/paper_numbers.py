"""The paper's published figures as data (``paper_numbers.toml``), and the ones a results row stands for.

Each figure carries the table it comes from and the settings it holds for (the paper's scene or dataset
average, the variant, IDs, bits, #WMCom, with or without attacks in training); :func:`match` finds the
figures a measured row can be set beside. Bit accuracies are loaded as fractions, as the results table
holds them.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import tomllib
from collections.abc import Mapping
from pathlib import Path
from typing import Any

DATA_FILE = Path(__file__).with_name("paper_numbers.toml")

# The paper's scenes by dataset (Sec. 4.1): a row on one of them can stand beside the dataset's average.
DATASETS: dict[str, tuple[str, ...]] = {
    "SYN": ("chair", "drums", "ficus", "hotdog", "lego", "materials", "mic", "ship"),
    "LLFF": ("fern", "flower", "fortress", "horns", "leaves", "orchids", "room", "trex"),
}
SETTINGS = ("variant", "num_ids", "bits", "wmcom", "noised")
ANY_VARIANT = "*"


@dataclasses.dataclass(frozen=True)
class PaperFigure:
    """One published figure and the settings it holds for (None: any)."""

    table: str  # the paper's label, e.g. "tab:ablation"
    caption: str
    label: str  # the row's name in the paper
    metric: str
    value: float
    scene: str | None = None  # a paper scene in lower case, or "SYN" / "LLFF" for the dataset's average
    variant: str | None = None  # None: no counterpart here; "*": any variant
    num_ids: int | None = None
    bits: int | None = None
    wmcom: int | None = None
    noised: bool | None = None
    approx: bool = False  # read from the text, not from a table


def _figures_of(block: Mapping[str, Any]) -> list[PaperFigure]:
    columns = list(block["columns"])
    by_scene = "metric" in block
    out = []
    for row in block["rows"]:
        values = list(row["values"])
        if len(values) != len(columns):
            raise ValueError(f"{DATA_FILE}: {block['id']} row {row['label']!r} has {len(values)} values")
        merged = {k: row.get(k, block.get(k)) for k in (*SETTINGS, "scene", "approx")}
        for column, value in zip(columns, values, strict=True):
            if math.isnan(value):
                continue
            metric = block["metric"] if by_scene else column
            scale = 0.01 if metric.startswith("bit_acc") else 1.0
            out.append(
                PaperFigure(
                    table=block["id"],
                    caption=block["caption"],
                    label=row["label"],
                    metric=metric,
                    value=value * scale,
                    scene=column if by_scene else merged["scene"],
                    variant=merged["variant"],
                    num_ids=merged["num_ids"],
                    bits=merged["bits"],
                    wmcom=merged["wmcom"],
                    noised=merged["noised"],
                    approx=bool(merged["approx"]),
                )
            )
    return out


@functools.cache
def figures() -> tuple[PaperFigure, ...]:
    """Every published figure, in the file's order."""
    data = tomllib.loads(DATA_FILE.read_text())
    return tuple(f for block in data["tables"] for f in _figures_of(block))


def dataset_of(scene: str | None) -> str | None:
    """``"SYN"`` / ``"LLFF"`` for one of the paper's scenes (or for the dataset's own name), else None."""
    if scene is None:
        return None
    if scene in DATASETS:
        return scene
    return next((name for name, scenes in DATASETS.items() if scene in scenes), None)


def _holds_for(figure: PaperFigure, row: Mapping[str, Any]) -> bool:
    if figure.variant is None or figure.variant not in (ANY_VARIANT, row.get("variant")):
        return False
    return all(
        getattr(figure, key) is None or getattr(figure, key) == row.get(key)
        for key in SETTINGS
        if key != "variant"
    )


def match(row: Mapping[str, Any]) -> dict[str, PaperFigure]:
    """The published figure of each metric that a results ``row`` stands beside: the first in the file
    whose settings hold for the row's (``paper_scene``, ``variant``, ``num_ids``, ``bits``, ``wmcom``,
    ``noised``), the row's own scene before its dataset's average. ``{}`` for a row with no paper scene."""
    scene = row.get("paper_scene")
    dataset = dataset_of(scene)
    if scene is None or dataset is None:
        return {}
    found: dict[str, PaperFigure] = {}
    for wanted in (scene, dataset):
        for figure in figures():
            if figure.metric in found or figure.scene not in (wanted, None) or not _holds_for(figure, row):
                continue
            if figure.scene is None and wanted != scene:
                continue
            found[figure.metric] = figure
    return found


def paper_scene(name: str, given: str | None) -> str | None:
    """The paper scene a study's scene stands for: the spec's ``paper``, else its name if the paper has it."""
    if given is not None:
        return given
    return name.lower() if dataset_of(name.lower()) is not None else None
