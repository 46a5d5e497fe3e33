"""A study spec (``SPEC.toml``) parsed into frozen dataclasses, every value checked.

A spec names the scenes (each fitted once and shared by its cells), the methods (a watermark variant plus
``--set`` overrides of the ``[watermark]`` section), the grid's axes (numbers of IDs, bit lengths, seeds),
the decoder file of each bit length, and what to measure. Any bad value is refused with one line naming its
key (``StudySpecError``), before anything runs. The layout, with every key::

    [study]
    name = "smoke"              # the study's name: [A-Za-z0-9_-]+
    ids = [2, 4]                # numbers of IDs
    bits = [16]                 # message lengths
    seeds = [0, 1]              # each sets watermark.seed and watermark.key_seed (default [0])
    set = []                    # watermark.* overrides every method starts from (before its own)

    [decoders]                  # the decoder each bit length starts from (default: the shipped one)
    8 = "decoders/dec8.npz"     # a file (relative to the spec's folder), or "fresh"

    [measure]
    split = "test"              # the evaluated split
    views = 0                   # evenly spread views of it (0: all)
    lpips = "alex"              # alex | vgg
    attacks = ["low"]           # attack suites: each a strength, the augmentations alone (mnerf attack)
    attack_names = []           # the augmentations of a suite (default: all 14)
    attack_views = 0            # evenly spread evaluated views the suites read (0: all)
    attack_seed = 0

    [[scenes]]
    name = "lego"
    preset = "quick"            # the fit's preset (configs/*.toml or a TOML path)
    data = "../data/lego"       # the scene's folder (relative to the spec's folder; not for procedural)
    downscale = 8               # data.downscale (optional)
    set = ["train.n_iters=800"] # more fit overrides (optional)
    # fit = "runs/lego"         # instead of the four above: an existing fitted run, shared, never refitted
    paper = "lego"              # the paper's scene (or SYN / LLFF) whose numbers this stands for

    [[methods]]
    name = "multinerf"
    variant = "multinerf"       # watermark.variant
    preset = "embed_cpu"        # a preset's [watermark] section (default: the one the fit recorded)
    set = []                    # watermark.* overrides
    ids = [16]                  # this method's own axes instead of the study's (optional)
    bits = [16]
    scenes = ["lego"]           # the scenes it runs on (optional; default: every scene)
"""

from __future__ import annotations

import dataclasses
import math
import os
import re
import tomllib
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, get_args

from mnerf_jax.core import config as config_lib
from mnerf_jax.core.errors import ConfigError, MnerfError
from mnerf_jax.core.watermark_config import Variant
from mnerf_jax.imaging import augment
from mnerf_jax.reader import decoder_io
from mnerf_jax.study import paper_numbers

NAME_PATTERN = re.compile(r"^[A-Za-z0-9_-]+$")
SPLITS = ("test", "val", "train")
LPIPS_NETS = ("alex", "vgg")
FRESH = decoder_io.FRESH  # a random-init decoder, trained with the field


class StudySpecError(MnerfError):
    """A study spec that cannot be run: malformed TOML, an unknown key, a bad value (one line, its key)."""


@dataclasses.dataclass(frozen=True)
class SceneSpec:
    """A scene: fitted once from ``preset`` (+ ``downscale``, ``set``) on ``data``, or the run ``fit``."""

    name: str
    preset: str | None = None
    data: str | None = None  # as written in the spec
    downscale: float | None = None
    set: tuple[str, ...] = ()
    fit: str | None = None  # as written in the spec
    paper: str | None = None
    base: Path = Path(".")  # the spec's folder: relative paths start there

    def preset_ref(self) -> str | None:
        """The fit's preset as ``config.load_preset`` takes it (None for a fitted run)."""
        return None if self.preset is None else preset_ref(self.preset, self.base)

    def data_path(self) -> Path | None:
        return None if self.data is None else resolve_path(self.data, self.base)

    def fit_path(self) -> Path | None:
        return None if self.fit is None else resolve_path(self.fit, self.base)

    def fit_overrides(self) -> tuple[str, ...]:
        """The fit's ``--set`` items: ``data.downscale`` first, then the scene's own."""
        down = () if self.downscale is None else (f"data.downscale={self.downscale:g}",)
        return (*down, *self.set)

    def settings(self) -> dict[str, Any]:
        """What the fit depends on (the cell and fit IDs hash this; names are left out)."""
        if self.fit is not None:
            return {"fit": self.fit}
        return {"preset": self.preset, "data": self.data, "set": list(self.fit_overrides())}


@dataclasses.dataclass(frozen=True)
class MethodSpec:
    """A method: a watermark variant, an optional ``[watermark]`` preset and ``watermark.*`` overrides."""

    name: str
    variant: str
    preset: str | None = None
    set: tuple[str, ...] = ()
    ids: tuple[int, ...] = ()  # empty: the study's
    bits: tuple[int, ...] = ()
    scenes: tuple[str, ...] = ()  # the scenes it runs on (empty: every scene); not a setting of its cells
    base: Path = Path(".")  # the spec's folder: a preset given as a TOML path starts there

    def runs_on(self, scene: str) -> bool:
        return not self.scenes or scene in self.scenes

    def preset_ref(self) -> str | None:
        """The preset as ``config.load_preset`` takes it (None: the fit's ``[watermark]`` section)."""
        return None if self.preset is None else preset_ref(self.preset, self.base)

    def overrides(self) -> tuple[str, ...]:
        return (f"watermark.variant={self.variant}", *self.set)

    def settings(self) -> dict[str, Any]:
        return {"variant": self.variant, "preset": self.preset, "set": list(self.set)}


@dataclasses.dataclass(frozen=True)
class MeasureSpec:
    """What each cell measures: an evaluation of ``split`` and the attack suites over its saved PNGs."""

    split: str = "test"
    views: int = 0
    lpips: str = "alex"
    attacks: tuple[str, ...] = ()
    attack_names: tuple[str, ...] = ()
    attack_views: int = 0
    attack_seed: int = 0

    def to_dict(self) -> dict[str, Any]:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(self).items()}


@dataclasses.dataclass(frozen=True)
class StudySpec:
    """A whole study: its axes, scenes, methods, decoders and measurements; ``path``: the spec file."""

    name: str
    ids: tuple[int, ...]
    bits: tuple[int, ...]
    seeds: tuple[int, ...]
    scenes: tuple[SceneSpec, ...]
    methods: tuple[MethodSpec, ...]
    measure: MeasureSpec
    decoders: Mapping[int, str]  # bits -> file (as written) or "fresh"
    path: Path

    def decoder_for(self, bits: int) -> str | None:
        """The decoder of ``bits`` as written in the spec; None: the shipped one."""
        return self.decoders.get(bits)

    def decoder_path(self, bits: int) -> Path | None:
        """``--decoder`` for ``bits``: a resolved file, ``Path("fresh")``, or None (the shipped one)."""
        raw = self.decoder_for(bits)
        if raw is None:
            return None
        return Path(FRESH) if raw == FRESH else resolve_path(raw, self.path.parent)


def resolve_path(raw: str, base: Path) -> Path:
    """``raw`` with ``~`` and ``$VARS`` expanded, relative to ``base`` unless absolute."""
    path = Path(os.path.expandvars(os.path.expanduser(raw)))
    return path if path.is_absolute() else base / path


# ------------------------------------------------------------------------------------------------ checks


class _Table:
    """A TOML table being read: typed getters whose errors name the key; unknown keys refused."""

    def __init__(self, values: Any, where: str, known: Sequence[str]):
        if not isinstance(values, Mapping):
            raise StudySpecError(f"{where}: expected a table, got {values!r}")
        unknown = sorted(set(values) - set(known))
        if unknown:
            raise StudySpecError(f"{where}.{unknown[0]}: unknown key (known: {', '.join(known)})")
        self.values, self.where = values, where

    def fail(self, key: str, message: str) -> StudySpecError:
        return StudySpecError(f"{self.where}.{key}: {message}")

    def has(self, key: str) -> bool:
        return key in self.values

    def str(self, key: str, default: str | None = None, *, required: bool = False) -> str | None:
        if key not in self.values:
            if required:
                raise self.fail(key, "missing")
            return default
        value = self.values[key]
        if not isinstance(value, str) or not value:
            raise self.fail(key, f"expected a non-empty string, got {value!r}")
        return value

    def name(self, key: str = "name") -> str:
        value = self.str(key, required=True)
        assert value is not None
        if not NAME_PATTERN.match(value):
            raise self.fail(key, f"letters, digits, _ and - only, got {value!r}")
        return value

    def int(self, key: str, default: int, minimum: int = 0) -> int:
        value = self.values.get(key, default)
        if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
            raise self.fail(key, f"expected an integer ≥ {minimum}, got {value!r}")
        return value

    def ints(
        self, key: str, default: Sequence[int] = (), *, minimum: int = 0, required: bool = False
    ) -> tuple[int, ...]:
        if key not in self.values:
            if required:
                raise self.fail(key, "missing")
            return tuple(default)
        value = self.values[key]
        if not isinstance(value, list) or not value:
            raise self.fail(key, f"expected a non-empty list of integers, got {value!r}")
        if any(isinstance(v, bool) or not isinstance(v, int) or v < minimum for v in value):
            raise self.fail(key, f"expected integers ≥ {minimum}, got {value!r}")
        if len(set(value)) != len(value):
            raise self.fail(key, f"lists a value twice: {value!r}")
        return tuple(value)

    def strs(self, key: str, choices: Sequence[str] | None = None) -> tuple[str, ...]:
        value = self.values.get(key, [])
        if not isinstance(value, list) or any(not isinstance(v, str) or not v for v in value):
            raise self.fail(key, f"expected a list of strings, got {value!r}")
        if choices is not None:
            bad = [v for v in value if v not in choices]
            if bad:
                raise self.fail(key, f"unknown {bad[0]!r} (known: {', '.join(choices)})")
        return tuple(value)

    def choice(self, key: str, default: str | None, choices: Sequence[str]) -> str:
        if key not in self.values and default is None:
            raise self.fail(key, f"missing (one of {', '.join(choices)})")
        value = self.values.get(key, default)
        if value not in choices:
            raise self.fail(key, f"expected one of {', '.join(choices)}, got {value!r}")
        return value


def _scene(values: Any, where: str, base: Path) -> SceneSpec:
    t = _Table(values, where, ("name", "preset", "data", "downscale", "set", "fit", "paper"))
    name, fit = t.name(), t.str("fit")
    if fit is not None:
        given = [k for k in ("preset", "data", "downscale", "set") if t.has(k)]
        if given:
            raise t.fail(given[0], "not with fit (a fitted run brings its own preset, data and settings)")
        if not (resolve_path(fit, base) / "run.json").is_file():
            raise t.fail("fit", f"{resolve_path(fit, base)} is not a fitted run (no run.json)")
        return SceneSpec(name=name, fit=fit, paper=_paper(t), base=base)
    downscale = t.values.get("downscale")
    if downscale is not None and (
        isinstance(downscale, bool)
        or not isinstance(downscale, int | float)
        or not math.isfinite(downscale)
        or downscale <= 0
    ):
        raise t.fail("downscale", f"expected a number > 0, got {downscale!r}")
    scene = SceneSpec(
        name=name,
        preset=t.str("preset", required=True),
        data=t.str("data"),
        downscale=None if downscale is None else float(downscale),
        set=t.strs("set"),
        paper=_paper(t),
        base=base,
    )
    try:
        config = config_lib.load_config(scene.preset_ref() or "", scene.fit_overrides())
    except ConfigError as err:
        raise StudySpecError(f"{where}: {err}") from None
    if config.data.dataset != "procedural" and scene.data is None:
        raise t.fail("data", f"missing (preset {scene.preset!r} reads a {config.data.dataset} scene)")
    return scene


def _paper(t: _Table) -> str | None:
    """The paper scene a scene stands for (its figures are set beside the row's), checked."""
    value = t.str("paper")
    if value is None:
        return None
    value = value.upper() if value.upper() in paper_numbers.DATASETS else value.lower()
    if paper_numbers.dataset_of(value) is None:
        known = [*paper_numbers.DATASETS, *(s for v in paper_numbers.DATASETS.values() for s in v)]
        raise t.fail(
            "paper", f"not one of the paper's scenes or datasets ({', '.join(known)}), got {value!r}"
        )
    return value


def preset_ref(preset: str, base: Path) -> str:
    """A preset as ``config.load_preset`` takes it: a bare name, or a TOML path relative to ``base``."""
    return preset if not Path(preset).suffix else str(resolve_path(preset, base))


_AXES_KEYS = (
    "watermark.variant",
    "watermark.num_ids",
    "watermark.bits",
    "watermark.seed",
    "watermark.key_seed",
)


def _watermark_items(t: _Table, key: str = "set") -> tuple[str, ...]:
    """``--set`` items of the ``[watermark]`` section only, none of the keys the grid's axes set."""
    items = t.strs(key)
    for item in items:
        name = item.split("=", 1)[0].strip()
        if not name.startswith("watermark."):
            raise t.fail(key, f"{item!r}: methods set watermark.* only (the fit's settings are the scene's)")
        if name in _AXES_KEYS:
            raise t.fail(key, f"{item!r}: set by the method's variant and the study's axes")
    return items


def _method(values: Any, where: str, base: Path, common: tuple[str, ...]) -> MethodSpec:
    t = _Table(values, where, ("name", "variant", "preset", "set", "ids", "bits", "scenes"))
    method = MethodSpec(
        name=t.name(),
        variant=t.choice("variant", None, get_args(Variant)),
        preset=t.str("preset"),
        set=(*common, *_watermark_items(t)),
        ids=t.ints("ids", minimum=1),
        bits=t.ints("bits", minimum=1),
        scenes=t.strs("scenes"),
        base=base,
    )
    try:
        base_config = config_lib.Config()
        if method.preset is not None:
            preset = config_lib.load_preset(method.preset_ref() or "")
            base_config = dataclasses.replace(base_config, watermark=preset.watermark)
        config_lib.apply_overrides(base_config, method.overrides())
    except ConfigError as err:
        raise StudySpecError(f"{where}: {err}") from None
    return method


def _decoders(values: Any, where: str) -> dict[int, str]:
    if not isinstance(values, Mapping):
        raise StudySpecError(f"{where}: expected a table of bit length = file, got {values!r}")
    out = {}
    for key, value in values.items():
        if not key.isdigit() or int(key) < 1:
            raise StudySpecError(f"{where}.{key}: expected a bit length (a positive integer) as the key")
        if not isinstance(value, str) or not value:
            raise StudySpecError(f"{where}.{key}: expected a decoder file or {FRESH!r}, got {value!r}")
        out[int(key)] = value
    return out


def _measure(values: Any) -> MeasureSpec:
    t = _Table(values, "measure", [f.name for f in dataclasses.fields(MeasureSpec)])
    return MeasureSpec(
        split=t.choice("split", "test", SPLITS),
        views=t.int("views", 0),
        lpips=t.choice("lpips", "alex", LPIPS_NETS),
        attacks=t.strs("attacks", augment.STRENGTHS),
        attack_names=t.strs("attack_names", augment.AUGMENTATION_NAMES),
        attack_views=t.int("attack_views", 0),
        attack_seed=t.int("attack_seed", 0),
    )


def _unique(names: Sequence[str], where: str) -> None:
    seen = set()
    for i, name in enumerate(names):
        if name in seen:
            raise StudySpecError(f"{where}[{i}].name: {name!r} is used twice")
        seen.add(name)


def parse_spec(values: Mapping[str, Any], path: Path) -> StudySpec:
    """A checked :class:`StudySpec` from the TOML's tables (``path``: the file, for relative paths)."""
    base = path.parent
    top = _Table(values, "spec", ("study", "decoders", "measure", "scenes", "methods"))
    for key in ("study", "scenes", "methods"):
        if not top.has(key):
            raise StudySpecError(f"{key}: missing ({path} needs [study], [[scenes]] and [[methods]])")
    study = _Table(values["study"], "study", ("name", "ids", "bits", "seeds", "set"))
    common = _watermark_items(study)
    for key in ("scenes", "methods"):
        if not isinstance(values[key], list) or not values[key]:
            raise StudySpecError(f"{key}: expected one or more [[{key}]] tables")
    scenes = tuple(_scene(v, f"scenes[{i}]", base) for i, v in enumerate(values["scenes"]))
    methods = tuple(_method(v, f"methods[{i}]", base, common) for i, v in enumerate(values["methods"]))
    _unique([s.name for s in scenes], "scenes")
    _unique([m.name for m in methods], "methods")
    scene_names = [s.name for s in scenes]
    for i, method in enumerate(methods):
        unknown = [name for name in method.scenes if name not in scene_names]
        if unknown:
            raise StudySpecError(
                f"methods[{i}].scenes: {', '.join(unknown)} not among the [[scenes]] "
                f"({', '.join(scene_names)})"
            )
    return StudySpec(
        name=study.name(),
        ids=study.ints("ids", minimum=1, required=True),
        bits=study.ints("bits", minimum=1, required=True),
        seeds=study.ints("seeds", (0,)),
        scenes=scenes,
        methods=methods,
        measure=_measure(values.get("measure", {})),
        decoders=_decoders(values.get("decoders", {}), "decoders"),
        path=path,
    )


def load_spec(path: str | Path) -> StudySpec:
    """Read and check ``SPEC.toml`` (StudySpecError, one line, on anything wrong)."""
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise StudySpecError(f"{path}: no such study spec") from None
    except OSError as err:
        raise StudySpecError(f"{path}: unreadable ({err})") from None
    try:
        values = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise StudySpecError(f"{path}: malformed TOML: {err}") from None
    try:
        return parse_spec(values, path.resolve())
    except StudySpecError as err:
        raise StudySpecError(f"{path}: {err}") from None
