"""Configs as data: frozen dataclasses, TOML presets in ``configs/``, dotted ``--set`` overrides.

A run's config is written beside its checkpoint (``RUN/config.json``) and compared on resume, so
every field here is plain data (ints, floats, strings, bools, tuples) and round-trips through JSON.
"""

from __future__ import annotations

import dataclasses
import json
import tomllib
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any, get_type_hints

from mnerf_jax.core.errors import MnerfError

CONFIG_DIR = Path(__file__).resolve().parent.parent / "configs"


class ConfigError(MnerfError, ValueError):
    """A config file or override that cannot be applied (unknown key, wrong type, bad value)."""


@dataclasses.dataclass(frozen=True)
class DataConfig:
    """Where the images come from and how they are turned into rays."""

    dataset: str = "auto"  # auto | blender | llff | nerfstudio | procedural
    downscale: float = 1.0  # image side divided by this (area resampling)
    white_bg: bool = True  # composite RGBA on white (False: black)
    llff_factor: int = 8  # LLFF: read images_<factor>/
    llff_hold: int = 8  # LLFF / nerfstudio without split: every n-th view is a test view
    ndc: bool = False  # forward-facing scenes: NDC rays (set by the llff preset)
    procedural_seed: int = 0  # built-in scene
    procedural_size: int = 64  # built-in scene: image side in pixels
    procedural_views: int = 48  # built-in scene: train views (test views = half of that)


@dataclasses.dataclass(frozen=True)
class ModelConfig:
    """TensoRF VM field and its MLP_Fea colour decoder."""

    density_ranks: tuple[int, int, int] = (16, 16, 16)
    appearance_ranks: tuple[int, int, int] = (48, 48, 48)
    app_features: int = 27  # basis matrix output width
    mlp_width: int = 128
    pe_features: int = 2  # sin/cos frequencies on the appearance features
    pe_view: int = 2  # sin/cos frequencies on the view direction
    density_activation: str = "softplus"  # softplus | relu
    density_shift: float = -10.0  # softplus(feature + shift)
    distance_scale: float = 25.0
    init_scale: float = 0.1  # factors start at init_scale * N(0, 1)


@dataclasses.dataclass(frozen=True)
class RenderConfig:
    """Ray sampling and compositing."""

    step_ratio: float = 0.5  # sample spacing in voxels
    near: float = 2.0
    far: float = 6.0
    aabb: tuple[float, float, float, float, float, float] = (-1.5, -1.5, -1.5, 1.5, 1.5, 1.5)
    weight_threshold: float = 1e-4  # colour is evaluated only where weight > this
    alpha_mask_threshold: float = 1e-4
    # Rays per chunk when rendering whole images. On the 2-core CPU (lego r_0, 40k rays, 128^3) chunks of
    # 2048-4096 rendered ~20 % faster than 8192 (their buffers stay in cache).
    chunk: int = 4096
    max_samples: int = 0  # 0: derived from the grid (TensoRF's rule); >0 caps it


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """TensoRF optimisation schedule."""

    seed: int = 0
    batch_size: int = 4096
    n_iters: int = 30000
    lr_grid: float = 0.02
    lr_network: float = 1e-3
    lr_decay_ratio: float = 0.1  # lr reaches lr * this at n_iters
    adam_b1: float = 0.9
    adam_b2: float = 0.99
    n_voxel_init: int = 128**3
    n_voxel_final: int = 300**3
    upsample_steps: tuple[int, ...] = (2000, 3000, 4000, 5500, 7000)
    alpha_mask_steps: tuple[int, ...] = (2000, 4000)
    l1_weight_initial: float = 8e-5
    l1_weight_rest: float = 4e-5
    tv_weight_density: float = 0.0
    tv_weight_app: float = 0.0
    random_background: bool = False  # composite on a random-colour background in training
    checkpoint_every: int = 1000
    log_every: int = 50
    keep_checkpoints: int = 2


@dataclasses.dataclass(frozen=True)
class WatermarkConfig:
    """MultiNeRF watermark grid, ID embedding and the two-phase embedding schedule."""

    num_ids: int = 4
    bits: int = 16
    wm_ranks: tuple[int, int, int] = (8, 8, 8)  # #WMCom per VM mode
    emb_dim: int = 16
    emb_hidden: int = 32
    # Emb's hidden activation: relu | silu | tanh (the paper says only "a small MLP"). With ReLU and a one-hot
    # input a unit negative for an ID never gets that ID's gradient again, and the weakest IDs of a run end
    # with few live units and their (γ, β) near the IDs' mean; but SiLU, which keeps every unit alive, left
    # other IDs as weak (lego, 16 IDs, the CPU hour: 90.1 % bits, right ID 94.7 %, 24.97 dB against ReLU's
    # 90.9-91.5 %, 89.3-94.9 %, 25.3-25.6 dB in two runs), so ReLU stays (docs/findings.md).
    emb_activation: str = "relu"
    # multinerf | no_grid | no_film | frozen_geometry | early | waterf | waterf_mod
    variant: str = "multinerf"
    min_hamming: int = 0  # 0: chosen from num_ids and bits
    key_seed: int = 0
    # -1: by the number of IDs, 50 + 200 per ID, at least 200 + 800 (watermark.phase_steps).
    phase1_steps: int = -1
    phase2_steps: int = -1
    # Phase 2's patch side (deferred back-propagation; peak memory follows it). At or above the view's side
    # one patch covers the view and the step renders once, on the graph, instead of a graph-free render and
    # the patches again: lego 1/8 (100 px), 16 IDs, 0.80 s a step against 1.08 s at 64, peak RSS 15.2 GB
    # against 4.9 GB (configs/embed_cpu_quality.toml spends that memory on more steps in the hour).
    patch_size: int = 64
    lambda_message: float = 0.95
    lambda_perceptual: float = 0.05
    lambda_rgb: float = 0.1
    lambda_tv: float = 0.02
    lambda_ssim: float = 0.2
    bce_temperature: float = 10.0
    # Both phases: the field learns from the mean of a step's K message BCEs weighted by BCE_k^id_loss_power
    # (held constant), the decoder from the plain mean (wm_step.message_loss). Not in the paper (0 there:
    # the plain mean for both). With 16 IDs two or three stay weak in a short run (their FiLM pair near the
    # IDs' mean); a power > 0 gives their renders more of the field's gradient.
    id_loss_power: float = 0.0
    # Both phases: + lambda_key · the cross-entropy of naming each render's own key among all N keys
    # (losses.key_cross_entropy, on the message term's logits). Not in the paper (0 there). The per-bit BCE
    # spends its gradient on every bit alike; identification fails where a render reads nearer another ID's
    # key (a weak ID collapsing onto a strong one), and this term's gradient sits on the bits that tell the
    # two apart. Lego 1/8, 16 IDs x 16 bits, 4,000 steps on a GPU, 0 / 0.05 / 0.2: 93.7 / 96.7 / 98.6 % bits
    # (worst ID 83.0 / 93.4 / 96.9 %), the right ID named (binomial) for 47.9 / 67.0 / 81.0 % of renders,
    # 25.84 / 25.15 / 24.95 dB. The CPU hour (embed_cpu, seed 0) at 0.1: 92.3 % against 89.1 %, named 33.1
    # against 26.1 %, 24.14 against 26.36 dB.
    lambda_key: float = 0.2
    perceptual: str = "watson"  # watson | vgg
    augment_strength: str = "low"
    # Phase 2 draws its augmentations from these (names of augment.AUGMENTATIONS); empty: all 14, the paper's
    # layer. A subset ablates the layer, or trains against the attacks a user expects.
    augment_names: tuple[str, ...] = ()
    augment_per_step: int = 2
    # Each drawn augmentation applies with this probability; 0: phase 2 with no attack. Under a tight quality
    # budget the decoder's thresholds learnt on attacked renders misread un-attacked ones: the lego CPU hour
    # with a budget tightened to 40 dB (seed 0) read 73.0 % bits at -0.51 dB with attacks, 80.8 % at -0.60 dB
    # at 0, reading more under every attack but JPEG and box / motion blur (mnerf attack; docs/findings.md).
    augment_prob: float = 0.75
    lr_grid: float = 0.02
    lr_network: float = 1e-3
    # The paper gives no decoder rate. 1e-3 rather than 1e-4 (with lambda_clean below), lego 1/8,
    # 16 IDs x 16 bits, 4,000 steps, 200 test views, on a GPU: 95.1 % bits and the right ID for 96.6 % of
    # renders, against 85.0 % and 78 % at 1e-4, at the same PSNR (25.8 / 25.7 dB). Without lambda_clean the
    # faster decoder starts to read the scene itself (demo scene: 1 of 24 clean renders named as an ID).
    lr_decoder: float = 1e-3
    # The fitted TensoRF's own factors, basis and MLP train at lr_grid / lr_network times this (the new
    # watermark modules at the full rates). WateRF and the paper use 1.0; but Adam's first steps move every
    # parameter by about its lr whatever its gradient, and at 1.0 that cost the fitted procedural field
    # 35.4 → 29.0 dB train-view PSNR in three steps (at 0.1: 33.9 after one step, 35.4 again at the third).
    lr_source_scale: float = 0.1
    # True: the fitted TensoRF (density, appearance, basis, MLP) does not train; its colour samples of every
    # training view are computed once and a step renders only what the watermark adds to them
    # (sample_cache.py): no ray march in the step and no deferred patches. Needs a variant whose FiLM
    # features enter the last layer (multinerf, no_grid, frozen_geometry) and jitter = false (the cached
    # samples are an evaluation render's).
    cache_source: bool = False
    # Phase 2: + lambda_clean · BCE(decoder(augmented ground-truth view), ½): a clean image should decode to
    # nothing. Not in the paper (0 there): a decoder that learns with the field otherwise learns to read the
    # scene itself, and clean renders decode as a key. Demo scene, 30 dB budget, lr_decoder 1e-3: 0.3 took
    # false detections from 4.2 % to none for 98.0 -> 92.3 % bits.
    lambda_clean: float = 0.3
    # What the clean term reads as unwatermarked: "ground_truth", the training view itself, or
    # "clean_model", the clean (pre-watermark) model's render of it, made once (the renders evaluation and a
    # verifier meet; smoother than the photographs, as every render is).
    clean_negative: str = "ground_truth"
    lr_decay_ratio: float = 0.1
    wavelet: str = "bior4.4"
    # The decoder reads a square window of this fraction of the image's shorter side, centred on the pixels
    # that differ from read_background (read_window.py), instead of the whole image; 0: the whole image (the
    # paper). For object-centred scenes on an empty backdrop, where the whole view's frame lies on background
    # and the decoders read patterns anchored to the frame. The lego CPU hour (100 + 2,000 steps), seeds
    # 0 / 1 / 2, at 0.72: 98.0 % bits on average against 90.7 % with the whole view, the right ID named
    # (binomial) for 78.6 % against 28.7 %, 2.1 dB less PSNR; with fidelity_psnr = 27 no gain (75.4 % against
    # 79.9 %, seed 0). configs/embed_cpu.toml sets it (2,600 steps: 100 % named, seeds 0 / 1; findings.md).
    read_window: float = 0.0
    # The backdrop's grey level the window's centring ignores (1: white, NeRF-Synthetic); < 0: centre the
    # window on the image.
    read_background: float = 1.0
    # The decoder's logits are averaged over the read windows moved by up to read_jitter pixels on each axis
    # ((2r + 1)² windows; read_window.jittered_logits) wherever a run's renders are read (evaluation,
    # mnerf extract: the radius is stored in the decoder file); 0: the centred window alone. Reading only:
    # the embedding trains on the centred window (phase 3 trained on moved windows read worse). The lego CPU
    # hour within 0.5 dB (embed_cpu_quality, seed 0), r = 1: 97.7 % bits, named 74.0 %, against 96.6 and
    # 66.4 % (docs/findings.md, "Reading over jittered windows, and phase 3's rate").
    read_jitter: int = 0
    checkpoint_every: int = 100
    seed: int = 0  # embedding randomness: module init, ID and view per step, sample jitter, augmentations
    jitter: bool = True  # jitter samples along rays while embedding (as TensoRF's training renders)
    id_threshold: float = 1e-3  # identification: Bonferroni-corrected p-value below this names an ID
    # Which p-value the identification decides by (both are reported; significance.py): "binomial", the
    # count of matching bits, or "sign_flip", the match weighted by each bit's confidence (the same null
    # hypothesis; lego CPU hour: the right ID verified for 45.8 % of renders at 1e-3 against 26.1 %).
    id_test: str = "binomial"
    lr_embedding: float = 1e-2  # Emb and Mod (each ID's Emb row learns only on the steps that draw it)
    # IDs rendered per step (K distinct IDs, one view): the K renders share the geometry pass and the colour
    # MLP up to its last layer (FiLM enters there), so every ID learns on K/N of the steps for much less than
    # K renders' cost. 0: every ID, at most 16 (watermark.ids_per_step_of); 1: one ID per step, as the paper.
    ids_per_step: int = 0
    # Quality budget (not in the paper): > 0 adds lambda_fidelity · relu(MSE / MSE_budget − 1) between each
    # watermarked render and the clean model's render of the same view (made once), both phases, with
    # MSE_budget = 10^(−fidelity_psnr / 10): no pull while a render is inside the budget, a steady one
    # outside it. The paper's losses alone set no scale for quality: the decoder's gradient on a 64-px view
    # is ~15,000× the patch L1's, so PSNR fell 11 dB on the demo scene whatever lambda_rgb (0.1 or 1.0).
    # A smooth penalty (MSE / MSE_budget)² held renders 9 dB inside a 35 dB budget: under Adam a small but
    # steady gradient moves parameters as far as a large one. 0: off (the paper). Its trade in the lego CPU
    # hour with lambda_key = 0.2, on two seeds: configs/embed_cpu.toml and docs/findings.md.
    fidelity_psnr: float = 0.0
    lambda_fidelity: float = 10.0
    # Tightening the quality budget over the run (not in the paper; wm_step.fidelity_budget_db). With
    # fidelity_psnr_start > 0 the budget is fidelity_psnr_start dB until the fraction fidelity_ramp[0] of the
    # schedule's steps, rises linearly in dB to fidelity_psnr by the fraction fidelity_ramp[1], and holds
    # there. A budget held from the first step keeps the field where its pattern has not yet formed (the
    # read window's runs lag for ~900 steps, and a 27 dB budget kept them there); a loose budget first lets
    # the key be written, and the ramp then shrinks it while the decoder, learning with it, follows.
    # The lego CPU hour (embed_cpu, seed 0), from 20 dB over 0.45-0.75 / 0.6-0.8 of the steps to 40 / 40.5 dB:
    # -0.51 / -0.48 dB against the clean model (the 0.5 dB) at 73.0 / 72.1 % bits, where the preset
    # without a budget reads 100 % at -11.8 dB (docs/findings.md). Ramped over 0.35-0.6 to 41.2 dB with no
    # attacks: -0.47 dB at 77.2 % bits, the best match right for 85.1 %; the same over 4,000 steps with one
    # patch per view (52 min): -0.48 dB at 90.4 %, the best match 95.7 %; configs/embed_cpu_quality.toml now
    # ramps 3,400 steps to 41.5 dB and refits the decoder after them (phase 3): -0.44 dB at 96.3 %.
    # 0: no ramp, fidelity_psnr from the start.
    fidelity_psnr_start: float = 0.0
    fidelity_ramp: tuple[float, float] = (0.0, 0.0)
    # Phase 3 (not in the paper; decoder_refit.py): after the field's schedule the decoder alone learns for
    # phase3_steps steps (0: off, the paper's two phases) on the finished field's renders of the training
    # views and of phase3_views novel views around them (object-centred scenes), every ID; the field, and
    # so the PSNR, is not changed. Lego 1/8, 16 IDs, the CPU-hour field, 50 test views: 90.7 % bits and
    # 30.0 % named before; 1,500 steps on the 100 training views: 97.1 %, 74.0 %; with 200 novel views
    # too: 99.3 %, 92.1 % (docs/findings.md). With a time budget the field's loop keeps
    # phase3_reserve_min minutes of it for phase 3, which itself stops when the budget is spent.
    phase3_steps: int = 0
    phase3_views: int = 0
    # How the novel views are spread (decoder_refit.novel_cameras): "angles", uniform in azimuth and elevation
    # between the training cameras' lowest and highest elevation; "sphere", uniform over the sphere's area
    # there, the density NeRF-Synthetic's cameras are drawn with (more views near the horizon, fewer near the
    # pole). phase3_elevation_margin: degrees the range reaches past the training cameras' on either side.
    phase3_view_density: str = "angles"
    phase3_elevation_margin: float = 0.0
    phase3_lr: float = 1e-3
    # Renders per phase-3 step (and a quarter as many negatives). At the same number of renders seen, more and
    # smaller batches read more on lego (4,000 x 16 against 2,000 x 32: 98.3 against 97.0 % bits on 50 test
    # views; configs/embed_cpu_quality.toml sets 16).
    phase3_batch: int = 32
    # Phase 3's weight of BCE(decoder(unwatermarked image), ½) (its negatives; 0: none). Phase 2's weight is
    # lambda_clean. A decoder refitted longer claims more clean renders: lego 1/8, 16 IDs, 9,000 steps of 16,
    # 200 test views (one H100 run each): 3.5 % of the clean renders named at 0.3, 1.0 % at 1, none at 3,
    # the renders named 97.2, 97.2 and 96.6 %; on the CPU (6,000 steps, one draw each) 94.75 % at 0.3, 93.6 %
    # at 1 and 87.9 % at 3, 1 / 0 / 1 of 200 clean renders claimed (docs/findings.md, "Phase 3's negatives").
    phase3_lambda_clean: float = 0.3
    phase3_reserve_min: float = 0.0
    keep_checkpoints: int = 2
    # Wall-clock budget of `mnerf embed` in minutes (0: off). On: the run stops before a step that, with the
    # last checkpoint, would not end inside it (judged by the steps just run; embed_budget.py). The field's
    # schedule is not resized, so a stopped field is the first steps of the full one; --resume continues it,
    # unless phase 3 ran on it (in the phase3_reserve_min kept, its schedule sized to the time left).
    time_budget_min: float = 0.0
    # With a time budget: once the field's first steps are timed (embed_budget.FIELD_SIZING_STEPS), shorten
    # phase 2 to the steps that end inside the budget (less phase3_reserve_min), so that the learning rates'
    # decay and the quality budget's ramp (fractions of the schedule) run their course on a slower machine
    # instead of being cut off. The sized schedule is the run's (config.json, checkpoints; --resume keeps it).
    budget_sizes_field: bool = False


@dataclasses.dataclass(frozen=True)
class Config:
    name: str = "default"
    data: DataConfig = DataConfig()
    model: ModelConfig = ModelConfig()
    render: RenderConfig = RenderConfig()
    train: TrainConfig = TrainConfig()
    watermark: WatermarkConfig = WatermarkConfig()

    def to_dict(self) -> dict[str, Any]:
        return _to_plain(dataclasses.asdict(self))

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2, sort_keys=True)


def _to_plain(value: Any) -> Any:
    if isinstance(value, Mapping):
        return {k: _to_plain(v) for k, v in value.items()}
    if isinstance(value, tuple | list):
        return [_to_plain(v) for v in value]
    return value


def _coerce(value: Any, hint: Any, where: str) -> Any:
    """Turn a JSON/TOML/CLI value into the field's declared type, or raise ConfigError."""
    origin = getattr(hint, "__origin__", None)
    if origin is tuple:
        if isinstance(value, str):
            value = [v for v in value.strip("()[] ").split(",") if v.strip()]
        if not isinstance(value, list | tuple):
            raise ConfigError(f"{where}: expected a list, got {value!r}")
        args = hint.__args__
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_coerce(v, args[0], where) for v in value)
        if len(value) != len(args):
            raise ConfigError(f"{where}: expected {len(args)} values, got {len(value)}")
        return tuple(_coerce(v, a, where) for v, a in zip(value, args, strict=True))
    if hint is bool:
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.lower() in ("true", "1", "yes", "false", "0", "no"):
            return value.lower() in ("true", "1", "yes")
        raise ConfigError(f"{where}: expected true/false, got {value!r}")
    if hint is int:
        if isinstance(value, bool):
            raise ConfigError(f"{where}: expected an integer, got {value!r}")
        try:
            as_float = float(value)
        except (TypeError, ValueError):
            raise ConfigError(f"{where}: expected an integer, got {value!r}") from None
        if as_float != int(as_float):
            raise ConfigError(f"{where}: expected an integer, got {value!r}")
        return int(as_float)
    if hint is float:
        try:
            return float(value)
        except (TypeError, ValueError):
            raise ConfigError(f"{where}: expected a number, got {value!r}") from None
    if hint is str:
        return str(value)
    if dataclasses.is_dataclass(hint):
        if not isinstance(value, Mapping):
            raise ConfigError(f"{where}: expected a table, got {value!r}")
        return _build(hint, value, where)
    return value


def _build(cls: type, values: Mapping[str, Any], where: str = "config", base: Any = None) -> Any:
    hints = get_type_hints(cls)
    fields = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(values) - fields)
    if unknown:
        raise ConfigError(f"unknown config key {where}.{unknown[0]} (known: {', '.join(sorted(fields))})")
    current = base if base is not None else cls()
    updates = {}
    for key, value in values.items():
        hint = hints[key]
        if dataclasses.is_dataclass(hint) and isinstance(value, Mapping):
            updates[key] = _build(hint, value, f"{where}.{key}", getattr(current, key))
        else:
            updates[key] = _coerce(value, hint, f"{where}.{key}")
    return dataclasses.replace(current, **updates)


def from_dict(values: Mapping[str, Any], base: Config | None = None) -> Config:
    """Build a Config from nested plain data (a TOML preset or a saved config.json)."""
    return _build(Config, values, "config", base)


def available_presets() -> list[str]:
    return sorted(p.stem for p in CONFIG_DIR.glob("*.toml"))


def load_preset(name: str) -> Config:
    """Load ``configs/<name>.toml`` (or a path to a TOML file) over the defaults."""
    path = Path(name)
    if not path.suffix:
        path = CONFIG_DIR / f"{name}.toml"
    if not path.is_file():
        raise ConfigError(f"no config preset {name!r} (available: {', '.join(available_presets())})")
    try:
        values = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(f"{path}: malformed TOML: {err}") from None
    values.setdefault("name", path.stem)
    return from_dict(values)


def parse_overrides(items: Iterable[str]) -> dict[str, Any]:
    """``["train.n_iters=100", "model.density_ranks=8,8,8"]`` -> nested dict of strings."""
    nested: dict[str, Any] = {}
    for item in items:
        if "=" not in item:
            raise ConfigError(f"--set expects key=value, got {item!r}")
        key, value = item.split("=", 1)
        parts = key.strip().split(".")
        node = nested
        for part in parts[:-1]:
            node = node.setdefault(part, {})
        node[parts[-1]] = value.strip()
    return nested


def apply_overrides(config: Config, items: Iterable[str]) -> Config:
    return from_dict(parse_overrides(items), base=config)


def load_config(name: str, overrides: Iterable[str] = ()) -> Config:
    return apply_overrides(load_preset(name), overrides)


def load_json(path: str | Path) -> Config:
    path = Path(path)
    try:
        values = json.loads(path.read_text())
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such config file") from None
    except json.JSONDecodeError as err:
        raise ConfigError(f"{path}: malformed JSON: {err}") from None
    return from_dict(values)
