"""Attacks on the model: what the holder of a watermarked field can do to its parameters before rendering
(``mnerf attack --model-suite``; :mod:`mnerf_jax.evaluation.model_attacks` renders and scores them).

Pure functions over a params pytree (a fitted or watermarked field, ``tensorf/field.py`` and
``watermark/model.py`` layouts):

- :func:`add_noise`: every float leaf plus Gaussian noise of ``strength`` times that leaf's own standard
  deviation (grids, basis, MLPs and the watermark module alike: one relative strength fits tensors of any
  scale), one key per leaf from the seed;
- :func:`quantise`: uniform per-tensor quantisation of the VM factors (every plane and line of every VM grid:
  density, appearance, the watermark grid) and the appearance basis to ``bits`` bits (``2^bits`` levels from
  the tensor's minimum to its maximum); the MLPs stay float, as a compressed field keeps them;
- :func:`prune`: in each VM grid, the rank-1 components of smallest norm (``‖plane_c‖·‖line_c‖``, the
  Frobenius norm of the component's outer product; ranked across the grid's three modes) set to zero;
- :func:`finetune_params`: the photometric fit continued on the training images (``tensorf.fit.finetune``)
  with the ID the attacker holds fixed (:func:`watermark.model.held_id_field_fns`): every parameter trains,
  the watermark grid, Emb and FiLM with the rest (at the fit's network rate), since an attacker who fits
  the field to the clean images has no reason to spare any of it.
"""

from __future__ import annotations

import dataclasses
import itertools
from collections.abc import Callable, Sequence
from typing import Any

import jax
import numpy as np

from mnerf_jax.core.errors import MnerfError
from mnerf_jax.tensorf import run as runs
from mnerf_jax.tensorf.fit import finetune
from mnerf_jax.watermark import model as watermark

Params = Any
Array = jax.Array

NOISE_STRENGTHS = (0.01, 0.05, 0.1)  # × each leaf's std
QUANT_BITS = (8, 4)
PRUNE_FRACTIONS = (0.1, 0.3)  # of each VM grid's components
FINETUNE_STEPS = (100, 500, 2000)
FAMILIES = ("noise", "quantise", "prune", "finetune")


class ModelAttackError(MnerfError):
    """A model attack that cannot be built (unknown suite, bad strength)."""


# ------------------------------------------------------------------------------------------ transforms


def add_noise(params: Params, strength: float, seed: int = 0) -> Params:
    """``params`` with every float leaf ``x`` replaced by ``x + strength · std(x) · N(0, 1)`` (leaf ``i`` of
    ``jax.tree.leaves`` draws from ``default_rng([seed, i])``); strength 0 returns the leaves unchanged.
    Host arrays out (numpy: no compilation per leaf shape)."""
    if strength < 0:
        raise ModelAttackError(f"noise strength must be ≥ 0, got {strength}")
    leaves, tree = jax.tree.flatten(params)
    out = []
    for i, leaf in enumerate(leaves):
        x = np.asarray(leaf)
        if strength == 0 or not np.issubdtype(x.dtype, np.floating) or x.size < 2:
            out.append(x)
            continue
        noise = np.random.default_rng([int(seed) % (1 << 63), i]).standard_normal(x.shape)
        out.append((x + strength * float(x.std()) * noise).astype(x.dtype))
    return jax.tree.unflatten(tree, out)


def quantise_array(x: Array | np.ndarray, bits: int) -> np.ndarray:
    """``x`` rounded to the nearest of ``2^bits`` evenly spaced levels from ``min(x)`` to ``max(x)`` (uniform
    per-tensor quantisation, dequantised): the error is at most half a step ``(max − min) / (2^bits − 1)``."""
    if not 1 <= int(bits) <= 16:
        raise ModelAttackError(f"quantisation needs 1 to 16 bits, got {bits}")
    x = np.asarray(x)
    lo, hi = float(x.min()), float(x.max())
    step = (hi - lo) / (2 ** int(bits) - 1)
    if step <= 0:
        return x.copy()
    return (lo + np.round((x.astype(np.float64) - lo) / step) * step).astype(x.dtype)


def is_vm_grid(node: Any) -> bool:
    """True for a VM grid ``{"planes": (3 arrays), "lines": (3 arrays)}`` (``tensorf/grids.py``)."""
    return isinstance(node, dict) and set(node) == {"planes", "lines"}


def map_vm_grids(params: Params, fn: Callable[[dict], dict]) -> Params:
    """``params`` with ``fn`` applied to every VM grid in it (nested dicts walked; new dicts)."""
    if is_vm_grid(params):
        return fn(params)
    if isinstance(params, dict):
        return {k: map_vm_grids(v, fn) for k, v in params.items()}
    return params


def quantise(params: Params, bits: int) -> Params:
    """Every VM factor (planes and lines of every VM grid) and the appearance ``basis`` quantised per tensor
    to ``bits`` bits (:func:`quantise_array`); the MLPs and the watermark's Emb / FiLM unchanged."""

    def grid_fn(grid: dict) -> dict:
        return {part: tuple(quantise_array(f, bits) for f in grid[part]) for part in ("planes", "lines")}

    out = map_vm_grids(params, grid_fn)
    if "basis" in out:
        out = {**out, "basis": quantise_array(out["basis"], bits)}
    return out


def component_norms(grid: dict) -> list[np.ndarray]:
    """Per mode ``m``, ``[C_m]``: ``‖P_m[..., c]‖ · ‖L_m[:, c]‖``, the Frobenius norm of component ``c``."""
    return [
        np.linalg.norm(np.asarray(p, np.float64), axis=(0, 1))
        * np.linalg.norm(np.asarray(l, np.float64), axis=0)
        for p, l in zip(grid["planes"], grid["lines"], strict=True)
    ]


def prune_grid(grid: dict, fraction: float) -> dict:
    """``grid`` with its ``round(fraction · ΣC_m)`` components of smallest norm (over all three modes; ties
    in mode order) set to zero in their plane and line; the others as they were."""
    if not 0.0 <= fraction <= 1.0:
        raise ModelAttackError(f"the pruned fraction must be in [0, 1], got {fraction}")
    norms = component_norms(grid)
    sizes = [int(n.shape[0]) for n in norms]
    count = int(round(fraction * sum(sizes)))
    drop = np.zeros(sum(sizes), bool)
    drop[np.argsort(np.concatenate(norms), kind="stable")[:count]] = True
    keep = np.split(~drop, list(itertools.accumulate(sizes))[:-1])
    return {
        part: tuple(
            np.asarray(f) * k.astype(np.asarray(f).dtype) for f, k in zip(grid[part], keep, strict=True)
        )
        for part in ("planes", "lines")
    }


def prune(params: Params, fraction: float) -> Params:
    """Every VM grid of ``params`` pruned by :func:`prune_grid` (each grid its own ranking)."""
    return map_vm_grids(params, lambda grid: prune_grid(grid, fraction))


# ------------------------------------------------------------------------------------------- fine-tuning


def finetune_params(
    run: runs.LoadedRun,
    scene: Any,
    steps: Sequence[int],
    held_id: int = 0,
    seed: int = 0,
    on_step: Callable[[int, dict[str, float]], None] | None = None,
) -> dict[int, Params]:
    """``{n: params}`` of a watermarked run's field fine-tuned for ``n`` steps of every ``steps`` (one
    trajectory) on ``scene``'s training images with the fit's loss, the field rendering ID ``held_id``
    (the copy the attacker holds); waterf, which has no IDs, trains as it renders."""
    cfg = run.config.watermark
    if watermark.uses_ids(cfg):
        index = int(held_id)
        if not 0 <= index < int(run.extras["num_ids"]):
            raise ModelAttackError(f"--finetune-id {held_id} is outside [0, {run.extras['num_ids']})")
        fns = watermark.held_id_field_fns(run.config.model, cfg, index)
    else:
        fns = run.field_fns
    return finetune.continue_fit(
        run.config, scene, run.params, run.geometry, fns, steps, seed=seed, on_step=on_step
    )


# ------------------------------------------------------------------------------------------ the registry


@dataclasses.dataclass(frozen=True)
class ModelAttack:
    """A named model attack: ``family`` (:data:`FAMILIES`), its ``value`` (noise: × each leaf's std;
    quantise: bits; prune: fraction of components; finetune: steps) and a one-line ``description``."""

    name: str
    family: str
    value: float
    description: str

    def apply(self, params: Params, seed: int = 0) -> Params:
        """The attacked params (noise, quantise, prune; for fine-tuning see :func:`finetune_params`)."""
        if self.family == "noise":
            return add_noise(params, self.value, seed)
        if self.family == "quantise":
            return quantise(params, int(self.value))
        if self.family == "prune":
            return prune(params, self.value)
        raise ModelAttackError(f"{self.name} fine-tunes the field: use finetune_params")


def _pct(x: float) -> str:
    return f"{round(100 * x)}"


def model_suite(name: str = "model", finetune_steps: Sequence[int] = FINETUNE_STEPS) -> list[ModelAttack]:
    """The attacks of model suite ``name``: ``model`` (all of them) or one family (:data:`FAMILIES`);
    ``finetune_steps``: the fine-tuning rows' step counts."""
    if name not in ("model", *FAMILIES):
        raise ModelAttackError(f"unknown model suite {name!r} (known: model, {', '.join(FAMILIES)})")
    steps = sorted({int(n) for n in finetune_steps})
    if any(n < 1 for n in steps):
        raise ModelAttackError(f"fine-tuning step counts must be ≥ 1, got {list(finetune_steps)}")
    rows = [
        ModelAttack(f"noise{_pct(s)}", "noise", s, f"Gaussian noise of {_pct(s)} % of each tensor's std")
        for s in NOISE_STRENGTHS
    ]
    rows += [
        ModelAttack(f"quant{b}", "quantise", b, f"VM factors and basis quantised per tensor to {b} bits")
        for b in QUANT_BITS
    ]
    rows += [
        ModelAttack(
            f"prune{_pct(f)}", "prune", f, f"the {_pct(f)} % smallest-norm components of each VM grid zeroed"
        )
        for f in PRUNE_FRACTIONS
    ]
    rows += [
        ModelAttack(f"finetune{n}", "finetune", n, f"{n} steps of the photometric fit on the training images")
        for n in steps
    ]
    return [a for a in rows if name == "model" or a.family == name]


def listing() -> str:
    """The model suites and their attacks, one per line (``mnerf attack --list``)."""
    rows = model_suite("model")
    lines = [f"--model-suite model ({len(rows)} attacks), or one family: {', '.join(FAMILIES)}"]
    lines += [f"  {a.name:<34} {a.description}" for a in rows]
    return "\n".join(lines)
