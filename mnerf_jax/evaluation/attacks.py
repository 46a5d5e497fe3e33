"""Robustness of a watermarked run: bit accuracy and identification of its evaluated renders under attack.

``mnerf evaluate`` saves every ID's render of every evaluated view as an 8-bit PNG
(``WMRUN/eval-<split>/id<K>/<view>.png``). This module reads those files back, applies each of the 14
augmentations of :mod:`mnerf_jax.imaging.augment` alone at one strength (Low / Medium / High, the paper's
policies; their random parameters drawn per image from a fixed seed), rounds the attacked images to 8 bits
again (what a verifier receives), decodes them with the run's decoder (and its read window) and scores them as
evaluation scores the renders themselves: mean and worst-ID bit accuracy, best-matching key right, and named
(the run's test and threshold). ``"none"`` is the PNGs as saved, the row ``eval-<split>.json`` reports as
``bit_accuracy_png_mean``. Writes ``WMRUN/eval-<split>-attacks.json``.

Reading saved files rather than rendering again keeps this cheap (no field is loaded) and scores exactly the
images the evaluation scored. The clean model's renders are not saved, so false detections under attack are
not measured here.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from mnerf_jax.core import rundir
from mnerf_jax.core.errors import MnerfError
from mnerf_jax.data.images import round_to_8bit
from mnerf_jax.evaluation import watermarked as wm_eval
from mnerf_jax.evaluation.plots import plt
from mnerf_jax.imaging import augment
from mnerf_jax.reader import extract, significance
from mnerf_jax.reader.identification import bit_accuracy, identify_logits, logits_to_bits
from mnerf_jax.tensorf import run as runs
from mnerf_jax.watermark import run as wm_run

NO_ATTACK = "none"


def saved_renders(run_dir: Path, split: str, views: int | None = None) -> tuple[dict[str, Any], np.ndarray]:
    """``(eval-<split>.json, renders [N, V, H, W, 3] float32)``: every ID's saved PNGs of the evaluated
    views, ``views`` of them evenly spread (None or 0: all). A clear error where the evaluation, or one of
    its files, is missing."""

    path = run_dir / f"eval-{split}.json"
    if not path.is_file():
        raise MnerfError(
            f"{run_dir} has no {path.name}: run `mnerf evaluate --run {run_dir} --split "
            f"{split}` first (it saves the renders this reads)"
        )
    try:
        result = json.loads(path.read_text())
    except json.JSONDecodeError as err:
        raise MnerfError(f"{path} is not valid JSON ({err}); evaluate again") from None
    names = list(result.get("view_names") or [])
    if not names:
        raise MnerfError(f"{path} lists no view names (written by an older mnerf evaluate); evaluate again")
    chosen = [names[i] for i in runs.view_indices(len(names), views)]
    folder = run_dir / f"eval-{split}"
    renders = []
    for n in range(int(result["num_ids"])):
        files = [folder / f"id{n}" / f"{name}.png" for name in chosen]
        missing = [str(f) for f in files if not f.is_file()]
        if missing:
            raise MnerfError(
                f"{len(missing)} saved render(s) of ID {n} are missing (first: {missing[0]}); "
                f"run `mnerf evaluate --run {run_dir} --split {split}` again"
            )
        renders.append(np.stack([extract.load_image(f) for f in files]))
    return result, np.stack(renders)


def attack(name: str, key: Any, images: np.ndarray, strength: str) -> np.ndarray:
    """``images [B, H, W, 3]`` after augmentation ``name`` (``"none"``: unchanged) at ``strength``."""

    if name == NO_ATTACK:
        return images
    return np.asarray(augment.AUGMENTATIONS[name](key, images, strength))


def score(logits: np.ndarray, messages: np.ndarray, threshold: float, test: str) -> dict[str, Any]:
    """Scores of attacked renders' ``logits [N, V, L]`` (ID n's renders in row n) against the keys
    ``messages [N, L]``: mean and worst-ID bit accuracy, best match right, named right."""

    n, v, bits = logits.shape
    per_id = bit_accuracy(logits_to_bits(logits), messages[:, None]).mean(axis=1)
    ident = identify_logits(logits.reshape(n * v, bits), messages, threshold, test)
    truth = np.repeat(np.arange(n), v)
    return {
        "bit_accuracy_mean": float(per_id.mean()),
        "bit_accuracy_min": float(per_id.min()),
        "bit_accuracy_per_id": per_id.tolist(),
        "identification_accuracy": float((ident.best_id == truth).mean()),
        "verified_identification_accuracy": float((ident.decision == truth).mean()),
    }


def evaluate_attacks(
    run_dir: str | Path,
    split: str = "test",
    strength: str = "low",
    names: Sequence[str] | None = None,
    views: int | None = None,
    seed: int = 0,
    progress: bool = False,
) -> dict[str, Any]:
    """Score a watermarked run's saved evaluation PNGs under each attack; writes and returns
    ``run_dir/eval-<split>-attacks.json``.

    ``names``: augmentations to apply (default all 14), each alone; ``"none"`` is always scored first.
    ``views``: evenly spread views of the evaluation's (None or 0: all). An attack draws its parameters from
    ``fold_in(PRNGKey(seed), its index in augment.AUGMENTATION_NAMES)``, the same for every ID (so the IDs
    meet the same attacks) and whichever other attacks are asked for.
    Keys: ``split``, ``strength``, ``views``, ``num_ids``, ``bits``, ``seed``, ``test``, ``threshold``,
    ``attacks`` ``{name: score(...)}`` in order, and ``mean_over_attacks`` (the 14 attacks' mean of each
    score, "none" left out).
    """
    import jax

    run_dir = Path(run_dir)
    if strength not in augment.STRENGTHS:
        raise MnerfError(f"unknown attack strength {strength!r} (known: {', '.join(augment.STRENGTHS)})")
    names = augment.resolve_names(names or None, 1)
    keys, decoder = wm_run.load_keys_and_decoder(run_dir)
    saved = rundir.read_run_config(run_dir).watermark
    threshold = float(saved.reading.id_threshold)
    test = significance.check_test(saved.reading.id_test)
    evaluation, renders = saved_renders(run_dir, split, views)
    messages = np.asarray(keys.messages, np.float32)
    if renders.shape[0] != messages.shape[0]:
        raise MnerfError(
            f"{run_dir}'s evaluation has {renders.shape[0]} IDs but its keys.json {messages.shape[0]}"
        )
    n, v = renders.shape[:2]
    base = jax.random.PRNGKey(seed)
    order = [NO_ATTACK, *names]
    bar = None
    if progress:
        bar = tqdm(total=len(order), unit="attack", desc=f"attacks ({strength})", dynamic_ncols=True)
    scores: dict[str, Any] = {}
    try:
        for name in order:
            # Keyed by the attack's place in the registry: the same draws whichever others are chosen.
            place = augment.AUGMENTATION_NAMES.index(name) if name != NO_ATTACK else 0
            key = jax.random.fold_in(base, place)
            # One ID at a time: the median filter's window stack is k² times the batch.
            attacked = np.concatenate([attack(name, key, renders[k], strength) for k in range(n)])
            attacked = round_to_8bit(attacked)  # a verifier gets 8 bits
            logits = wm_eval.decode_renders(decoder, saved, attacked, batch=32)
            scores[name] = score(logits.reshape(n, v, -1), messages, threshold, test)
            if bar is not None:
                bar.update(1)
                bar.set_postfix(attack=name, bits=f"{scores[name]['bit_accuracy_mean']:.3f}")
    finally:
        if bar is not None:
            bar.close()
    attacked_only = [s for name, s in scores.items() if name != NO_ATTACK]
    result = {
        "split": split,
        "strength": strength,
        "views": v,
        "num_ids": n,
        "bits": int(messages.shape[1]),
        "seed": seed,
        "test": test,
        "threshold": threshold,
        "step": evaluation.get("step"),
        "attacks": scores,
        "mean_over_attacks": {
            k: float(np.mean([s[k] for s in attacked_only]))
            for k in (
                "bit_accuracy_mean",
                "bit_accuracy_min",
                "identification_accuracy",
                "verified_identification_accuracy",
            )
        }
        if attacked_only
        else None,
    }
    rundir.write_json_atomic(run_dir / f"eval-{split}-attacks.json", result)
    return result


def attack_order(result: Mapping[str, Any]) -> list[str]:
    """The attacks of ``result`` in the order of :data:`augment.AUGMENTATION_NAMES`, ``"none"`` first (the
    JSON file keeps its keys sorted)."""

    rank = {name: i for i, name in enumerate((NO_ATTACK, *augment.AUGMENTATION_NAMES))}
    return sorted(result["attacks"], key=lambda name: rank.get(name, len(rank)))


def format_table(result: Mapping[str, Any]) -> str:
    """The attacks as a text table: bits mean / worst ID, best match, named."""
    lines = [
        f"{'attack (' + result['strength'] + ')':<16} {'bits':>8} {'worst ID':>9} {'best match':>11} "
        f"{'named':>8}"
    ]
    rows = [(name, result["attacks"][name]) for name in attack_order(result)]
    if result.get("mean_over_attacks"):
        rows.append(("mean of attacks", result["mean_over_attacks"]))
    for name, s in rows:
        named = s["verified_identification_accuracy"]
        lines.append(
            f"{name:<16} {s['bit_accuracy_mean']:>8.2%} {s['bit_accuracy_min']:>9.2%} "
            f"{s['identification_accuracy']:>11.2%} {named:>8.2%}"
        )
    return "\n".join(lines)


def attacks_plot(path: Path, results: Mapping[str, Mapping[str, Any]]) -> Path:
    """Bar plot of bit accuracy per attack, with the 50 % chance line: for one run (``{label: result}``) the
    mean over IDs and the worst ID, for several each run's mean over IDs side by side (the attacks of the
    first run, in :func:`attack_order`)."""

    first = next(iter(results.values()))
    names = attack_order(first)
    if len(results) == 1:
        bars = {
            "mean over IDs": [first["attacks"][k]["bit_accuracy_mean"] for k in names],
            "worst ID": [first["attacks"][k]["bit_accuracy_min"] for k in names],
        }
    else:
        bars = {
            label: [r["attacks"].get(k, {}).get("bit_accuracy_mean", np.nan) for k in names]
            for label, r in results.items()
        }
    x = np.arange(len(names))
    width = 0.8 / len(bars)
    fig, ax = plt.subplots(figsize=(0.55 * len(names) + 5.0, 3.6))
    for j, (label, values) in enumerate(bars.items()):
        ax.bar(x - 0.4 + width * (j + 0.5), np.asarray(values, float) * 100, width=width, label=label)
    ax.axhline(50.0, color="grey", linestyle="--", linewidth=1, label="chance")
    ax.set_xticks(x, names, rotation=45, ha="right", fontsize=8)
    ax.set_ylabel("bit accuracy (%)")
    ax.set_ylim(0, 100)
    title = f"{first['num_ids']} IDs x {first['views']} views, {first['strength']} attacks"
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.0, 1.0))
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
