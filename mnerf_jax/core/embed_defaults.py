"""What ``mnerf embed`` does without ``--config``: an embedding chosen from the fitted run and the machine.

The method is that of the ``embed_cpu_quality`` preset, the one that meets the lego protocol's targets within
its quality budget (the fitted field frozen and its samples cached, a quality budget that tightens over the
run, the read window, phase 3's decoder refit; docs/results.md). What the scene and the machine change:

* a fit whose preset ships its own embedding (a ``[watermark]`` section, as ``procedural``) keeps it;
* the time budget grows with the render's pixels, from the preset's at 100² to twice that at 141² and
  above, and is the GPU's own on a GPU;
* the phase-3 reserve follows the time budget, and more IDs than one step renders lengthen the field's
  schedule so that each ID is rendered as often;
* the read window centres on the object against a uniform backdrop, on the image otherwise;
* a read window well above the decoder's training side is downscaled to it (``reading.max_side``); one
  close to it is read as it is, since resampling blurs the finest patterns the field writes;
* the source is cached only when its samples fit in half the free memory; else deferred patches.

``choose(facts)`` is pure (facts in, settings out), so the choice is tested without a machine; the embedding
prints the settings and records them in the run (``run.json``'s ``auto``), and ``--resume`` replays them.
"""

from __future__ import annotations

import dataclasses
import math
import os
import tomllib
from pathlib import Path
from typing import Any

from mnerf_jax.core import config as config_lib
from mnerf_jax.core.watermark_config import MAX_AUTO_IDS_PER_STEP, ReadingConfig, window_side

AUTO = "auto"  # --config's default: this module's choice
FROM_RUN = "run"  # --config run: the [watermark] section the fitted run recorded
PAPER = "paper"  # --config paper: the paper's method (configs/paper.toml)
METHOD_PRESET = "embed_cpu_quality"

# The side the method preset's schedule and time budget were set for, and the budget's growth with pixels.
REFERENCE_PIXELS = 100 * 100
MAX_BUDGET_FACTOR = 2.0
GPU_MINUTES = 30.0  # the embedding's wall-clock target on one GPU (issue 52)
# A cached sample: xyz, clean logits (3 float32 each), weight (float32) and ray index (int32).
CACHE_BYTES_PER_SAMPLE = 32
# A generous bound on the coloured samples a fitted field's ray keeps (most rays cross empty space or stop at
# the first opaque surface; the cache's own counts are in docs/experiments/).
CACHE_SAMPLES_PER_RAY = 16
CACHE_MEMORY_SHARE = 0.5  # the share of free memory the cache may take
UNCACHED_PATCH = 128  # deferred patches' side when the source is not cached
SYNTHETIC_DATASETS = ("blender", "procedural")  # rendered on a uniform backdrop
# Reads up to this many times the decoder's training side stay as they are (docs/experiments/).
READ_AS_IS_FACTOR = 1.5


@dataclasses.dataclass(frozen=True)
class SceneFacts:
    """What the choice depends on: the fitted run's preset, its training views (``views`` of ``height ×
    width`` pixels), the backdrop's grey level in [0, 1] (None for a real background), the IDs to embed, the
    JAX backend (``cpu``, ``gpu``, ...) and free host memory (bytes)."""

    fit_preset: str
    height: int
    width: int
    views: int
    backdrop: float | None
    num_ids: int
    backend: str
    memory_bytes: int


@dataclasses.dataclass(frozen=True)
class Choice:
    """A preset whose ``[watermark]`` section is the base, ``--set`` items over it, and a reason per item."""

    preset: str
    settings: tuple[str, ...] = ()
    reasons: tuple[str, ...] = ()

    def to_dict(self) -> dict[str, object]:
        return {"preset": self.preset, "settings": list(self.settings), "reasons": list(self.reasons)}

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> Choice:
        """The choice :meth:`to_dict` recorded (``run.json``'s ``auto``)."""
        settings, reasons = values.get("settings", ()), values.get("reasons", ())
        return cls(str(values["preset"]), tuple(map(str, settings)), tuple(map(str, reasons)))

    def describe(self) -> str:
        """One line per setting, with why: what ``mnerf embed`` prints before it starts."""
        lines = [f"the {self.preset} preset's embedding"]
        lines += [f"  {s}  ({r})" for s, r in zip(self.settings, self.reasons, strict=True)]
        return "\n".join(lines)


def preset_ships_embedding(name: str) -> bool:
    """True when ``configs/<name>.toml`` has its own ``[watermark]`` section (False for other names)."""
    path = config_lib.CONFIG_DIR / f"{name}.toml"
    try:
        return "watermark" in tomllib.loads(path.read_text())
    except (OSError, tomllib.TOMLDecodeError):
        return False


def free_memory_bytes() -> int:
    """MemAvailable of /proc/meminfo; the physical memory where that is not readable."""
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))


def cache_bytes(facts: SceneFacts) -> int:
    """A bound on the sample cache of the training views (bytes)."""
    rays = facts.views * facts.height * facts.width
    return rays * (CACHE_SAMPLES_PER_RAY * CACHE_BYTES_PER_SAMPLE + 4)


def backdrop_of(scene_kind: str, white_bg: bool) -> float | None:
    """The uniform backdrop a scene's renders have: white or black for synthetic scenes, None for captures
    (``scene_kind``: ``data.Scene.kind``)."""
    if scene_kind in SYNTHETIC_DATASETS:
        return 1.0 if white_bg else 0.0
    return None


def read_side(facts: SceneFacts, window: float) -> int:
    """The longer side (pixels) of what the decoder is given of a training view: the read window's side,
    or the whole view's longer side when ``window`` is 0."""
    if not window:
        return max(facts.height, facts.width)
    return window_side(facts.height, facts.width, window)


def choose(facts: SceneFacts) -> Choice:
    """The embedding for ``facts`` (see the module's docstring)."""
    if preset_ships_embedding(facts.fit_preset):
        return Choice(facts.fit_preset)
    base = config_lib.load_preset(METHOD_PRESET).watermark
    settings: list[tuple[str, str]] = []

    pixels = facts.height * facts.width
    if facts.backend == "cpu":
        factor = min(max(pixels / REFERENCE_PIXELS, 1.0), MAX_BUDGET_FACTOR)
        minutes = base.time_budget.minutes * factor
        why = f"{facts.width}×{facts.height} renders on the CPU"
    else:
        minutes = GPU_MINUTES
        why = f"on the {facts.backend.upper()}"
    if minutes != base.time_budget.minutes:
        settings.append((f"watermark.time_budget.minutes={minutes:g}", why))
        reserve = base.phase3.reserve_min * minutes / base.time_budget.minutes
        settings.append((f"watermark.phase3.reserve_min={reserve:.3g}", "the same share of the time budget"))

    if facts.num_ids > MAX_AUTO_IDS_PER_STEP:
        rounds = math.ceil(facts.num_ids / MAX_AUTO_IDS_PER_STEP)
        settings.append(
            (
                f"watermark.schedule.phase2_steps={base.schedule.phase2_steps * rounds}",
                f"{facts.num_ids} IDs, {MAX_AUTO_IDS_PER_STEP} a step: each rendered as often",
            )
        )

    if facts.backdrop is None:
        settings.append(
            ("watermark.reading.background=-1", "no uniform backdrop: the window centres on the image")
        )
    elif facts.backdrop != base.reading.background:
        settings.append((f"watermark.reading.background={facts.backdrop:g}", "the scene's backdrop"))

    side, trained = read_side(facts, base.reading.window), ReadingConfig().max_side
    if not base.reading.max_side and side > READ_AS_IS_FACTOR * trained:
        settings.append(
            (
                f"watermark.reading.max_side={trained}",
                f"its {side}-px read downscaled to the decoder's training side",
            )
        )

    if cache_bytes(facts) > CACHE_MEMORY_SHARE * facts.memory_bytes:
        gib = cache_bytes(facts) / 2**30
        why = f"the source's samples (up to {gib:.1f} GiB) would not fit in half the free memory"
        settings.append(("watermark.schedule.cache_source=false", why))
        settings.append((f"watermark.schedule.patch_size={UNCACHED_PATCH}", "deferred patches instead"))
    return Choice(METHOD_PRESET, tuple(s for s, _ in settings), tuple(r for _, r in settings))
