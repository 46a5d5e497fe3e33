"""A study's grid: its cells (scene × method × IDs × bits × seed), their stable IDs, shards and selection.

A cell's ID is a readable slug and a short hash of the cell's settings,
``lego-multinerf-n16-b16-s0-1a2b3c4d``: the hash covers what the cell computes (the scene's fit settings,
the method's variant, preset and overrides, the IDs, bits, seed and decoder), not the names, so an edited
setting makes a new cell while an unchanged one keeps its folder across runs, spec edits and machines.
Shards split the cells into N groups of about equal estimated cost (``study.cost.shard_weights``): the
costliest cell first, each to the group with the least cost so far (ties by cell ID), which is
deterministic, disjoint and covering. Adding cells to the spec can move others to another shard; shards
that share one folder skip the cells already done whichever shard ran them.
"""

from __future__ import annotations

import dataclasses
import fnmatch
import hashlib
import json
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

from mnerf_jax.core import config as config_lib
from mnerf_jax.core import rundir
from mnerf_jax.core.config import Config
from mnerf_jax.core.errors import MnerfError
from mnerf_jax.study.spec import MethodSpec, SceneSpec, StudySpec
from mnerf_jax.watermark import model as watermark

HASH_CHARS = 8


def digest(settings: Any) -> str:
    """A short hex digest of JSON-able ``settings`` (key order does not matter)."""
    text = json.dumps(settings, sort_keys=True, separators=(",", ":"))
    return hashlib.sha1(text.encode()).hexdigest()[:HASH_CHARS]


def fit_id(scene: SceneSpec) -> str:
    """The folder name of a scene's shared fit: ``<scene>-<hash of its fit settings>``."""
    return f"{scene.name}-{digest(scene.settings())}"


@dataclasses.dataclass(frozen=True)
class Cell:
    """One run of the study: a scene's fit embedded by a method with ``num_ids`` × ``bits``, one seed."""

    scene: SceneSpec
    method: MethodSpec
    num_ids: int
    bits: int
    seed: int
    decoder: str | None  # as written in the spec's [decoders]; None: the shipped decoder

    def settings(self) -> dict[str, Any]:
        """Everything the cell's figures depend on (hashed into its ID)."""
        return {
            "scene": self.scene.settings(),
            "method": self.method.settings(),
            "num_ids": self.num_ids,
            "bits": self.bits,
            "seed": self.seed,
            "decoder": self.decoder,
        }

    @property
    def hash(self) -> str:
        return digest(self.settings())

    @property
    def id(self) -> str:
        slug = f"{self.scene.name}-{self.method.name}-n{self.num_ids}-b{self.bits}-s{self.seed}"
        return f"{slug}-{self.hash}"

    def embed_overrides(self) -> tuple[str, ...]:
        """The embedding's ``--set`` items: the method's, then the seed (init, steps, and the keys)."""
        return (*self.method.overrides(), f"watermark.seed={self.seed}", f"watermark.key_seed={self.seed}")


def expand(spec: StudySpec) -> list[Cell]:
    """Every cell, in spec order: scenes, then the methods that run on the scene, then IDs, bits and seeds
    (a method's own axes replace the study's)."""
    return [
        Cell(scene, method, n, bits, seed, spec.decoder_for(bits))
        for scene in spec.scenes
        for method in spec.methods
        if method.runs_on(scene.name)
        for n in method.ids or spec.ids
        for bits in method.bits or spec.bits
        for seed in spec.seeds
    ]


# ------------------------------------------------------------------------------------- shards, selection


def parse_shard(text: str) -> tuple[int, int]:
    """``"I/N"`` -> ``(I, N)`` with 0 ≤ I < N; MnerfError otherwise."""
    try:
        index, count = (int(part) for part in text.split("/"))
    except ValueError:
        raise MnerfError(f"--shard {text!r}: expected I/N, e.g. 0/4 (shards 0 to N-1 of N)") from None
    if count < 1 or not 0 <= index < count:
        raise MnerfError(f"--shard {text!r}: expected 0 ≤ I < N (shards 0 to N-1 of N)")
    return index, count


def assign_shards(
    cells: Sequence[Cell], count: int, weights: Mapping[str, float] | None = None
) -> dict[str, int]:
    """Each cell's shard (cell ID -> 0..count-1), balancing the summed ``weights`` (cell ID -> estimated
    cost; None: every cell weighs 1): the greedy longest-first rule, the heaviest cell to the lightest shard,
    ties broken by cell ID and then by the lower shard."""
    weight = {c.id: 1.0 for c in cells} if weights is None else weights
    loads = [0.0] * count
    shards: dict[str, int] = {}
    for cell in sorted(cells, key=lambda c: (-weight[c.id], c.id)):
        index = min(range(count), key=lambda i: (loads[i], i))
        shards[cell.id] = index
        loads[index] += weight[cell.id]
    return shards


def select(
    cells: Sequence[Cell],
    shard: tuple[int, int] | None = None,
    only: Iterable[str] = (),
    weights: Mapping[str, float] | None = None,
) -> list[Cell]:
    """The cells of ``shard`` (assigned over every cell of ``cells`` by ``assign_shards`` with ``weights``)
    whose IDs match one of the ``only`` globs (none: every cell), in ``cells``' order."""
    patterns = [p for p in only if p]
    chosen = list(cells)
    if shard is not None:
        assigned = assign_shards(cells, shard[1], weights)
        chosen = [c for c in chosen if assigned[c.id] == shard[0]]
    if patterns:
        chosen = [c for c in chosen if any(fnmatch.fnmatchcase(c.id, p) for p in patterns)]
    return chosen


# ------------------------------------------------------------------------------------------- resolution


def fit_config(scene: SceneSpec) -> Config:
    """The config a scene is (or was) fitted with: the fitted run's, or the preset with its overrides."""
    fitted = scene.fit_path()
    if fitted is not None:
        return rundir.read_run_config(fitted)
    return config_lib.load_config(scene.preset_ref() or "", scene.fit_overrides())


def embed_config(cell: Cell, fitted: Config | None = None) -> Config:
    """The config the cell's embedding runs with, as ``watermark.embed.resolve_config`` builds it: the fit's
    config, the method preset's ``[watermark]`` section (default: the fit's), the cell's overrides, its IDs
    and bits, the phase steps resolved. ConfigError for a cell that cannot run (a variant that refuses the
    cached source, waterf with several IDs)."""
    base = fit_config(cell.scene) if fitted is None else fitted
    if cell.method.preset is not None:
        preset = config_lib.load_preset(cell.method.preset_ref() or "")
        base = dataclasses.replace(base, watermark=preset.watermark)
    config = config_lib.apply_overrides(base, cell.embed_overrides())
    wm = dataclasses.replace(config.watermark, num_ids=cell.num_ids, bits=cell.bits)
    wm.check_ids()
    phase1, phase2 = watermark.phase_steps(wm)
    wm = dataclasses.replace(
        wm, schedule=dataclasses.replace(wm.schedule, phase1_steps=phase1, phase2_steps=phase2)
    )
    return dataclasses.replace(config, watermark=wm)


def resolved_settings(config: Config) -> dict[str, Any]:
    """The watermark settings a results row reports beside the spec's (from a resolved config)."""
    wm = config.watermark
    ranks = list(wm.module.wm_ranks)
    return {
        "wm_ranks": ",".join(map(str, ranks)),
        "wmcom": ranks[0] if len(set(ranks)) == 1 else None,
        "phase1_steps": wm.schedule.phase1_steps,
        "phase2_steps": wm.schedule.phase2_steps,
        "phase3_steps": wm.phase3.steps,
        "ids_per_step": wm.schedule.ids_per_step,
        "cache_source": wm.schedule.cache_source,
        "noised": bool(wm.augment.prob > 0 and wm.augment.per_step > 0),
        "time_budget_min": wm.time_budget.minutes,
    }
