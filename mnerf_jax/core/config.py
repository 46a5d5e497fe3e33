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
from typing import Any, Literal, get_args, get_origin, get_type_hints

from mnerf_jax.core.errors import ConfigError
from mnerf_jax.core.watermark_config import WatermarkConfig, translate_flat

CONFIG_DIR = Path(__file__).resolve().parents[2] / "configs"


@dataclasses.dataclass(frozen=True)
class DataConfig:
    """Where the images come from and how they are turned into rays."""

    dataset: str = "auto"  # auto | blender | llff | nerfstudio | procedural
    downscale: float = 1.0  # image side divided by this (area resampling)
    white_bg: bool = True  # composite RGBA on white (False: black)
    llff_factor: int = 8  # LLFF: read images_<factor>/
    llff_hold: int = 8  # LLFF / nerfstudio without split: every n-th view is a test view
    ndc: bool = False  # forward-facing scenes: NDC rays (set by the llff preset)
    # nerfstudio captures: the poses rotated (up: mean camera up onto +z; pca: the cameras' principal axes),
    # centred and scaled into [-1, 1]^3; auto: up, except for instant-ngp files (aabb_scale) and files with
    # camera_angle_x only, which keep their frame; none: the file's frame
    orientation: Literal["auto", "up", "pca", "none"] = "auto"
    centring: Literal["focus", "poses", "none"] = "focus"  # nerfstudio captures: the origin moved here
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
    chunk: int = (
        4096  # rays per chunk when rendering whole images (small enough for the buffers to stay in cache)
    )
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
class Config:
    name: str = "default"
    data: DataConfig = DataConfig()
    model: ModelConfig = ModelConfig()
    render: RenderConfig = RenderConfig()
    train: TrainConfig = TrainConfig()
    watermark: WatermarkConfig = dataclasses.field(default_factory=WatermarkConfig)

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


def flat_items(value: Any, prefix: str = "") -> dict[str, Any]:
    """A config (or a section, or nested plain data) as ``{"a.b": leaf}`` with dotted names."""
    if dataclasses.is_dataclass(value):
        value = {f.name: getattr(value, f.name) for f in dataclasses.fields(value)}
    if isinstance(value, Mapping):
        out: dict[str, Any] = {}
        for key, item in value.items():
            out.update(flat_items(item, f"{prefix}{key}."))
        return out
    return {prefix[:-1]: value}


def _coerce(value: Any, hint: Any, where: str) -> Any:
    """Turn a JSON/TOML/CLI value into the field's declared type, or raise ConfigError."""
    origin = get_origin(hint)
    if origin is Literal:
        if value not in get_args(hint):
            raise ConfigError(
                f"{where}: expected one of {', '.join(map(str, get_args(hint)))}, got {value!r}"
            )
        return value
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
    """Build a Config from nested plain data (a TOML preset or a saved config.json; one written before the
    watermark's sections is translated)."""
    if isinstance(values.get("watermark"), Mapping):
        values = {**values, "watermark": translate_flat(dict(values["watermark"]))}
    return _build(Config, values, "config", base)


def watermark_from_flat(**values: Any) -> WatermarkConfig:
    """A WatermarkConfig from nested values or the flat names of the layout before the sections
    (``phase3_steps=4`` for ``phase3.steps``), checked as any config."""
    return _build(WatermarkConfig, translate_flat(values), "watermark")


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
