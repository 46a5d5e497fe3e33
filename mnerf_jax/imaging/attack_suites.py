"""Named attacks with their parameters, their composition, and the suites ``mnerf attack --suite`` runs.

An :class:`Attack` maps uint8 images ``[B, H, W, 3]`` and a seed to uint8 images ``[B, H', W', 3]``
through one or more stages. A stage draws its random parameters from a generator seeded by the seed and
the stage's own name (:func:`stage_rng`), per image in batch order: the same seed gives every watermark ID's
renders of the same views (and the clean model's) the same parameters, whichever other attacks run, and a
composed attack ``a+b`` is exactly ``b`` applied to ``a``'s output. The paper's 14 augmentations
(:mod:`mnerf_jax.imaging.augment`, JAX) run as stages too, keyed as ``mnerf attack`` always keyed them
(``fold_in(PRNGKey(seed), their index)``), on the 8-bit images scaled to [0, 1] and rounded back.

Suites: ``codecs``, ``geometric``, ``photometric``, ``regen`` (offline stand-ins for regeneration by a
model), ``peers`` (the list NeRF-watermarking peers report), ``paper`` (the 14 augmentations at Low /
Medium / High and every pair at Low) and ``all``. :func:`codec_model_attack` runs CompressAI's learned codecs
from the user's weights (``--codec-model ARCHITECTURE=PATH``, :mod:`imaging.compression_models`);
:func:`hook_attack` wraps a user's function (``--regen module:function``), for a model this package does not
ship.
"""

from __future__ import annotations

import dataclasses
import importlib
import importlib.util
import itertools
import sys
import zlib
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import jax
import numpy as np

from mnerf_jax.imaging import attacks as A
from mnerf_jax.imaging import augment, compression_models
from mnerf_jax.imaging.attacks import AttackError

StageFn = Callable[[np.ndarray, int], np.ndarray]


def stage_rng(seed: int, name: str) -> np.random.Generator:
    """The generator a stage called ``name`` draws from under ``seed`` (any int)."""
    return np.random.default_rng([zlib.crc32(name.encode()), int(seed) % (1 << 64)])


@dataclasses.dataclass(frozen=True)
class Stage:
    """One step of an attack: ``run(images uint8 [B, H, W, 3], seed) -> uint8 [B, H', W', 3]``."""

    name: str
    run: StageFn


@dataclasses.dataclass(frozen=True)
class Attack:
    """A named attack: ``family`` (codec, geometric, photometric, regen, peers, paper, augment, hook), a
    one-line ``description``, its ``stages`` in order; ``unavailable``: why it cannot run here (None: it can).
    """

    name: str
    family: str
    description: str
    stages: tuple[Stage, ...]
    unavailable: str | None = None

    def __call__(self, images: np.ndarray, seed: int = 0) -> np.ndarray:
        """``images`` uint8 ``[B, H, W, 3]`` after every stage; AttackError if a stage returns anything but
        ``B`` uint8 RGB images, or if the attack is unavailable."""
        if self.unavailable:
            raise AttackError(f"attack {self.name} cannot run here: {self.unavailable}")
        out = A.check_images(images, f"the images given to {self.name}")
        for stage in self.stages:
            result = A.check_images(stage.run(out, seed), f"what {stage.name} returned")
            if len(result) != len(out):
                raise AttackError(f"{stage.name} returned {len(result)} images for {len(out)}")
            out = result
        return out


def numpy_attack(
    name: str, family: str, description: str, fn: Callable[..., np.ndarray], **params: Any
) -> Attack:
    """An attack of one stage: ``fn(images, stage_rng(seed, name), **params)`` (:mod:`imaging.attacks`)."""
    return Attack(
        name, family, description, (Stage(name, lambda x, seed: fn(x, stage_rng(seed, name), **params)),)
    )


def augmentation_attack(aug: str, strength: str, name: str | None = None) -> Attack:
    """The paper's augmentation ``aug`` at ``strength`` on 8-bit images (named ``aug@strength`` unless
    ``name``); its key is ``fold_in(PRNGKey(seed), index of aug)``, as ``mnerf attack`` has always drawn."""
    augment.resolve_names([aug], 1)  # an unknown name is refused
    if strength not in augment.STRENGTHS:
        raise AttackError(f"unknown attack strength {strength!r} (known: {', '.join(augment.STRENGTHS)})")
    index = augment.AUGMENTATION_NAMES.index(aug)
    name = name or f"{aug}@{strength}"

    def run(images: np.ndarray, seed: int) -> np.ndarray:
        key = jax.random.fold_in(jax.random.PRNGKey(seed), index)
        out = augment.apply(aug, key, images.astype(np.float32) / np.float32(255.0), strength)
        return A.to_uint8(np.asarray(out))

    params = ", ".join(f"{k} {v}" for k, v in augment.PARAMS[strength][aug].items())
    return Attack(name, "paper", f"the paper's {aug} at {strength} ({params})", (Stage(name, run),))


def compose(*attacks: Attack, family: str | None = None) -> Attack:
    """The attacks one after the other, named ``a+b+…``; each stage keeps its own draws."""
    return Attack(
        "+".join(a.name for a in attacks),
        family or attacks[0].family,
        "; then ".join(a.description for a in attacks),
        tuple(s for a in attacks for s in a.stages),
        next((a.unavailable for a in attacks if a.unavailable), None),
    )


# ------------------------------------------------------------------------------------------ the registry

JPEG_QUALITIES = (90, 70, 50, 30, 10)
WEBP_QUALITIES = (90, 70, 50, 30, 10)
CROP_AREAS = (0.8, 0.6, 0.4)
ROTATIONS = (5, 15, 30)
SCALES = (0.5, 0.75, 1.5)
TRANSLATIONS = (0.05, 0.1)
NOISE_SIGMAS = (0.01, 0.02, 0.05, 0.1)
NO_WEBP = None if A.WEBP_SUPPORTED else "this Pillow was built without WebP support"


def _pct(x: float) -> str:
    return f"{round(100 * x)}"


def _codecs() -> list[Attack]:
    rows = [
        numpy_attack(f"jpeg{q}", "codec", f"JPEG (Pillow/libjpeg) at quality {q}", A.jpeg, quality=q)
        for q in JPEG_QUALITIES
    ]
    webp = [
        numpy_attack(f"webp{q}", "codec", f"WebP (Pillow/libwebp) at quality {q}", A.webp, quality=q)
        for q in WEBP_QUALITIES
    ]
    return rows + [dataclasses.replace(a, unavailable=NO_WEBP) for a in webp]


def _geometric() -> list[Attack]:
    rows = []
    for where in ("centre", "random"):
        for area in CROP_AREAS:
            rows.append(
                numpy_attack(
                    f"crop_{where}{_pct(area)}",
                    "geometric",
                    f"{where} crop keeping {_pct(area)} % of the area, left at that size",
                    A.crop,
                    area=area,
                    random=where == "random",
                )
            )
    rows += [
        numpy_attack(
            f"rotate{d}",
            "geometric",
            f"rotation by ±{d}° (sign per image), black corners",
            A.rotate,
            degrees=d,
        )
        for d in ROTATIONS
    ]
    for scale in SCALES:
        rows.append(
            numpy_attack(
                f"rescale{_pct(scale)}_back",
                "geometric",
                f"rescaled to {_pct(scale)} % and back",
                A.rescale,
                scale=scale,
                back=True,
            )
        )
        rows.append(
            numpy_attack(
                f"rescale{_pct(scale)}",
                "geometric",
                f"rescaled to {_pct(scale)} %, left at that size",
                A.rescale,
                scale=scale,
            )
        )
    rows += [
        numpy_attack("flip_h", "geometric", "mirrored left-right", A.flip),
        numpy_attack("flip_v", "geometric", "mirrored upside down", A.flip, vertical=True),
    ]
    rows += [
        numpy_attack(
            f"translate{_pct(f)}",
            "geometric",
            f"shifted by {_pct(f)} % of each side (directions per image), black band",
            A.translate,
            fraction=f,
        )
        for f in TRANSLATIONS
    ]
    return rows


def _photometric() -> list[Attack]:
    def factor_rows(
        kind: str, fn: Callable[..., np.ndarray], what: str, factors: Sequence[float]
    ) -> list[Attack]:
        return [numpy_attack(f"{kind}{f:g}", "photometric", f"{what} × {f:g}", fn, factor=f) for f in factors]

    rows = factor_rows("brightness", A.brightness, "brightness (Pillow)", (0.6, 1.4))
    rows += factor_rows("contrast", A.contrast, "contrast (Pillow)", (0.6, 1.4))
    rows += factor_rows("saturation", A.saturation, "saturation (Pillow)", (0.5, 1.5))
    rows += [
        numpy_attack(f"hue{t:g}", "photometric", f"hue rotated by ±{t:g} turn", A.hue, turns=t)
        for t in (0.05, 0.1)
    ]
    rows += [numpy_attack(f"gamma{g:g}", "photometric", f"gamma {g:g}", A.gamma, gamma=g) for g in (0.7, 1.5)]
    rows.append(numpy_attack("greyscale", "photometric", "greyscale (ITU-R 601 luma)", A.greyscale))
    rows += [
        numpy_attack(
            f"gaussian_noise{s:g}",
            "photometric",
            f"Gaussian noise, σ = {s:g} of the range",
            A.gaussian_noise,
            sigma=s,
        )
        for s in NOISE_SIGMAS
    ]
    rows += [
        numpy_attack(
            f"salt_pepper{a:g}",
            "photometric",
            f"salt and pepper on {_pct(a)} % of the values",
            A.salt_and_pepper,
            amount=a,
        )
        for a in (0.01, 0.05)
    ]
    rows += [
        numpy_attack(
            f"gaussian_blur{s:g}", "photometric", f"Gaussian blur, σ = {s:g} px", A.gaussian_blur, sigma=s
        )
        for s in (1, 2)
    ]
    rows += [
        numpy_attack(f"median{k}", "photometric", f"median filter {k}×{k}", A.median_blur, size=k)
        for k in (3, 5)
    ]
    rows += [
        numpy_attack(
            f"motion_blur{n}",
            "photometric",
            f"motion blur over {n} px (direction per image)",
            A.motion_blur,
            length=n,
        )
        for n in (5, 9)
    ]
    return rows


def _regen() -> list[Attack]:
    return [
        numpy_attack("jpeg5", "regen", "JPEG at quality 5", A.jpeg, quality=5),
        dataclasses.replace(
            numpy_attack("webp5", "regen", "WebP at quality 5", A.webp, quality=5), unavailable=NO_WEBP
        ),
        numpy_attack(
            "rescale25_back", "regen", "rescaled to 25 % and back", A.rescale, scale=0.25, back=True
        ),
        numpy_attack(
            "denoise_tv0.1", "regen", "total-variation denoising, weight 0.1", A.denoise_tv, weight=0.1
        ),
        numpy_attack(
            "denoise_bilateral",
            "regen",
            "bilateral filter, σ colour 0.1, σ space 2 px",
            A.denoise_bilateral,
            sigma_color=0.1,
            sigma_spatial=2.0,
        ),
        numpy_attack("denoise_wavelet", "regen", "wavelet denoising (BayesShrink)", A.denoise_wavelet),
    ]


def _peers_only() -> list[Attack]:
    """The peers' rows no other suite has (CopyRNeRF / WateRF: Gaussian blur of deviation 0.1, brightness
    2.0 read as a factor)."""
    return [
        numpy_attack(
            "gaussian_blur0.1",
            "peers",
            "Gaussian blur, σ = 0.1 px (the peers' deviation)",
            A.gaussian_blur,
            sigma=0.1,
        ),
        numpy_attack(
            "brightness2", "peers", "brightness × 2 (the peers' 2.0, Pillow)", A.brightness, factor=2.0
        ),
    ]


def _paper() -> list[Attack]:
    singles = [augmentation_attack(a, s) for a in augment.AUGMENTATION_NAMES for s in augment.STRENGTHS]
    low = {a: augmentation_attack(a, "low") for a in augment.AUGMENTATION_NAMES}
    pairs = [compose(low[a], low[b]) for a, b in itertools.combinations(augment.AUGMENTATION_NAMES, 2)]
    return singles + pairs


def _registry() -> tuple[dict[str, Attack], dict[str, tuple[str, ...]]]:
    groups = {
        "codecs": _codecs(),
        "geometric": _geometric(),
        "photometric": _photometric(),
        "regen": _regen(),
    }
    paper = _paper()
    attacks = {a.name: a for rows in (*groups.values(), _peers_only(), paper) for a in rows}
    combined = compose(attacks["crop_random40"], attacks["brightness2"], attacks["jpeg10"], family="peers")
    attacks[combined.name] = combined
    suites = {name: tuple(a.name for a in rows) for name, rows in groups.items()}
    suites["peers"] = (
        "gaussian_noise0.1",
        "rotate30",
        "rescale75",
        "gaussian_blur0.1",
        "crop_random40",
        "jpeg50",
        "jpeg10",
        "brightness2",
        combined.name,
    )
    suites["paper"] = tuple(a.name for a in paper)
    suites["all"] = tuple(dict.fromkeys(n for rows in suites.values() for n in rows))
    return attacks, suites


ATTACKS, SUITES = _registry()
SUITE_NAMES: tuple[str, ...] = tuple(SUITES)


def suite(name: str) -> list[Attack]:
    """The attacks of suite ``name``, in order; AttackError for an unknown suite."""
    if name not in SUITES:
        raise AttackError(f"unknown attack suite {name!r} (known: {', '.join(SUITE_NAMES)})")
    return [ATTACKS[n] for n in SUITES[name]]


def resolve(names: Sequence[str], strength: str = "low") -> list[Attack]:
    """The attacks named: a registry name (``mnerf attack --list``), one of the 14 augmentation names at
    ``strength`` (named plainly, as ``--strength`` has always scored them), or ``a+b+…`` of those composed.
    AttackError for an unknown or repeated name."""
    out = []
    for name in names:
        parts = []
        for part in name.split("+"):
            if part in ATTACKS:
                parts.append(ATTACKS[part])
            elif part in augment.AUGMENTATION_NAMES:
                parts.append(augmentation_attack(part, strength, name=part))
            else:
                raise AttackError(
                    f"unknown attack {part!r}: `mnerf attack --list` names them "
                    f"(suites: {', '.join(SUITE_NAMES)})"
                )
        out.append(parts[0] if len(parts) == 1 else compose(*parts))
    repeated = sorted({a.name for a in out if [b.name for b in out].count(a.name) > 1})
    if repeated:
        raise AttackError(f"attacks named twice: {', '.join(repeated)}")
    return out


def listing() -> str:
    """Every suite and its attacks with their descriptions, as text (``mnerf attack --list``)."""
    lines = []
    for name in SUITE_NAMES:
        lines.append(
            f"{name} ({len(SUITES[name])} attacks)" + (": every attack above" if name == "all" else "")
        )
        if name == "all":
            continue
        for attack in suite(name):
            note = f"  [unavailable: {attack.unavailable}]" if attack.unavailable else ""
            lines.append(f"  {attack.name:<34} {attack.description}{note}")
    lines.append(
        "regen models (--codec-model ARCHITECTURE=WEIGHTS, CompressAI's weights): "
        + ", ".join(compression_models.ARCHITECTURES)
    )
    return "\n".join(lines)


# ------------------------------------------------------------------------ a user's regeneration model


def load_hook(spec: str) -> Callable[[np.ndarray], Any]:
    """The function ``spec`` names: ``module:function`` (an importable module, dotted) or
    ``path/to/file.py:function``; AttackError, in one line, for a bad spec or what cannot be imported."""
    module_name, sep, function = spec.rpartition(":")
    if not sep or not module_name or not function.isidentifier():
        raise AttackError(
            f"--regen takes MODULE:FUNCTION (e.g. mypkg.regen:diffuse or regen.py:diffuse), got {spec!r}"
        )
    try:
        if module_name.endswith(".py"):
            path = Path(module_name)
            if not path.is_file():
                raise AttackError(f"--regen {spec}: {path} does not exist")
            loader_spec = importlib.util.spec_from_file_location(f"mnerf_regen_{path.stem}", path)
            if loader_spec is None or loader_spec.loader is None:
                raise AttackError(f"--regen {spec}: {path} cannot be loaded as a Python module")
            module = importlib.util.module_from_spec(loader_spec)
            # Registered as imported modules are: dataclasses and pickling in it look their module up.
            sys.modules[loader_spec.name] = module
            loader_spec.loader.exec_module(module)
        else:
            module = importlib.import_module(module_name)
    except AttackError:
        raise
    except Exception as err:  # whatever the user's module raises on import
        raise AttackError(
            f"--regen {spec}: cannot import {module_name} ({type(err).__name__}: {err})"
        ) from None
    fn = getattr(module, function, None)
    if not callable(fn):
        raise AttackError(f"--regen {spec}: {module_name} has no function {function}")
    return fn


def hook_attack(spec: str) -> Attack:
    """An attack that calls the user's function ``spec`` (:func:`load_hook`) on a copy of each batch, uint8
    ``[B, H, W, 3]``; it must return ``B`` uint8 RGB images (any size of at least 4 px), else AttackError
    (one line; so is an exception raised inside it). Named ``regen:module:function`` (a file: its name
    without the folder)."""
    fn = load_hook(spec)
    module_name, _, function = spec.rpartition(":")
    name = f"regen:{Path(module_name).name if module_name.endswith('.py') else module_name}:{function}"

    def run(images: np.ndarray, seed: int) -> np.ndarray:
        del seed  # the user's model draws its own randomness
        try:
            out = fn(images.copy())
        except Exception as err:  # the user's model: any failure becomes one line
            raise AttackError(f"--regen {spec} raised {type(err).__name__}: {err}") from None
        out = A.check_images(out, f"--regen {spec}'s result (it must return uint8 [B, H, W, 3])")
        if len(out) != len(images):
            raise AttackError(f"--regen {spec} returned {len(out)} images for {len(images)}")
        return out

    return Attack(name, "hook", f"the user's regeneration function {spec}", (Stage(name, run),))


def codec_model_attack(spec: str) -> Attack:
    """A row for CompressAI's codec ``ARCHITECTURE=PATH`` (:mod:`imaging.compression_models`, weights the
    user supplies), named ``ARCHITECTURE-qN`` (``qN`` from CompressAI's file names, else the file's stem);
    deterministic (the seed is unused). AttackError in one line for a bad spec, file or weights."""
    architecture, sep, path = spec.partition("=")
    if not sep or not architecture or not path:
        raise AttackError(
            f"--codec-model takes ARCHITECTURE=PATH ({', '.join(compression_models.ARCHITECTURES)}), "
            f"got {spec!r}"
        )
    model = compression_models.load(architecture.strip(), Path(path))
    name = f"{model.architecture}-{compression_models.quality_label(path)}"
    description = (
        f"CompressAI {model.architecture} (N {model.n}, M {model.m}) from {Path(path).name}: "
        "its eval forward's x_hat, 8-bit"
    )
    return Attack(name, "regen", description, (Stage(name, lambda x, seed: model(x)),))
